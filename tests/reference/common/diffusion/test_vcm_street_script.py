"""bench/vcm_street.py (docs/skyeyes.md, "The street from one view"): its settings, and that a
setting applies the anchor, then the street, then the sky, as the pipeline does."""

from __future__ import annotations

import types

import numpy as np
import pytest
from builders.bench_scripts import load_bench

from reference.common.diffusion import warp


@pytest.fixture(scope="module")
def vs():
    return load_bench("vcm_street")


def test_settings_parse_to_what_they_name(vs):
    assert vs.parse("0.5:0") == (0.5, 0.0, warp.STREET_VIEW_M, 0.0)
    assert vs.parse("0.65:0.8:6") == (0.65, 0.8, 6.0, 0.0)
    assert vs.parse("0.5:0.8:4:0.7") == (0.5, 0.8, 4.0, 0.7)
    for bad in ("0.5", "1.5:0", "0.5:2", "0.5:0.5:4:1.5", "0.5:0.5:4:1:1"):
        with pytest.raises(SystemExit, match="expected"):
            vs.parse(bad)


def test_a_setting_is_the_anchor_then_the_street_then_the_sky(vs, monkeypatch):
    """With the anchor, the street and the sky on, the frames go through `warp.prior_anchor` (the
    preset's sigma and tiles), then `warp.street_transfer` (the setting's mix and view), then
    `warp.sky_fit` (its mix); 0 skips each."""
    calls = []
    monkeypatch.setattr(warp, "prior_anchor", lambda x, r, sigma, mix, tiles: calls.append(("anchor", sigma, mix, tiles)) or x + 1)
    monkeypatch.setattr(warp, "street_transfer", lambda x, cams, depths, zg, *, mix, view_m:
                        calls.append(("street", len(cams), zg, mix, view_m)) or x * 2)
    monkeypatch.setattr(warp, "sky_fit", lambda x, cams, depths, *, mix: calls.append(("sky", len(depths), mix)) or x - 3)
    monkeypatch.setattr(warp, "prior_depth", lambda prior, scene, f, w, h: np.zeros((h, w)))
    monkeypatch.setattr(warp, "scaled_camera", lambda cam, w, h: cam)
    monkeypatch.setattr(warp, "prior_ground", lambda prior, scene: 0.25)
    monkeypatch.setattr(vs, "_guides", lambda priors, h, w: np.zeros((len(priors), h, w, 3), np.float32))
    monkeypatch.setattr(vs, "frame_key", lambda scene, f: id(f))
    frames = [types.SimpleNamespace(camera=lambda: None) for _ in range(3)]
    parts = vs.Sequences.__new__(vs.Sequences)
    parts.m = types.SimpleNamespace(scene_model=lambda s: {id(f): None for f in frames},
                                    prior=types.SimpleNamespace(fit_scene=lambda s: None))
    parts.zg, parts.geometry = {}, {}
    scene, q = types.SimpleNamespace(name="s"), types.SimpleNamespace(frames=frames, id="q")
    raw = np.full((3, 4, 4, 3), 0.25, np.float32)
    out = parts.apply((0.6, 0.8, 4.0, 0.0), scene, q, raw)
    assert calls == [("anchor", 3.0, 0.6, 4), ("street", 3, 0.25, 0.8, 4.0)]
    np.testing.assert_allclose(out, (raw + 1) * 2)
    calls.clear()
    out = parts.apply((0.6, 0.8, 4.0, 0.7), scene, q, raw)
    assert calls == [("anchor", 3.0, 0.6, 4), ("street", 3, 0.25, 0.8, 4.0), ("sky", 3, 0.7)]
    np.testing.assert_allclose(out, (raw + 1) * 2 - 3)
    calls.clear()
    np.testing.assert_allclose(parts.apply((0.0, 0.0, 4.0, 0.5), scene, q, raw), raw - 3)
    assert calls == [("sky", 3, 0.5)]
    calls.clear()
    np.testing.assert_allclose(parts.apply((0.0, 0.0, 4.0, 0.0), scene, q, raw), raw)
    assert calls == []
