"""Best in column, and whether the best is *credibly* best.

Every measured table's rows share a protocol (id, version, sha256), extractor weights and ground
truth (`tables.measured_tables` groups them so), so two rows can be paired. Rules, in order:

1. A metric whose interval is null in either row (too few scenes) is never credibly best.
2. **Paired bootstrap replicates** (every metric, set metrics included): each results file
   carries `metrics[m]["replicates"]`, R values of the metric under resamples whose indices
   depend only on (seed, resamples, number of clusters). For two results with the same
   statistics, replicate r of A and replicate r of B used the same resample, so the paired
   replicates of the difference are `advantage(A_r, B_r)` (> 0: A better). The best is credibly
   best when their interval (the results' level and interval method) excludes 0.
3. Without replicates: per-frame metrics by a paired bootstrap of per-sequence differences
   (`stats.advantage_interval`); set metrics by non-overlapping intervals (conservative).

A best that is not credibly best gets the dagger.
"""

from __future__ import annotations

import math

import numpy as np

from .. import stats
from ..metricspec import METRICS
from .tables import Row, Table

RULE_REPLICATES = "paired bootstrap replicates"
RULE_SEQUENCES = "paired bootstrap of per-sequence differences (no replicates)"
RULE_OVERLAP = "overlapping intervals (no replicates)"
RULE_NO_INTERVAL = "no interval (too few scenes)"
RULE_ONE_ROW = "one row: nothing to compare"


def _replicate_array(reps) -> np.ndarray | None:
    """Replicates [R] as float64 (null -> NaN), or None if they are not a list of numbers/nulls."""
    if not isinstance(reps, list) or not reps:
        return None
    if not all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in reps):
        return None
    return np.array([math.nan if v is None else float(v) for v in reps], dtype=np.float64)


#: Statistics that must agree for replicate r of two results to come from the same resample.
_PAIRING_KEYS = ("resamples", "seed", "interval", "cluster", "clusters")


def paired_replicates(a: Row, b: Row, metric: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The two rows' replicates of `metric` if they can be paired (same resampling: resamples,
    seed, interval method, cluster unit and count; same length), else None."""
    ra, rb = _replicate_array(a.replicates.get(metric)), _replicate_array(b.replicates.get(metric))
    if ra is None or rb is None or len(ra) != len(rb):
        return None
    if any(a.statistics.get(k) != b.statistics.get(k) for k in _PAIRING_KEYS):
        return None
    return ra, rb


def replicate_interval(ra: np.ndarray, rb: np.ndarray, metric: str, level: float, *,
                       estimate: float | None = None, statistics: dict | None = None,
                       centre: float | None = None) -> tuple[float, float] | None:
    """Interval of the paired replicate advantage of A over B (> 0: A better), from the replicate
    differences advantage(A_r, B_r) [R] (undefined ones dropped); None when none is left.

    Bootstrap replicates: their percentile interval. Half-sampling replicates (results'
    `statistics.interval` "half-sampling"): `stats.interval_from_replicates`, which rescales
    half-sample spread to the full sample around `estimate` (the advantage of the two values),
    exactly as `evaluate` and `compare` make their intervals (about `centre`, the advantage of
    the two intervals' centres, for FD∞)."""
    d = stats.advantage(ra, rb, metric)  # [R]
    st = statistics or {}
    half = getattr(stats, "interval_from_replicates", None)
    if st.get("interval") == "half-sampling" and half is not None and estimate is not None and st.get("clusters"):
        iv = half(estimate, d, level, int(st["clusters"]), centre)
        return None if iv is None else (iv[0], iv[1])
    d = d[~np.isnan(d)]
    return stats.percentile_interval(d, level) if len(d) else None


def _level(a: Row) -> float:
    lv = a.statistics.get("level")
    return float(lv) if isinstance(lv, (int, float)) else 0.95


def _credible(a: Row, b: Row, m: str) -> tuple[bool, str]:
    """Is row a (the best on m) credibly better than row b (the runner-up)? And by which rule."""
    if m in a.no_interval or m in b.no_interval:  # too few scenes: no interval means no claim either
        return False, RULE_NO_INTERVAL
    pair = paired_replicates(a, b, m)
    if pair is not None:
        est = float(stats.advantage(np.array([a.values[m]]), np.array([b.values[m]]), m)[0])
        centre = (float(stats.advantage(np.array([a.centres[m]]), np.array([b.centres[m]]), m)[0])
                  if m in a.centres and m in b.centres else None)
        iv = replicate_interval(*pair, m, _level(a), estimate=est, statistics=a.statistics, centre=centre)
        return iv is not None and iv[0] > 0, RULE_REPLICATES
    if METRICS[m].kind == "frame":
        seqs = sorted(a.sequences)
        va = np.array([a.sequences[s].get(m, math.nan) for s in seqs], dtype=np.float64)
        vb = np.array([b.sequences.get(s, {}).get(m, math.nan) for s in seqs], dtype=np.float64)
        st = a.statistics
        iv = stats.advantage_interval(stats.advantage(va, vb, m), resamples=int(st.get("resamples", 1000)),
                                      level=_level(a), seed=int(st.get("seed", 0)))
        return iv is not None and iv[0] > 0, RULE_SEQUENCES
    (alo, ahi), (blo, bhi) = a.intervals[m], b.intervals[m]
    return (alo > bhi if stats.higher_is_better(m) else ahi < blo), RULE_OVERLAP


def mark_best(t: Table) -> None:
    """Fill t.best (bold), t.not_credible (dagger) and, for measured tables, t.rules."""
    for m in t.metrics:
        vals = [(i, r.values.get(m)) for i, r in enumerate(t.rows) if r.values.get(m) is not None]
        if not vals:
            continue
        if len(vals) < 2:  # a lone value is best of nothing: no bold, no dagger
            if not t.reported:
                t.rules[m] = RULE_ONE_ROW
            continue
        hib = stats.higher_is_better(m)
        order = sorted(vals, key=lambda iv: -iv[1] if hib else iv[1])
        best_v = order[0][1]
        t.best[m] = [i for i, v in vals if v == best_v]
        if t.reported:
            continue
        credible, t.rules[m] = _credible(t.rows[order[0][0]], t.rows[order[1][0]], m)
        if len(t.best[m]) == 1 and not credible:  # an exact tie: both bold, nothing to flag
            t.not_credible.add(m)


def rules_summary(t: Table) -> str:
    """'Marks: PSNR, SSIM by paired bootstrap replicates; FID by overlapping intervals (...)'."""
    from .tables import LABEL

    by_rule: dict[str, list[str]] = {}
    for m in t.metrics:
        if m in t.rules:
            by_rule.setdefault(t.rules[m], []).append(LABEL[m])
    if not by_rule:
        return "Marks: no values to compare."
    return "Marks decided by: " + "; ".join(f"{', '.join(ms)}: {rule}" for rule, ms in by_rule.items()) + "."
