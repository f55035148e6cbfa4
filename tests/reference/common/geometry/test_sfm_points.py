"""SfM is actually taken where it should work: overlapping 256 px SynthTown aerial views (10 deg
apart around one target, as a drone orbit) triangulate points, and those points lie on the
surfaces the renderer hit (its depth buffer is the independent oracle)."""

import logging

import numpy as np
import pytest

from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.data.synthtown import town as tw
from skyeyes_bench.data.synthtown.render import Scene, render
from skyeyes_bench.data.writer import DatasetWriter

SIZE = 256


def _orbit_views(n=6, step_deg=10.0):
    town = tw.make_town("test-0", 0, (3, 3))
    scene = Scene.from_town(town)
    lane = tw.make_lanes(town, 1, 16, 2.0, 0)[0]
    h = lane["heading_deg"]
    tx = lane["start"][0] + 16 * np.cos(np.deg2rad(h))
    ty = lane["start"][1] + 16 * np.sin(np.deg2rad(h))
    cams = []
    for i in range(n):
        a = np.deg2rad(h + i * step_deg)
        cams.append(Camera.from_ypr([tx - 40 * np.cos(a), ty - 40 * np.sin(a), 40.0], h + i * step_deg, -45.0,
                                    fov_deg=60, width=SIZE, height=SIZE))
    return cams, [render(scene, c, aa=1)[:2] for c in cams]


@pytest.mark.slow  # ~4 s of CPU (SIFT, matching, triangulation), ~9 s wall under load
def test_sfm_triangulates_overlapping_aerial_views_onto_the_rendered_surfaces(tmp_path, caplog):
    from reference.common.geometry import sfm

    cams, renders = _orbit_views()
    K = cams[0].K
    intr = {"width": SIZE, "height": SIZE, "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2])}
    with DatasetWriter(tmp_path / "ds", name="sfm", protocol="synthtown@1") as w:
        s = w.scene("test-0-lane00", {"ground": intr, "aerial": intr})
        for c, (rgb, _) in zip(cams, renders):
            s.add_aerial(rgb, c.c2w)
        s.add_ground(renders[0][0], cams[0].c2w, sequence="yaw000", index=0)
        s.close()
        w.finish(splits={"train": [], "test": ["test-0-lane00"]})
    frames = list(open_dataset(tmp_path / "ds").split("test")[0].aerial)
    with caplog.at_level(logging.WARNING):
        xyz, rgb, msg = sfm.sfm_points(frames, tmp_path / "sfm")
    assert not caplog.records, [r.getMessage() for r in caplog.records]  # no fallback, no failure
    assert msg.startswith("SfM:") and len(xyz) >= 50, msg  # 150 measured here
    assert rgb.shape == xyz.shape and 0 <= rgb.min() and rgb.max() <= 1
    # Each point, projected into each view that sees it, lies at the depth the renderer hit there.
    rel = []
    for c, (_, depth) in zip(cams, renders):
        uv, z = c.project(xyz)
        seen = (z > 0) & (uv >= 0).all(1) & (uv < SIZE).all(1)
        hit = depth[uv[seen, 1].astype(int), uv[seen, 0].astype(int)]
        rel.append(np.abs(z[seen] - hit) / hit)
    rel = np.concatenate(rel)
    assert len(rel) >= 3 * 50 and np.median(rel) < 0.02 and np.mean(rel < 0.05) > 0.7, (np.median(rel), np.mean(rel < 0.05))
