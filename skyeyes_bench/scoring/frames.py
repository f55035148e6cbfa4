"""The frame metrics of a scoring run: frame by frame (`score_frames`: PSNR, SSIM, LPIPS, ...),
then a sequence at a time from the ground truth's depth and poses (`score_sequences`: seen /
unseen regions, warp consistency). Each computed by the function its `metricspec` entry names."""

from __future__ import annotations

import numpy as np

from .. import imagefiles
from ..metricspec import frame_metrics, metric_def, sequence_metrics
from ..registry import load_entry_point
from .context import ScoringRun
from .inputs import missing_depth

_FRAME_BATCH = 16


def _batches(items: list, size: int):
    for i in range(0, len(items), size):
        yield items[i:i + size]


def score_frames(run: ScoringRun) -> None:
    """The per-frame metrics the protocol asks for (`MetricDef.per_frame`), a record per frame of
    `run.frames` with its file hashes and values; a metric whose function raises
    `MetricUnavailable` (missing weights) is marked unavailable once, not retried per batch."""
    from ..metrics import MetricUnavailable

    specs = run.specs(n for n in frame_metrics() if metric_def(n).per_frame)
    functions = {m.name: load_entry_point(metric_def(m.name).per_frame) for m in specs}
    bar = run.bar(len(run.frames), "per-frame metrics", "frame")
    with run.time("frame_metrics_s"), bar:
        for batch in _batches(run.frames, _FRAME_BATCH):
            preds = np.stack([imagefiles.read_image(run.pred_path(s, f)) for s, f in batch])  # [B, H, W, 3]
            gts = np.stack([f.image() for _, f in batch])  # [B, H, W, 3]
            values: dict[str, np.ndarray] = {}  # name -> [B]
            for m in specs:
                if run.is_unavailable(m.name):
                    continue
                try:
                    values[m.name] = functions[m.name](preds, gts, m)
                except MetricUnavailable as e:
                    run.mark_unavailable([m.name], e.reason, e.fix)
            for i, (scene, f) in enumerate(batch):
                run.add_record(scene, f, {name: float(v[i]) for name, v in values.items()})
            bar.update(len(batch))


def _sequence_groups(run: ScoringRun) -> dict[str, list]:
    """{entry point: the protocol's specs it computes together} of the depth-based metrics whose
    depth layers every scored scene has (the others are marked unavailable)."""
    groups: dict[str, list] = {}
    for m in run.specs(sequence_metrics()):
        groups.setdefault(metric_def(m.name).per_sequence, []).append(m)
    scenes = sorted({s for s, _ in run.frames})
    for entry, ms in list(groups.items()):
        gone = missing_depth(run.ds, scenes, [m.name for m in ms])
        if gone:
            for name, why in gone.items():
                run.mark_unavailable([name], why["reason"], why["fix"])
            del groups[entry]
    return groups


def _sequence_data(run: ScoringRun, scene: str, fs: list):
    """The frames `fs` of one sequence of `scene` (in order) as the depth metrics see them; the
    seen masks computed on first use, per tolerance, timed as "masks_s"."""
    from ..estimators import SequenceData
    from ..metrics.masks import seen_masks

    masks: dict[float, np.ndarray] = {}

    def seen(tol: float) -> np.ndarray:
        if tol not in masks:
            with run.time("masks_s"):
                masks[tol] = seen_masks(run.ds.scenes[scene], fs, tol)
        return masks[tol]

    return SequenceData(preds=np.stack([imagefiles.read_image(run.pred_path(scene, f)) for f in fs]),
                        gts=np.stack([f.image() for f in fs]), depths=np.stack([f.depth() for f in fs]),
                        cameras=[f.camera() for f in fs], seen=seen)


def score_sequences(run: ScoringRun) -> None:
    """The frame metrics computed a sequence at a time (`MetricDef.per_sequence`), added to the
    frames' records: the value (null for an empty region) and, for pixel-weighted metrics,
    `<name>_n`, the region's pixel count."""
    from ..metrics import MetricUnavailable

    groups = _sequence_groups(run)
    if not groups:
        return
    by_seq: dict[tuple[str, str], list] = {}
    for s, f in run.frames:
        by_seq.setdefault((s, f.sequence), []).append(f)
    run.start_clock("masks_s")
    bar = run.bar(len(by_seq), "depth metrics", "sequence")
    with run.time("sequence_metrics_s"), bar:
        for (scene, _), fs in by_seq.items():
            fs = sorted(fs, key=lambda f: f.index)
            data = _sequence_data(run, scene, fs)
            for entry, ms in groups.items():
                if all(run.is_unavailable(m.name) for m in ms):
                    continue
                try:
                    values = load_entry_point(entry)(data, ms)
                except MetricUnavailable as e:  # missing weights: reported once, not retried per sequence
                    run.mark_unavailable([m.name for m in ms], e.reason, e.fix)
                    continue
                for name, (v, n) in values.items():
                    for i, f in enumerate(fs):
                        got = {name: None if np.isnan(v[i]) else float(v[i])}
                        if n is not None:
                            got[f"{name}_n"] = int(n[i])
                        run.add_values(scene, f, got)
            bar.update(1)
