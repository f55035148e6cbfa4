"""With the real extractor weights (CI runs `skyeyes-bench weights fetch` first): Inception matches
the TorchScript module called with clean-fid's preprocessing written out here; FID / FVD of a
set against itself is 0; FID rises with blur."""

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.ndimage import gaussian_filter
from skimage import data as skdata

from skyeyes_bench import paths
from skyeyes_bench.metrics import FeatureStats, frechet_distance, weights as W
from skyeyes_bench.metrics.extractors import get_extractor

# Resolved at collection, before the per-test cache isolation: where `weights fetch` put them.
REAL_DIR = paths.weights_dir()
INCEPTION = "inception-2015-12-05-fid-helper-default_1.pt"
I3D = "i3d-kinetics-400.ckpt"


def _have(name):
    p = REAL_DIR / name
    return p.is_file() and W.sha256_file(p) == W.WEIGHT_FILES[name].sha256


HAVE_INCEPTION, HAVE_I3D = _have(INCEPTION), _have(I3D)
pytestmark = pytest.mark.weights


@pytest.fixture(autouse=True)
def _link_real_weights():
    d = paths.weights_dir()
    d.mkdir(parents=True, exist_ok=True)
    for name in (INCEPTION, I3D):
        if (REAL_DIR / name).is_file() and not (d / name).exists():
            (d / name).symlink_to(REAL_DIR / name)


needs_inception = pytest.mark.skipif(not HAVE_INCEPTION, reason=f"{INCEPTION} absent from {REAL_DIR}: "
                                     "run `skyeyes-bench weights fetch`")
needs_i3d = pytest.mark.skipif(not HAVE_I3D, reason=f"{I3D} absent from {REAL_DIR}: run `skyeyes-bench weights fetch`")


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
