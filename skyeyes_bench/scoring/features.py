"""The features of a scoring run's set metrics (FID, KID, FVD, ...): one row per frame, or per
clip of a sequence (`clips`), of the submission and of the ground truth, from the feature cache."""

from __future__ import annotations

import numpy as np

from ..errors import UserError
from ..metricspec import IMAGE_EXTRACTOR, metric_def
from .context import ScoringRun


def clips(n_frames: int, length: int, stride: int) -> list[range]:
    """Clips of `length` consecutive frames starting every `stride` frames (none if too short)."""
    return [range(s, s + length) for s in range(0, n_frames - length + 1, max(1, stride))]


def _wanted(protocol) -> tuple[dict[str, list], dict[str, list[str]]]:
    """({extractor: the set-metric specs that use it}, {extractor: the frame metrics that use it}).
    A frame metric's network (LPIPS) runs inside its per-frame function; its weights are named too."""
    wanted: dict[str, list] = {}
    for m in protocol.metrics:
        if metric_def(m.name).kind == "set":
            wanted.setdefault(m.extractor, []).append(m)
    frame_users: dict[str, list[str]] = {}
    for m in protocol.metrics:
        if metric_def(m.name).kind == "frame" and m.extractor:
            wanted.setdefault(m.extractor, [])
            frame_users.setdefault(m.extractor, []).append(m.name)
    return wanted, frame_users


def _image_features(run: ScoringRun, ex_id: str, ex, specs: list):
    """(submission [N, D], ground truth [N, D], sequence [N]): a row per scored frame."""
    from ..metrics.cache import extract_image_features

    sub_paths = [run.pred_path(s, f) for s, f in run.frames]
    gt_paths = [f.path for _, f in run.frames]
    seq = np.array([run.sequence_of(s, f) for s, f in run.frames], dtype=np.int64)
    fs = extract_image_features(ex_id, sub_paths, progress=run.progress, device=run.device)
    fg = extract_image_features(ex_id, gt_paths, progress=run.progress, device=run.device)
    return fs, fg, seq


def _clip_features(run: ScoringRun, ex_id: str, ex, specs: list):
    """(submission [N, D], ground truth [N, D], sequence [N]): a row per clip of the protocol's
    clip_length / clip_stride (the same for every metric of the extractor), sequence by sequence."""
    from ..metrics.cache import extract_clip_features

    spec = specs[0]
    if len({(m.clip_length, m.clip_stride) for m in specs}) > 1:
        raise UserError(f"protocol {run.protocol.ref}: metrics {', '.join(m.name for m in specs)} share "
                        f"extractor {ex_id} but not clip_length/clip_stride")
    clips_sub, clips_gt, seq_l = [], [], []
    by_seq: dict[int, list] = {}
    for s, f in run.frames:
        by_seq.setdefault(run.sequence_of(s, f), []).append((s, f))
    for k in sorted(by_seq):
        fr = sorted(by_seq[k], key=lambda sf: sf[1].index)
        for c in clips(len(fr), spec.clip_length, spec.clip_stride or spec.clip_length):
            clips_sub.append([run.pred_path(*fr[i]) for i in c])
            clips_gt.append([fr[i][1].path for i in c])
            seq_l.append(k)
    seq = np.array(seq_l, dtype=np.int64)
    if not clips_sub:
        return np.zeros((0, ex.dim)), np.zeros((0, ex.dim)), seq
    fs = extract_clip_features(ex_id, clips_sub, progress=run.progress, device=run.device)
    fg = extract_clip_features(ex_id, clips_gt, progress=run.progress, device=run.device)
    return fs, fg, seq


def features(run: ScoringRun) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict]]:
    """Features of the submission and ground truth for every set-metric extractor, computed on
    `run.device` (its type is recorded in each extractor's info); an extractor without its weights
    marks its metrics unavailable.

    Returns ({"<extractor>": {"sub": [N, D], "gt": [N, D], "seq": [N]}}, {extractor: info})."""
    from ..metrics import MetricUnavailable
    from ..metrics.extractors import get_extractor

    wanted, frame_users = _wanted(run.protocol)
    out: dict[str, dict[str, np.ndarray]] = {}
    extractors: dict[str, dict] = {}
    with run.time("features_s"):
        for ex_id, specs in wanted.items():
            try:
                ex = get_extractor(ex_id)
                extractors[ex_id] = {"kind": ex.kind, "dim": ex.dim, "weights_sha256": ex.weights_sha256,
                                     "device": run.device.type}
            except MetricUnavailable as e:
                extractors[ex_id] = {"status": "unavailable", "reason": e.reason}
                run.mark_unavailable([m.name for m in specs], e.reason, e.fix)
                continue
            if not specs:  # a frame metric's network: record the weights it used
                gone = any(run.is_unavailable(name) for name in frame_users[ex_id])
                extractors[ex_id]["status"] = "unavailable" if gone else "ok"
                continue
            extract = _image_features if ex.kind == IMAGE_EXTRACTOR else _clip_features
            try:
                fs, fg, seq = extract(run, ex_id, ex, specs)
            except MetricUnavailable as e:
                extractors[ex_id]["status"] = "unavailable"
                run.mark_unavailable([m.name for m in specs], e.reason, e.fix)
                continue
            extractors[ex_id]["status"] = "ok"
            out[ex_id] = {"sub": np.asarray(fs), "gt": np.asarray(fg), "seq": seq}
    return out, extractors
