"""Write SynthTown datasets in the canonical layout (protocols synthtown@1 and @2; a preset names its own).

Cameras follow the capture protocol (Skyeyes supplement Sec. 1.1): ground cameras every 2 m
along a lane at 2 m height, pitch 0, yaw = lane heading + k * 45 deg (k = 0..7, one sequence
per k, named `yaw000` .. `yaw315`); aerial cameras over the same points at 52 m, pitch -45 deg.
Every `aerial_stride`-th ground point gets `aerial_yaws` aerial views with headings spread
evenly around the compass (lane heading + k * 360 / aerial_yaws): seen from above at 45 deg,
each one covers the ground from straight below to the horizon in its heading, so the lane's
facades, cars and trees are seen from the front, the back and both sides.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from ... import paths
from ...cameras import Camera
from ...errors import UserError
from ..writer import DatasetWriter
from . import town as tw
from .presets import PRESETS, SPLITS, TRAIN_TOWNS, VAL_TOWNS, Preset, for_split
from .render import LABELS, PALETTE, Scene, render_batch

#: Bump when the rendered bytes change for the same preset and seed.
GENERATOR_VERSION = "1"


def dataset_name(preset: str | Preset, seed: int, split: str = "test") -> str:
    """The dataset's name and cache folder: the preset's `dataset` (e.g. synthtown-v2-small; its
    validation data's: synthtown-v2-small-val), -seedN if seed > 0."""
    return get_preset(preset, split).dataset + (f"-seed{seed}" if seed != 0 else "")


def get_preset(preset: str | Preset, split: str = "test") -> Preset:
    """The named preset (or `preset` itself), for the data of `split` (`presets.for_split`)."""
    if split not in SPLITS:
        raise UserError(f"split {split!r}: expected one of {', '.join(SPLITS)}")
    if not isinstance(preset, Preset):
        if preset not in PRESETS:
            raise UserError(f"unknown SynthTown preset {preset!r}; known: {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    if split == "val" and preset.protocol == "synthtown-stiff@1":
        raise UserError(f"preset {preset.name!r}: its protocol {preset.protocol} is for reporting only and has "
                        "no validation split (choose settings on `--preset small --split val`)")
    return for_split(preset, split)


def lane_cameras(lane: dict, p: Preset, town: tw.Town | None = None
                 ) -> tuple[list[tuple[str, int, Camera]], list[tuple[int, float, Camera]]]:
    """Ground cameras [(sequence, index, camera)] and aerial cameras [(point, yaw offset, camera)] of
    a lane (`lane`'s start and heading in `town`'s coordinates). In a tilted town (`Town.world`)
    the cameras stand the protocol's heights above the street's points in the world, level
    (pitch 0 and -45 deg in the world), heading along the street's direction seen from above."""
    h = lane["heading_deg"]
    fwd = np.array([np.cos(np.deg2rad(h)), np.sin(np.deg2rad(h))])
    pts = [np.asarray(lane["start"]) + i * p.step_m * fwd for i in range(p.frames)]
    if town is not None and town.world is not None:
        pts = [town.to_world([x, y, 0.0]) for x, y in pts]
        f3 = town.to_world([fwd[0], fwd[1], 0.0])
        h = float(np.rad2deg(np.arctan2(f3[1], f3[0])))
    else:
        pts = [np.array([x, y, 0.0]) for x, y in pts]
    ground = []
    for k in range(8):
        yaw = 45 * k
        for i, pt in enumerate(pts):
            cam = Camera.from_ypr([pt[0], pt[1], pt[2] + p.ground_height_m], h + yaw, 0.0,
                                  fov_deg=p.fov_deg, width=p.width, height=p.height)
            ground.append((f"yaw{yaw:03d}", i, cam))
    aerial = []
    for i in range(0, p.frames, p.aerial_stride):
        for k in range(p.aerial_yaws):
            off = k * 360.0 / p.aerial_yaws
            cam = Camera.from_ypr([pts[i][0], pts[i][1], pts[i][2] + p.aerial_height_m], h + off, p.aerial_pitch_deg,
                                  fov_deg=p.fov_deg, width=p.width, height=p.height)
            aerial.append((i, off, cam))
    return ground, aerial


def plan(p: Preset, seed: int) -> list[dict]:
    """Towns and lanes to render: [{town, scene names, lanes}] (cheap, no rendering)."""
    out = []
    for town_name, n_lanes in p.lanes:
        t = tw.make_town(town_name, seed, p.blocks)
        lanes = tw.make_lanes(t, n_lanes, p.frames, p.step_m, seed)
        out.append({"town": t, "lanes": lanes,
                     "scenes": [f"{town_name}-lane{j:02d}" for j in range(n_lanes)]})
    return out


# Worker-process state: one prepared Scene per town (built on first use).
_SCENES: dict[tuple, Scene] = {}


def _render_job(job: tuple) -> list[tuple]:
    """Render a chunk of views of one town (in a worker process or in-line)."""
    town_name, seed, blocks, cull, aa, views = job
    key = (town_name, seed, blocks, cull)
    if key not in _SCENES:
        _SCENES.clear()
        _SCENES[key] = Scene.from_town(tw.make_town(town_name, seed, blocks), cull_m=cull)
    return render_batch(_SCENES[key], [Camera(K, c2w, w, h) for K, c2w, w, h in views], aa)


def _default_workers(p: Preset) -> int:
    env = os.environ.get("SKYEYES_WORKERS")
    if env:
        return max(1, int(env))
    return 1 if p.name == "smoke" else max(1, min(2, os.cpu_count() or 1))


def generate_dataset(out: Path, preset: str = "small", seed: int = 0, *, overwrite: bool = False,
                     progress: bool = True, workers: int | None = None, split: str = "test") -> Path:
    """Render a SynthTown dataset into `out` (atomically: a temporary folder moved into place).

    Args:
        out: dataset folder to create.
        preset: "smoke", "small" or "paper" (see presets.py).
        seed: dataset seed; another seed gives other towns and lanes.
        overwrite: replace an existing `out` (only once the new one is complete).
        progress: tqdm progress bar on stderr.
        workers: render processes (default: 1 for smoke, else min(2, cores); env SKYEYES_WORKERS).
        split: "test" (the preset's train and test towns) or "val" (its train towns and the
            validation towns instead: `presets.for_split`).
    Returns:
        `out`.
    """
    out = Path(out)
    p = get_preset(preset, split)
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UserError(f"seed {seed!r}: expected an integer >= 0")
    seed = int(seed)
    if out.exists() and not overwrite:  # fail before rendering anything
        raise UserError(f"{out}: already exists; pass --force to replace it")
    towns = plan(p, seed)
    chunk, jobs, where = _render_jobs(towns, p, seed)
    from tqdm import tqdm

    n_workers = workers or _default_workers(p)
    bar = tqdm(total=len(where), desc=f"synthtown-{p.name}", unit="img", file=sys.stderr, disable=None if progress else True)
    pool = None
    try:
        if n_workers > 1:
            import multiprocessing as mp

            pool = mp.get_context("spawn").Pool(n_workers)
            chunks = pool.imap(_render_job, jobs, chunksize=max(1, 4 // chunk))
        else:
            chunks = map(_render_job, jobs)
        results = (r for c in chunks for r in c)
        with DatasetWriter(out, name=dataset_name(p, seed), protocol=p.protocol, overwrite=overwrite) as w:
            _write_views(w, towns, where, results, p, seed, bar)
            roles = [town_role(e["town"].name) for e in towns]
            splits = {role: [s for e, r in zip(towns, roles) if r == role for s in e["scenes"]]
                      for role in ("train", "val", "test") if role == "train" or role in roles}
            w.finish(splits=splits, meta={
                "generator": "synthtown", "generator_version": GENERATOR_VERSION, "preset": p.name,
                "preset_config": p.to_dict(), "seed": seed, "official": p.official,
                "towns": {e["town"].name: e["town"].params for e in towns},
                "semantics": {"labels": list(LABELS), "palette": PALETTE.tolist()},
                "depth": "planar z in metres, float32 EXR, inf = sky",
            })
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    return out


def _render_jobs(towns: list[dict], p: Preset, seed: int) -> tuple[int, list[tuple], list[tuple]]:
    """Views per render job, render jobs (chunks of one town's views, `_render_job`'s argument) and
    what each rendered view is, in render order: (town, lane, kind, sequence or point, index or yaw
    offset, camera)."""
    # Views are rendered in chunks of about 16k pixels: small images share one traversal.
    chunk = max(1, 16384 // (p.width * p.height))
    jobs, where = [], []
    for ti, entry in enumerate(towns):
        for li, lane in enumerate(entry["lanes"]):
            ground, aerial = lane_cameras(lane, p, entry["town"])
            for kind, cams in (("ground", ground), ("aerial", aerial)):
                for a, b, cam in cams:
                    where.append((ti, li, kind, a, b, cam))
                for c0 in range(0, len(cams), chunk):
                    views = [(c.K, c.c2w, c.width, c.height) for _, _, c in cams[c0:c0 + chunk]]
                    jobs.append((entry["town"].name, seed, p.blocks, p.cull_m, p.aa, views))
    return chunk, jobs, where


def _write_views(w: DatasetWriter, towns: list[dict], where: list[tuple], results, p: Preset, seed: int, bar) -> None:
    """Write the rendered views (`results`, in the order of `where`) into their scenes, one scene open at a time."""
    writers: dict[tuple[int, int], object] = {}
    for (ti, li, kind, a, b, cam), (rgb, depth, labels) in zip(where, results):
        entry = towns[ti]
        if (ti, li) not in writers:
            for prev in writers.values():
                prev.close()
            writers.clear()
            lane = entry["lanes"][li]
            intr = cam.intrinsics_dict()
            writers[(ti, li)] = w.scene(entry["scenes"][li], {"ground": intr, "aerial": intr}, meta={
                "town": entry["town"].name, "lane": lane, "preset": p.name, "seed": seed,
                "ground_height_m": p.ground_height_m, "aerial_height_m": p.aerial_height_m,
                "aerial_pitch_deg": p.aerial_pitch_deg, "step_m": p.step_m,
            })
        sw = writers[(ti, li)]
        if kind == "ground":
            sw.add_ground(rgb, cam.c2w, sequence=a, index=b, depth=depth, semantics=labels)
        else:
            sw.add_aerial(rgb, cam.c2w, depth=depth, semantics=labels, point=a, yaw_offset_deg=b)
        bar.update(1)
    for prev in writers.values():
        prev.close()


def town_role(name: str) -> str:
    """The split a town's lanes belong to: "train", "val" or "test" (the test and stiff towns)."""
    return "train" if name in TRAIN_TOWNS else "val" if name in VAL_TOWNS else "test"


def ensure_dataset(preset: str = "small", seed: int = 0, progress: bool = True, split: str = "test") -> Path:
    """`<cache>/data/<the preset's dataset>[-seed<N>]`, generated there first if absent (with
    `split="val"`, the preset's validation data: `<dataset>-val`).

    A folder there made for another protocol or preset configuration (an older release's data
    under the same name) is a one-line error, not silently used.

    Generation is atomic (a killed run leaves nothing) and serialised by a lock file beside the
    dataset: a second process asking for the same dataset waits for the first and then uses its
    result instead of rendering it again.
    """
    import fcntl

    p = get_preset(preset, split)
    path = paths.data_dir() / dataset_name(p, int(seed))
    if (path / "dataset.json").is_file():
        return _check_cached(path, p)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.parent / f".{path.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes (also if we are killed)
        if (path / "dataset.json").is_file():  # another process made it while we waited
            return _check_cached(path, p)
        if path.exists():
            raise UserError(f"{path}: exists but holds no dataset.json (not a SynthTown dataset); remove it")
        return generate_dataset(path, p, int(seed), progress=progress)


def _check_cached(path: Path, p: Preset) -> Path:
    """`path` if its dataset.json was made from preset `p` for `p.protocol`; else a one-line UserError."""
    from ... import inputfiles

    def rendered(cfg: dict) -> dict:  # the fields that decide the pixels (not the preset's name)
        return {k: v for k, v in cfg.items() if k not in ("name", "official")}

    doc = inputfiles.read_json(path / "dataset.json")
    cfg = (doc.get("meta") or {}).get("preset_config")
    if doc.get("protocol") != p.protocol or (cfg is not None and rendered(cfg) != rendered(p.to_dict())):
        raise UserError(f"{path}/dataset.json: made for protocol {doc.get('protocol')!r} with another "
                        f"configuration than preset {p.name!r} ({p.protocol}); remove the folder to regenerate it")
    return path
