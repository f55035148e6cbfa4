"""Feature cache: keyed by content, second call extracts nothing, corruption detected and recomputed."""

import numpy as np
import pytest

from skyeyes_bench import paths
from skyeyes_bench.imagefiles import read_image, write_image
from skyeyes_bench.metrics import cache
from skyeyes_bench.metrics.extractors import get_extractor


@pytest.fixture
def frames(tmp_path):
    rng = np.random.default_rng(0)
    out = []
    for i in range(6):
        p = tmp_path / f"f{i}.png"
        write_image(p, rng.random((24, 32, 3)))
        out.append(p)
    return out


def test_image_features_cached_and_equal_direct(frames, monkeypatch):
    direct = get_extractor("random-image-64").features(np.stack([read_image(p) for p in frames]))
    a = cache.extract_image_features("random-image-64", frames, batch_size=4, progress=False)
    assert cache.last_call == {"hits": 0, "misses": 6, "corrupt": 0}
    assert np.allclose(a, direct, rtol=1e-6, atol=1e-7)
    ex = get_extractor("random-image-64")
    monkeypatch.setattr(type(ex), "features", lambda self, x: pytest.fail("extracted again"))
    b = cache.extract_image_features("random-image-64", frames[::-1], progress=False)
    assert cache.last_call["hits"] == 6 and cache.last_call["misses"] == 0
    assert np.array_equal(b, a[::-1])


def test_cache_key_is_content_not_path(frames, tmp_path):
    cache.extract_image_features("random-image-64", frames[:2], progress=False)
    copy = tmp_path / "elsewhere.png"
    copy.write_bytes(frames[0].read_bytes())
    cache.extract_image_features("random-image-64", [copy], progress=False)
    assert cache.last_call["hits"] == 1
    # different content -> miss
    write_image(frames[1], np.zeros((24, 32, 3)))
    cache.extract_image_features("random-image-64", [frames[1]], progress=False)
    assert cache.last_call["misses"] == 1


@pytest.mark.parametrize("damage", ["truncate", "flip", "empty"])
def test_corrupted_entry_detected_and_recomputed(frames, damage):
    a = cache.extract_image_features("random-image-64", frames, progress=False)
    entries = sorted((paths.features_dir() / "random-image-64").rglob("*.f64"))
    assert len(entries) == 6
    e = entries[0]
    data = bytearray(e.read_bytes())
    if damage == "truncate":
        e.write_bytes(bytes(data[:-5]))
    elif damage == "flip":
        data[3] ^= 0xFF
        e.write_bytes(bytes(data))
    else:
        e.write_bytes(b"")
    b = cache.extract_image_features("random-image-64", frames, progress=False)
    assert cache.last_call == {"hits": 5, "misses": 1, "corrupt": 1}
    assert np.array_equal(a, b)
    cache.extract_image_features("random-image-64", frames, progress=False)
    assert cache.last_call["hits"] == 6  # repaired


def test_clip_features_keyed_by_ordered_members(frames):
    clips = [frames[0:3], frames[3:6]]
    a = cache.extract_clip_features("random-video-64", clips, batch_size=1, progress=False)
    direct = get_extractor("random-video-64").features(np.stack([[read_image(p) for p in c] for c in clips]))
    assert np.allclose(a, direct, rtol=1e-6, atol=1e-7)
    cache.extract_clip_features("random-video-64", clips, progress=False)
    assert cache.last_call["hits"] == 2
    cache.extract_clip_features("random-video-64", [frames[0:3][::-1]], progress=False)
    assert cache.last_call["misses"] == 1  # order matters


def test_wrong_kind_rejected(frames):
    with pytest.raises(ValueError):
        cache.extract_image_features("random-video-64", frames, progress=False)


def test_mixed_sizes_in_one_batch(tmp_path):
    rng = np.random.default_rng(1)
    ps = []
    for i, shape in enumerate([(16, 16, 3), (20, 24, 3), (16, 16, 3)]):
        p = tmp_path / f"m{i}.png"
        write_image(p, rng.random(shape))
        ps.append(p)
    got = cache.extract_image_features("random-image-64", ps, progress=False)
    ex = get_extractor("random-image-64")
    for p, g in zip(ps, got):
        assert np.allclose(g, ex.features(read_image(p)[None])[0], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("damage", ["delete", "flip"])
def test_warm_cache_needs_verified_weights(frames, monkeypatch, damage):
    """Issue 14: with the weight file deleted or one byte flipped, cached features must not be
    served; the metric is unavailable with the fixing command."""
    import hashlib

    from skyeyes_bench.metrics import extractors as E
    from skyeyes_bench.metrics import weights as W

    blob = bytes(range(256)) * 8
    wdir = paths.weights_dir()
    wdir.mkdir(parents=True, exist_ok=True)
    (wdir / "fake-weights.bin").write_bytes(blob)
    monkeypatch.setitem(W.WEIGHT_FILES, "fake-weights.bin", W.WeightFile(
        "fake-weights.bin", hashlib.sha256(blob).hexdigest(), note="test"))

    class Weighted(E.RandomImage64):  # random features, but guarded by a real weight file
        id, files = "weighted-image-64", ("fake-weights.bin",)
        weights_sha256 = E.Extractor.weights_sha256
        status = E.Extractor.status

    monkeypatch.setitem(E.EXTRACTORS, Weighted.id, Weighted)
    monkeypatch.delitem(E._INSTANCES, Weighted.id, raising=False)
    cache.extract_image_features(Weighted.id, frames, progress=False)
    cache.extract_image_features(Weighted.id, frames, progress=False)
    assert cache.last_call["hits"] == len(frames)  # warm
    p = wdir / "fake-weights.bin"
    if damage == "delete":
        p.unlink()
    else:
        p.write_bytes(bytes([blob[0] ^ 1]) + blob[1:])  # one bit, same size
    with pytest.raises(W.MetricUnavailable, match="weighted-image-64 unavailable: weights (missing|mismatch).*fix: "):
        cache.extract_image_features(Weighted.id, frames, progress=False)
