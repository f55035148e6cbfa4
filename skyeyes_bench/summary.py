"""Results from a complete partial (`finalize`): per-sequence values, summaries with half-sampling
intervals over the protocol's clusters (scenes or sequences) and their replicates, set metrics;
and the lines a terminal shows of them (`format_summary`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import stats
from .errors import UserError
from .metricspec import CLIP_FEATURES, frame_metrics, metric_def
from .registry import load_entry_point
from .results import RESULTS_FORMAT, lines_digest, timed_stage, progress_bar


# --------------------------------------------------------------------------- summary


@dataclass(frozen=True)
class _Resampling:
    """The resampling of one `finalize`: the protocol's statistics `st`, the cluster of each
    sequence (`cl_of_seq`), the number of clusters `k`, the reason there are too few (`few`) and
    the clusters of each half-sampling replicate (`counts`, None when too few)."""

    st: Any
    cl_of_seq: np.ndarray
    k: int
    few: str | None
    counts: np.ndarray | None

    def summarise(self, value: float, replicates: np.ndarray | None, floor: float | None = None,
                  centre: float | None = None) -> dict:
        """interval (null + reason below MIN_CLUSTERS; clipped at the metric's `floor`; about
        `centre` when the metric has one), replicates (6 significant digits)."""
        if replicates is None:
            return {"interval": None, "interval_note": self.few, "replicates": None}
        out: dict = {"replicates": stats.round_replicates(replicates)}
        if centre is not None and math.isfinite(centre):
            out["interval_centre"] = centre
        iv = stats.interval_from_replicates(value, replicates, self.st.interval, self.k, centre)
        if iv is None:
            out.update(interval=None, interval_note="no replicate is defined")
        else:
            # clipped at the floor, but never above the value (FID∞ extrapolates and may lie below 0)
            out["interval"] = [iv[0] if floor is None else max(iv[0], min(floor, value)), iv[1]]
            if iv[2]:
                out["interval_note"] = ("interval widened to contain the value: the half-sample draws lie on one "
                                        "side of it (a small-sample bias of this metric larger than its spread)")
        return out


def finalize(doc: dict, features: dict, *, timing: dict | None = None, progress: bool = False) -> dict:
    """Turn a complete (all sequences) partial into results: per-sequence values, summaries with
    half-sampling intervals over the protocol's clusters (scenes or sequences) and their
    replicates, set metrics. Pure given its inputs (deterministic seeds)."""
    from .protocol import load_protocol

    timing = {} if timing is None else timing
    protocol = load_protocol(doc["protocol"]["ref"])
    if protocol.sha256 != doc["protocol"]["sha256"]:
        raise UserError(f"protocol {protocol.ref} changed since these values were computed (sha256 "
                        f"{doc['protocol']['sha256'][:12]}... then, {protocol.sha256[:12]}... now)")
    st = protocol.statistics
    seq_ids = doc["dataset"]["sequences"]
    frames = sorted(doc["frames"], key=lambda r: (r["sequence"], r["index"]))
    # The resampling unit: scenes (all sequences of a lane share one fitted model) or, for
    # protocols that say so (synthtown@1), sequences.
    cl_of_seq, cluster_names = stats.cluster_map(seq_ids, st.cluster)
    k = len(cluster_names)
    few = stats.too_few(k, st.cluster)
    counts = None if few else stats.replicate_counts(k, st.bootstrap_resamples, st.seed)
    rs = _Resampling(st, cl_of_seq, k, few, counts)
    res = dict(doc)
    res["format"] = RESULTS_FORMAT
    res["frames"] = frames
    res["sha256"] = {
        "submission_frames": lines_digest([f"{r['scene']}/{r['file']} {r['sha256']}\n" for r in frames]),
        "ground_truth": lines_digest([f"{r['scene']}/{r['file']} {r['gt_sha256']}\n" for r in frames]),
    }
    res["statistics"] = {
        "method": f"half-sampling of {st.cluster}s without replacement (paired submission/ground truth): each "
                  f"replicate recomputes the metric on {k // 2} of the {k} {st.cluster}s",
        "cluster": st.cluster, "clusters": k, "cluster_ids": cluster_names, "min_clusters": stats.MIN_CLUSTERS,
        "too_few": few, "resamples": st.bootstrap_resamples, "level": st.interval, "seed": st.seed,
        "interval": stats.INTERVAL_METHOD, "half_size": k // 2, "scale": stats.half_scale(k) if k >= 2 else None}
    metrics, per_seq = _frame_metrics(doc, frames, protocol, rs, timing)
    timing.setdefault("set_metrics_s", 0.0)
    _set_metrics(doc, features, protocol, rs, timing, progress, metrics)
    res["metrics"] = {name: metrics[name] for name in protocol.metric_names if name in metrics}
    res["sequences"] = per_seq
    res.pop("unavailable", None)
    return res


def _frame_metrics(doc: dict, frames: list[dict], protocol, rs: _Resampling,
                   timing: dict) -> tuple[dict[str, dict], dict[str, dict]]:
    """The protocol's frame metrics over `frames` (sorted by sequence and index), and the value
    of each per sequence: ({metric: entry}, {sequence id: {"frames": n, metric: value}})."""
    st = rs.st
    seq_ids = doc["dataset"]["sequences"]
    k_seq = len(seq_ids)
    seqs = np.array([r["sequence"] for r in frames], dtype=np.int64)
    clusters = rs.cl_of_seq[seqs]
    metrics: dict[str, dict] = {}
    per_seq: dict[str, dict] = {sid: {"frames": int((seqs == i).sum())} for i, sid in enumerate(seq_ids)}
    # over: means of values near 1e308 (only a hostile part holds them) are +-inf, without a warning
    with timed_stage(timing, "bootstrap_s"), np.errstate(over="ignore"):
        for name in frame_metrics():
            if not protocol.metric(name):
                continue
            if name in doc["unavailable"]:
                metrics[name] = {"status": "unavailable", **doc["unavailable"][name]}
                continue
            spec = metric_def(name)
            v = np.array([np.nan if r[name] is None else r[name] for r in frames], dtype=np.float64)
            w = np.array([r[f"{name}_n"] for r in frames], dtype=np.float64) if spec.weighted else None
            if w is not None and not (w[~np.isnan(v)] > 0).any():
                metrics[name] = {"status": "unavailable", "reason": f"no frame has a pixel of {name}'s region: "
                                 "its value is undefined on this dataset", "fix": "none (a property of the data)"}
                continue
            if w is None:
                value = float(np.mean(v)) if not np.isposinf(v).any() else math.inf
            else:
                value = stats.pooled_value(v, w, spec.pool)
            reps = None if rs.counts is None else stats.frame_metric_samples(v, clusters, rs.counts, w, spec.pool)
            metrics[name] = {"status": "ok", "kind": "frame", "value": value, "level": st.interval,
                             "higher_is_better": spec.higher_is_better, "n": int(len(v)),
                             **rs.summarise(value, reps)}
            if w is not None:  # pooled pixels (docs/metrics.md): n frames hold `pixels` of the region
                metrics[name].update(n=int((w > 0).sum()), pixels=int(w.sum()), pool=spec.pool)
            if spec.reference:
                metrics[name]["reference"] = True  # a property of the ground truth: not ranked
            if name == "psnr":
                metrics[name]["infinite_frames"] = int(np.isposinf(v).sum())
                seqv = stats.sequence_psnr(v, seqs, k_seq)
            else:
                seqv = stats.frame_metric_samples(v, seqs, np.eye(k_seq), w, spec.pool)
            for i, sid in enumerate(seq_ids):
                per_seq[sid][name] = None if np.isnan(seqv[i]) else float(seqv[i])
    return metrics, per_seq


def _set_metrics(doc: dict, features: dict, protocol, rs: _Resampling, timing: dict, progress: bool,
                 metrics: dict[str, dict]) -> None:
    """Add the protocol's set metrics, computed from `features`, to `metrics`."""
    st, k = rs.st, rs.k
    for m in protocol.metrics:
        spec = metric_def(m.name)
        if spec.kind != "set":
            continue
        if m.name in doc["unavailable"]:
            metrics[m.name] = {"status": "unavailable", **doc["unavailable"][m.name]}
            continue
        f = features[m.extractor]
        xs, xg = np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64)
        cl = rs.cl_of_seq[np.asarray(f["seq"], np.int64)]
        if len(xs) < spec.min_rows:
            what = "clips" if spec.features == CLIP_FEATURES else "frames"
            metrics[m.name] = {"status": "unavailable", "reason": f"{len(xs)} {what} of {m.clip_length or 1} "
                               f"frames; need at least {spec.min_rows}",
                               "fix": "sequences must hold at least clip_length frames"}
            continue
        with timed_stage(timing, "set_metrics_s"):
            value = float(load_entry_point(spec.estimator)(xs, xg, m, st.seed))
        reps = centre = None
        if rs.counts is not None:
            with timed_stage(timing, "bootstrap_s"):
                if spec.centre:  # an estimate with random subsets: its interval's centre (MetricDef.centre)
                    centre = float(load_entry_point(spec.centre)(xs, xg, m, st.seed))
                fn = stats.set_metric_bootstrap(m.name, xs, xg, cl, k, m, st.seed)
                bar = progress_bar(progress, total=len(rs.counts), desc=f"resample {m.name}", unit="replicate")
                with bar:
                    reps = stats.set_metric_samples(fn, cl, cl, rs.counts, progress=bar.update)
        metrics[m.name] = {"status": "ok", "kind": "set", "value": value, "level": st.interval,
                           "higher_is_better": spec.higher_is_better, "n": int(len(xs)),
                           "extractor": m.extractor, "unit": "clip" if spec.features == CLIP_FEATURES else "frame",
                           **rs.summarise(value, reps, spec.lower_bound, centre)}


