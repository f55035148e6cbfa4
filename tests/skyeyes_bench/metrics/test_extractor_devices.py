"""The feature extractors on a device (issue 34), checked without a GPU.

Under `stray_device()` every tensor that project code makes without naming a device is made on
`meta`, while the data stays on the CPU: a tensor that would land on the CPU next to CUDA data
breaks here too. Each extractor, run inside it on the CPU, must give exactly the features it gives
outside it (same computation, every tensor where the data is), and no site may be reported.
The real networks are loaded outside the block (loading builds on the CPU and moves the network
once, by design); what runs inside is everything done per batch. GPU numerics: test_evaluate_gpu.py.
"""

import numpy as np
import pytest
from builders.devices import stray_device
from builders.weights import require

from skyeyes_bench import paths
from skyeyes_bench.metrics import cache, lpips
from skyeyes_bench.metrics.extractors import (
    RandomImage64, RandomVideo64, current_device, full_fp32, get_extractor, on_device)


def _images(n=3, size=40, seed=0):
    """float32 [n, size, size, 3] in [0, 1], 8-bit values (what frames read from PNGs hold)."""
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 256, (n, size, size, 3)) / 255.0).astype(np.float32)


def _clips(n=2, t=4, size=40, seed=0):
    """float32 [n, t, size, size, 3]: a texture panning one pixel per frame, 8-bit values."""
    base = _images(n, size, seed)
    return np.stack([np.stack([np.roll(b, k, axis=1) for k in range(t)]) for b in base])


def _inside(fn):
    """fn() inside stray_device: (result, the sites it moved to meta)."""
    with stray_device() as mode:
        out = fn()
    return out, mode.sites


# --------------------------------------------------------------------------- test-only extractors


@pytest.mark.parametrize("t", [4, 1])  # t=1: the motion half is made as zeros, on the data's device
def test_random_extractors_make_every_tensor_where_the_data_is(t):
    """random-image-64 / random-video-64 on the CPU, loaded and run inside stray_device: the
    same features to the bit, and no device-less tensor."""
    images, clips = _images(), _clips(t=t)
    want_i = get_extractor("random-image-64").features(images)
    want_v = get_extractor("random-video-64").features(clips)
    # fresh instances: the seeded network is drawn and moved inside the block too
    (got_i, got_v), sites = _inside(lambda: (RandomImage64().features(images, device="cpu"),
                                             RandomVideo64().features(clips)))
    assert sites == [], sites
    assert got_i.dtype == np.float64 and got_i.shape == (3, 64)
    assert got_v.dtype == np.float64 and got_v.shape == (2, 64)
    assert np.array_equal(got_i, want_i) and np.array_equal(got_v, want_v)


def test_features_through_the_cache_under_stray_device(tmp_path, monkeypatch):
    """The path evaluate takes (files -> cache -> extractor), cold cache, inside stray_device:
    the same features as outside it."""
    from skyeyes_bench.imagefiles import write_image

    frames = []
    for i, img in enumerate(_images(6)):
        frames.append(tmp_path / f"f{i}.png")
        write_image(frames[-1], img)
    clips = [frames[:4], frames[2:]]
    want_i = cache.extract_image_features("random-image-64", frames, batch_size=4, progress=False)
    want_v = cache.extract_clip_features("random-video-64", clips, progress=False)
    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path / "cold"))  # nothing cached: everything computed inside
    (got_i, got_v), sites = _inside(lambda: (
        cache.extract_image_features("random-image-64", frames, batch_size=4, progress=False, device="cpu"),
        cache.extract_clip_features("random-video-64", clips, progress=False)))
    assert cache.last_call["misses"] == 2
    assert sites == [], sites
    assert np.array_equal(got_i, want_i) and np.array_equal(got_v, want_v)


def test_cache_entries_are_kept_apart_per_device_type():
    """CPU entries keep the layout they had before devices (no suffix: old caches stay valid);
    another device type gets its own folder, so a CPU run is never served GPU features."""
    ex = get_extractor("random-image-64")
    key = "ab" + "0" * 62
    cpu, gpu = cache._entry(ex, key), cache._entry(ex, key, "cuda")
    assert cpu == paths.features_dir() / "random-image-64" / "noweights" / "ab" / f"{key}.f64"
    assert gpu == paths.features_dir() / "random-image-64" / "noweights-cuda" / "ab" / f"{key}.f64"


def test_on_device_sets_the_default_device_within_its_block():
    import torch

    assert current_device() == torch.device("cpu")  # the reference, when nobody asks
    with on_device(torch.device("meta")):
        assert current_device() == torch.device("meta")
        assert current_device("cpu") == torch.device("cpu")  # an explicit device wins
        with on_device("cpu"):
            assert current_device() == torch.device("cpu")
        assert current_device() == torch.device("meta")
    assert current_device() == torch.device("cpu")


def test_full_fp32_leaves_the_cpu_alone():
    import torch

    before = torch.backends.cudnn.conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision
    with full_fp32("cpu"):
        assert (torch.backends.cudnn.conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision) == before
    assert (torch.backends.cudnn.conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision) == before


# --------------------------------------------------------------------------- real weights


@pytest.mark.weights
def test_inception_under_stray_device():
    ex = get_extractor("inception-tf-2015")
    require(*ex.files)
    images = _images(2, size=32)  # resized to 299 by clean-fid's PIL bicubic, on the CPU
    want = ex.features(images)  # loads the network (outside: loading is CPU-then-move by design)
    got, sites = _inside(lambda: ex.features(images, device="cpu"))
    assert sites == [], sites
    assert got.shape == (2, 2048) and np.array_equal(got, want)


@pytest.mark.weights
def test_i3d_under_stray_device(one_torch_thread):
    ex = get_extractor("i3d-kinetics400")
    require(*ex.files)
    clips = _clips(1, t=16, size=32)  # one 16-frame clip, bilinear-resized to 224 on the CPU
    want = ex.features(clips)
    got, sites = _inside(lambda: ex.features(clips, device="cpu"))
    assert sites == [], sites
    assert got.shape == (1, 400) and np.array_equal(got, want)


@pytest.mark.weights
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_under_stray_device(net):
    ex = get_extractor(f"lpips-{net}-v0.1")
    require(*ex.files)
    a, b = _images(2, size=48, seed=1), _images(2, size=48, seed=2)
    want, want_map = lpips(a, b, net=net), ex.distance_map(a, b)
    with on_device("cpu"):  # the route evaluate takes: the device from on_device, none passed
        (got, got_map), sites = _inside(lambda: (lpips(a, b, net=net), ex.distance_map(a, b)))
    assert sites == [], sites
    assert got.shape == (2,) and np.array_equal(got, want)
    assert got_map.shape == (2, 48, 48) and np.array_equal(got_map, want_map)
