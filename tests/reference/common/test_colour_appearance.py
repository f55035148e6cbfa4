"""The learned appearance (`reference/common/appearance.py`) against closed forms."""

import numpy as np
import pytest

from reference.common.appearance import AppearanceFit, Backgrounds, ColourMap, above_horizon, quadratic_features
from skyeyes_bench.cameras import Camera


def test_colour_map_recovers_a_known_quadratic_map():
    rng = np.random.default_rng(0)
    coef = np.vstack([np.eye(3)[[0]] * 0.05, 0.6 * np.eye(3), rng.normal(0, 0.05, (6, 3))])
    x = rng.random((5000, 3))
    y = np.stack([1.0 + 0 * x[:, 0], *x.T, *(x.T ** 2), x[:, 0] * x[:, 1], x[:, 0] * x[:, 2], x[:, 1] * x[:, 2]], 1) @ coef
    got = ColourMap.fit(x, y, ridge=1e-9)
    np.testing.assert_allclose(got.coef, coef, atol=1e-4)
    np.testing.assert_allclose(got(x[:10]), np.clip(y[:10], 0, 1), atol=1e-4)


def test_features_are_the_ten_quadratic_monomials():
    c = np.array([[0.2, 0.3, 0.5]])
    np.testing.assert_allclose(quadratic_features(c)[0], [1, .2, .3, .5, .04, .09, .25, .06, .1, .15])


def test_too_few_pixels_or_a_strong_ridge_give_the_identity():
    ident = ColourMap()
    x = np.random.default_rng(1).random((5, 3))
    np.testing.assert_array_equal(ColourMap.fit(x, 1 - x).coef, ident.coef)
    np.testing.assert_array_equal(ColourMap.fit(np.zeros((0, 3)), np.zeros((0, 3))).coef, ident.coef)
    x = np.random.default_rng(2).random((500, 3))
    strong = ColourMap.fit(x, 1 - x, ridge=1e6)
    np.testing.assert_allclose(strong.coef, ident.coef, atol=1e-3)
    np.testing.assert_allclose(ident(x), x.astype(np.float32), atol=1e-7)


def test_output_is_clipped_and_round_trips():
    m = ColourMap(np.vstack([np.full((1, 3), 0.8), 2 * np.eye(3), np.zeros((6, 3))]))
    out = m(np.array([[0.0, 0.5, 1.0]]))
    np.testing.assert_allclose(out, [[0.8, 1.0, 1.0]])
    assert out.dtype == np.float32
    back = ColourMap.from_dict(m.to_dict())
    np.testing.assert_array_equal(back.coef, m.coef)
    with pytest.raises(ValueError, match=r"\(10, 3\)"):
        ColourMap.from_dict({"coef": [[0.0] * 3] * 9})


def test_above_horizon_level_and_pitched_down():
    level = Camera.from_ypr([0, 0, 2.0], 30.0, 0.0, fov_deg=90, width=8, height=6)
    up = above_horizon(level)
    want = np.zeros((6, 8), bool)
    want[:3] = True  # rows whose centre lies above cy = 3 (v + 0.5 < 3)
    np.testing.assert_array_equal(up, want)
    down = Camera.from_ypr([0, 0, 50.0], 0.0, -60.0, fov_deg=90, width=8, height=8)
    assert not above_horizon(down).any()
    b = Backgrounds(np.array([0.1, 0.2, 0.3], np.float32), np.array([0.7, 0.6, 0.5], np.float32))
    img = b.image(level)
    np.testing.assert_array_equal(img[:3], np.broadcast_to(b.sky, (3, 8, 3)))
    np.testing.assert_array_equal(img[3:], np.broadcast_to(b.ground, (3, 8, 3)))
    rt = Backgrounds.from_dict(b.to_dict())
    np.testing.assert_array_equal(rt.sky, b.sky)


def test_appearance_fit_backgrounds_are_means_over_uncovered_pixels():
    rng = np.random.default_rng(3)
    cam = Camera.from_ypr([0, 0, 2.0], 0.0, 0.0, fov_deg=90, width=10, height=8)
    acc = AppearanceFit(covered=0.5)
    up = above_horizon(cam)
    truths, alphas = [], []
    for _ in range(3):
        truth = rng.random((8, 10, 3)).astype(np.float32)
        alpha = rng.random((8, 10)).astype(np.float32)
        render = np.clip(truth * 0.5 + 0.3, 0, 1)
        acc.add(render, alpha, truth, cam)
        truths.append(truth)
        alphas.append(alpha)
    t, a = np.stack(truths), np.stack(alphas)
    cmap, bg = acc.result(np.zeros(3), np.zeros(3))
    unc = a < 0.5
    np.testing.assert_allclose(bg.sky, t[unc & up[None]].mean(0), rtol=1e-5)
    np.testing.assert_allclose(bg.ground, t[unc & ~up[None]].mean(0), rtol=1e-5)
    # The colour map inverts render = 0.5 truth + 0.3 on the covered pixels (up to the ridge's
    # small pull towards the identity, whose own error here is |0.3 - 0.5 truth|, 0.15 on average).
    cov = ~unc
    err = np.abs(cmap(np.clip(t[cov] * 0.5 + 0.3, 0, 1)) - t[cov])
    assert err.mean() < 0.02 and err.max() < 0.06
    # Nothing uncovered: the defaults.
    full = AppearanceFit()
    full.add(t[0], np.ones((8, 10), np.float32), t[0], cam)
    _, bg2 = full.result(np.array([0.1, 0.1, 0.1]), np.array([0.9, 0.9, 0.9]))
    np.testing.assert_allclose(bg2.sky, 0.1)
    np.testing.assert_allclose(bg2.ground, 0.9)