# --------------------------------------------------------------------------- terminal


def format_summary(res: dict) -> str:
    """Human-readable lines for the terminal."""
    lines = [f"{res['submission'].get('method')} {res['submission'].get('method_version') or ''} on "
             f"{res['protocol']['ref']} ({res['dataset']['name']}, {res['dataset'].get('split', 'test')} split, "
             f"{len(res['frames'])} frames, {len(res['dataset']['sequences'])} sequences)"]
    st = res.get("statistics") or {}
    if st.get("cluster"):
        lines.append(f"  intervals: {st['interval']} over {st['clusters']} {st['cluster']}s"
                     + (f" -- {st['too_few']}: no intervals" if st.get("too_few") else ""))
    for name, m in res["metrics"].items():
        if m["status"] != "ok":
            lines.append(f"  {name:<6} unavailable: {m['reason']} (fix: {m['fix']})")
            continue
        arrow = "higher is better" if m["higher_is_better"] else "lower is better"
        if m.get("reference"):
            arrow = "of the ground truth: not a score"
        extra = f"  ({m['infinite_frames']} exact frames)" if m.get("infinite_frames") else ""
        if m.get("interval") is None:
            iv = f"(no interval: {m.get('interval_note') or 'none'})"
        else:
            lo, hi = m["interval"]
            iv = f"[{lo:.4g}, {hi:.4g}] {int(m['level'] * 100)}%"
            if m.get("interval_note"):
                extra += f"  [note: {m['interval_note']}]"
        lines.append(f"  {name:<6} {m['value']:.4g}  {iv}  ({arrow}){extra}")
        if m.get("pixels") is not None:
            lines[-1] += f"  [{m['pixels']} pixels of {m['n']} frames]"
    t = res.get("timing_s", {})
    lines.append("  evaluator time: " + ", ".join(f"{k} {v:.2f}" for k, v in t.items() if isinstance(v, float)))
    return "\n".join(lines)
