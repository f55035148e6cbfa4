"""Region metrics (skyeyes_bench.metrics.regions), the SSIM and LPIPS maps they average, the mask
cache, and the pooling of pixel-weighted values (stats) against independent computations."""

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from skyeyes_bench import stats
from skyeyes_bench.metrics import image, regions
from skyeyes_bench.metrics.lpips_net import LPIPSNet


def _pair(seed, shape=(3, 24, 20, 3)):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    return a, np.clip(a + 0.1 * rng.normal(size=shape), 0, 1)


def test_region_psnr_by_hand_and_empty_regions():
    a, b = _pair(0)
    masks = np.zeros(a.shape[:3], bool)
    masks[0, :5] = True
    masks[1] = True
    v, n = regions.psnr(a, b, masks)
    assert n.tolist() == [100, 480, 0]
    mse0 = ((a[0, :5] - b[0, :5]) ** 2).mean()
    assert v[0] == pytest.approx(-10 * np.log10(mse0), rel=1e-12)
    assert v[1] == pytest.approx(image.psnr(a[1], b[1]), rel=1e-12)
    assert np.isnan(v[2])
    same, _ = regions.psnr(a, a, masks)
    assert np.isposinf(same[:2]).all()


def test_ssim_map_is_skimages_map_and_region_mean_uses_window_centres():
    a, b = _pair(1, (2, 32, 28, 3))
    for i in range(2):
        _, full = structural_similarity(a[i], b[i], gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1, channel_axis=-1, full=True)
        ours = image.ssim_map(a[i], b[i])
        assert ours == pytest.approx(full[5:-5, 5:-5], abs=1e-10)  # skimage crops r = 5 for its mean
    masks = np.zeros(a.shape[:3], bool)
    masks[:, :, :14] = True  # left half: window centres in columns 5..13 (rows 5..26)
    v, n = regions.ssim(a, b, masks)
    assert n.tolist() == [22 * 9] * 2
    m = image.ssim_map(a, b).mean(-1)
    assert v == pytest.approx(m[:, :, :9].mean(axis=(1, 2)), rel=1e-12)
    everywhere, _ = regions.ssim(a, b, np.ones_like(masks))
    assert everywhere == pytest.approx(image.ssim(a, b), rel=1e-12)


def _random_net(net: str) -> LPIPSNet:
    torch.manual_seed(0)
    m = LPIPSNet(net)
    for lin in m.lins:  # the heads are non-negative in lpips v0.1
        lin.weight.data.abs_()
    return m.eval()


def test_lpips_spatial_map_mean_is_the_distance_for_integer_upsampling(one_torch_thread):
    # VGG16's taps are at 1, 1/2, 1/4, 1/8, 1/16 of a 32x32 input: bilinear upsampling with
    # align_corners=False by an integer factor gives every input sample the same total weight,
    # so the map's mean is exactly the spatially averaged distance (AlexNet's sizes do not divide).
    net = _random_net("vgg")
    x0, x1 = torch.rand(2, 3, 32, 32) * 2 - 1, torch.rand(2, 3, 32, 32) * 2 - 1
    with torch.inference_mode():
        d = net(x0, x1)
        m = net(x0, x1, spatial=True)
    assert m.shape == (2, 32, 32)
    assert m.mean(dim=(1, 2)) == pytest.approx(d, rel=1e-5)


def test_lpips_spatial_map_locates_the_difference(one_torch_thread):
    net = _random_net("alex")
    x0 = torch.rand(1, 3, 96, 96) * 2 - 1
    x1 = x0.clone()
    x1[..., :, 64:] = torch.rand(1, 3, 96, 32) * 2 - 1  # only the right third differs
    with torch.inference_mode():
        m = net(x0, x1, spatial=True)[0]
        d = net(x0, x1)[0]
    assert m[:, 72:].mean() > 5 * m[:, :40].mean()
    assert float(m.mean()) == pytest.approx(float(d), rel=0.15)  # close, not equal (borders)


def test_masked_mean_empty_and_full():
    maps = np.arange(24, dtype=float).reshape(2, 3, 4)
    masks = np.zeros((2, 3, 4), bool)
    masks[0, 0] = True
    v, n = regions.masked_mean(maps, masks)
    assert v[0] == pytest.approx(1.5) and np.isnan(v[1]) and n.tolist() == [4, 0]


def test_pooled_values_and_resamples():
    # two clusters; frame values with pixel weights; NaN values (empty regions) carry weight 0
    v = np.array([20.0, 30.0, np.nan, np.inf, 10.0])
    w = np.array([10, 30, 0, 5, 0], dtype=float)  # the last frame: value but no pixels -> left out
    cl = np.array([0, 0, 0, 1, 1])
    mse = (10 * 0.01 + 30 * 0.001 + 5 * 0.0) / 45
    assert stats.pooled_value(v, w, "mse") == pytest.approx(-10 * np.log10(mse), rel=1e-12)
    assert stats.pooled_value(v[:2], w[:2], "mean") == pytest.approx((200 + 900) / 40)
    reps = stats.frame_metric_samples(v, cl, np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]), w, "mse")
    assert reps[0] == pytest.approx(-10 * np.log10((0.1 + 0.03) / 40), rel=1e-12)
    assert np.isposinf(reps[1])  # every pixel of cluster 1 exact
    assert reps[2] == pytest.approx(stats.pooled_value(v, w, "mse"))
    none = stats.frame_metric_samples(v, cl, np.array([[0.0, 0.0]]), w, "mean")
    assert np.isnan(none[0])
    # without weights: the old mean of per-frame values
    assert stats.frame_metric_samples(np.array([1.0, 3.0]), np.array([0, 0]), np.ones((1, 1)))[0] == 2.0


def test_mask_cache_hits_and_detects_damage(tmp_path, synthtown_smoke):
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.metrics import geometry, masks

    ds = open_dataset(synthtown_smoke)
    scene = ds.split("test")[0]
    seq = next(iter(scene.sequences.values()))
    fs = list(seq.frames[:3])
    got = masks.seen_masks(scene, fs, 0.01)
    assert masks.last_call == {"hits": 0, "misses": 3, "corrupt": 0}
    ref = geometry.seen_mask(fs[1].depth(), fs[1].camera(), np.stack([a.depth() for a in scene.aerial]),
                             [a.camera() for a in scene.aerial], 0.01)
    assert (got[1] == ref).all() and 0 < got.mean() < 1
    again = masks.seen_masks(scene, fs, 0.01)
    assert masks.last_call == {"hits": 3, "misses": 0, "corrupt": 0} and (again == got).all()
    entry = next(masks.masks_dir().rglob("*.bits"))
    entry.write_bytes(entry.read_bytes()[:-1] + b"x")
    assert (masks.seen_masks(scene, fs, 0.01) == got).all() and masks.last_call["corrupt"] == 1
    masks.seen_masks(scene, fs, 0.02)  # another tolerance: other entries
    assert masks.last_call == {"hits": 0, "misses": 3, "corrupt": 0}  # each call counts afresh
