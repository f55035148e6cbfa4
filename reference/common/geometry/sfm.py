"""Sparse points for a scene: SfM triangulation with the known aerial poses (pycolmap), and the
documented fallback when neither SfM nor MVS (`mvs.py`) yields enough points.

Fallback ("ground-plane rays"): for a grid of pixels of every aerial view, the ray is cut with
the ground plane z = 0 and the point is lifted to a random height in [0, max_height] along
the same ray (so it still projects to that pixel); colour is the pixel's. It needs nothing but
the poses and images, and the training moves the points to the surfaces.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from skyeyes_bench.data.layout import Frame

log = logging.getLogger(__name__)

#: pycolmap's rigs and frames API (Reconstruction.add_camera_with_trivial_rig,
#: add_image_with_trivial_frame) first appears in pycolmap 4.0 (COLMAP's src/pycolmap/scene/
#: reconstruction.cc at tag 4.0.0; absent at 3.13.0); pyproject's `reference` extra pins >=4.0.
PYCOLMAP_MIN_MAJOR = 4


def _major_version(version: str) -> int | None:
    head = version.split(".", 1)[0]
    return int(head) if head.isdigit() else None


def _failed(reason: str) -> str:
    """Log why SfM gave no points (a warning: the caller falls back) and return the reason."""
    log.warning("SfM: %s; the caller's fallback init is used", reason)
    return reason


def sfm_points(frames: list[Frame], workdir: Path, *, max_features: int = 4096) -> tuple[np.ndarray, np.ndarray, str]:
    """Triangulate SIFT matches between aerial views with their known poses.

    Returns (xyz [M, 3] float64 m, rgb [M, 3] float32 [0, 1], message). M may be 0; the
    message says what happened (for the run log).
    """
    empty = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    try:
        import pycolmap
    except ImportError as e:
        return (*empty, _failed(f"pycolmap unavailable ({e})"))
    major = _major_version(getattr(pycolmap, "__version__", ""))
    if major is not None and major < PYCOLMAP_MIN_MAJOR:
        return (*empty, _failed(f"pycolmap {pycolmap.__version__} is older than {PYCOLMAP_MIN_MAJOR}.0 (this code "
                                "calls Reconstruction.add_camera_with_trivial_rig / add_image_with_trivial_frame); "
                                f"pip install 'pycolmap>={PYCOLMAP_MIN_MAJOR}.0'"))
    pycolmap.logging.minloglevel = 2  # errors only: COLMAP's INFO log is hundreds of lines
    workdir = Path(workdir)
    if workdir.exists():
        shutil.rmtree(workdir)
    images = workdir / "images"
    images.mkdir(parents=True)
    names = []
    for i, f in enumerate(frames):
        name = f"{i:05d}.png"
        shutil.copyfile(f.path, images / name)
        names.append(name)
    db_path = workdir / "database.db"
    intr = frames[0].intrinsics
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(float(intr[k])) for k in ("fx", "fy", "cx", "cy"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.num_threads = 2
    # Tiny renders: start SIFT one octave up (first_octave = -1 is the default already).
    try:
        pycolmap.extract_features(db_path, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(db_path, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(str(db_path))
        db_images = db.read_all_images()
        db_cameras = db.read_all_cameras()
        db.close()
        rec = pycolmap.Reconstruction()
        for cam in db_cameras:
            rec.add_camera_with_trivial_rig(cam)
        by_name = {n: f for n, f in zip(names, frames)}
        for img in db_images:
            w2c = np.linalg.inv(by_name[img.name].c2w)
            im = pycolmap.Image(name=img.name, camera_id=img.camera_id, image_id=img.image_id)
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(matrix=w2c[:3, :4]))
        out = workdir / "triangulated"
        out.mkdir()
        rec = pycolmap.triangulate_points(rec, db_path, images, out)
    except Exception as e:  # SfM is best effort: any failure means the fallback init, said in the log
        log.debug("SfM traceback", exc_info=True)
        return (*empty, _failed(f"SfM failed ({type(e).__name__}: {e})"))
    pts = rec.points3D
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32), "SfM triangulated no points"
    xyz = np.array([p.xyz for p in pts.values()], dtype=np.float64)
    rgb = np.array([p.color for p in pts.values()], dtype=np.float32) / 255.0
    return xyz, rgb, f"SfM: {len(xyz)} points from {len(frames)} aerial views"


def ground_plane_points(frames: list[Frame], *, per_view: int = 2000, max_height: float = 20.0,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fallback init (see module docstring): xyz [M, 3], rgb [M, 3]."""
    rng = np.random.default_rng(seed)
    xyz, rgb = [], []
    for f in frames:
        img = f.image()
        cam = f.camera()
        h, w = img.shape[:2]
        u = rng.uniform(0, w, per_view)
        v = rng.uniform(0, h, per_view)
        _, d = cam.rays(np.stack([u, v], 1), normalize=False)  # [N, 3], camera z = 1
        o = cam.c2w[:3, 3]
        down = d[:, 2] < -1e-6
        t_ground = -o[2] / np.where(down, d[:, 2], -1.0)
        # Lift to a random height in [0, max_height] along the ray (t shrinks as z rises).
        z = rng.uniform(0, max_height, len(u)) * (rng.random(len(u)) < 0.5)
        t = t_ground * (o[2] - z) / o[2]
        keep = down & (t > 0)
        xyz.append(o + t[keep, None] * d[keep])
        rgb.append(img[v[keep].astype(int).clip(0, h - 1), u[keep].astype(int).clip(0, w - 1)])
    return np.concatenate(xyz), np.concatenate(rgb).astype(np.float32)
