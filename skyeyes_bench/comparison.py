"""Paired comparison of two results files (`skyeyes-bench compare`): the same estimand for A, B
and A - B, its half-sampling interval (`stats`), and for per-frame metrics a Student-t summary
of per-cluster differences (`bayes`). Pure functions on results documents and arrays; the
command reads the files."""

from __future__ import annotations

import math

import numpy as np

from typing import Callable

from .bayes import hdi, student_t_posterior
from .metricspec import METRICS, sample_count_warning
from .registry import load_entry_point
from .seeds import add_seed_tests
from .stats import (INTERVAL_METHOD, advantage, advantage_interval, cluster_map, frame_metric_samples,
                    higher_is_better, interval_from_replicates, replicate_counts, replicate_draws,
                    set_metric_bootstrap, set_metric_samples, too_few)


#: What the Student-t summary describes (printed in compare's JSON beside its numbers).
BAYES_ESTIMAND = ("location mu of a Student-t model of the per-{unit} differences of the metric's per-{unit} "
                  "frame mean (advantage of A); the same quantity as the headline advantage when every {unit} "
                  "has as many frames and the differences are symmetric, but robust to one broken {unit}: it "
                  "may differ from the headline advantage when they are not")


#: Largest per-cluster difference the Student-t model is fitted to. Its priors span 1000 standard
#: deviations and emcee's moves square distances between walkers: differences of 1e80 overflowed
#: float64 there, and from about 1e154 emcee refused to start (a traceback in `compare`). Per-frame
#: metrics differ by less than 1e3, so nothing real comes near this bound.
BAYES_MAX_DIFFERENCE = 1e12


def _in_model_range(d: np.ndarray) -> bool:
    """Whether per-cluster differences d [K] are small enough for the Student-t sampler."""
    return bool(np.abs(d).max() <= BAYES_MAX_DIFFERENCE)


def bayes_summary(d: np.ndarray, *, unit: str = "scene", walkers: int, steps: int, burn: int, seed: int) -> dict:
    """Student-t posterior summary of per-cluster advantages d [K] (> 0: A better): P(A better)
    = P(mu > 0) and the 95% HDI of mu, or the reason there is none (too few clusters, infinite
    differences, zero variance)."""
    k = len(d)
    bayes: dict = {"fitted": False, "estimand": BAYES_ESTIMAND.format(unit=unit), "clusters": k}
    few = too_few(k, unit)
    n_inf = int(np.isinf(d).sum())
    if few:
        bayes.update(note=few, p_a_better=None, hdi=None)
    elif np.isnan(d).any():
        bayes.update(note=f"a {unit} has no value for one method", p_a_better=None, hdi=None)
    elif n_inf:
        bayes["note"] = (f"{n_inf} {unit}(s) have an infinite difference (one method reproduces every "
                         f"frame exactly, the other does not); a Student-t model of finite differences "
                         f"does not apply")
        bayes["p_a_better"] = 1.0 if (d > 0).all() else 0.0 if (d < 0).all() else None
        bayes["hdi"] = None
    elif not _in_model_range(d):
        bayes.update(note=f"a per-{unit} difference of {float(np.abs(d).max()):.3g} exceeds "
                          f"{BAYES_MAX_DIFFERENCE:.0e}, the largest the Student-t model is fitted to", p_a_better=None,
                     hdi=None)
    elif float(np.std(d)) <= 1e-12 * max(1.0, float(np.abs(d).max())):
        # Zero variance: every cluster differs by the same amount (identical methods: 0).
        # A Student-t posterior would collapse to a point (sigma -> 0); report that point.
        bayes.update(note=f"zero variance: every per-{unit} difference is equal; the posterior is a "
                          "point mass at that value (no sampling)",
                     mu_mean=float(d[0]), hdi=[float(d[0])] * 2,
                     p_a_better=0.5 if d[0] == 0 else float(d[0] > 0))
    else:
        post = student_t_posterior(d, walkers=walkers, steps=steps, burn=burn, seed=seed)
        bayes.update(fitted=True, mu_mean=float(post.mu.mean()), hdi=list(hdi(post.mu, 0.95)),
                     p_a_better=float(np.mean(post.mu > 0)), sigma_mean=float(post.sigma.mean()),
                     nu_median=float(np.median(post.nu)), acceptance=post.acceptance,
                     autocorr_steps=post.autocorr, kept_steps=post.kept_steps, warnings=list(post.warnings))
    return bayes


def compare_per_sequence(a: np.ndarray, b: np.ndarray, metric: str, *, resamples: int, level: float,
                         seed: int, walkers: int, steps: int, burn: int, unit: str = "sequence") -> dict:
    """Paired comparison of per-cluster values a [K], b [K] of one metric (same cluster order),
    each cluster weighted equally.

    Returns a JSON-able dict: mean advantage of A (> 0: A better), its half-sampling interval
    (None below MIN_CLUSTERS clusters, with the reason in `interval_note`), and the Student-t
    summary (`bayes_summary`)."""
    d = advantage(a, b, metric)
    k = len(d)
    mean = float(np.mean(d)) if not np.isnan(d).any() else math.nan
    out: dict = {"metric": metric, "higher_is_better": higher_is_better(metric), "clusters": k,
                 "advantage_mean": mean, "level": level, "bootstrap_interval": None}
    few = too_few(k, unit)
    if few:
        out["interval_note"] = few
    else:
        iv = advantage_interval(d, resamples=resamples, level=level, seed=seed)
        out["bootstrap_interval"] = list(iv) if iv else None
    out["bayes"] = bayes_summary(d, unit=unit, walkers=walkers, steps=steps, burn=burn, seed=seed)
    return out


# --------------------------------------------------------------------------- comparing results


def _shown(text, limit: int = 120) -> str:
    """A string read from a results file, for a one-line message: as it is when printable, else
    with its control characters and bidi overrides escaped; at most `limit` characters."""
    s = str(text)
    s = s if s.isprintable() else ascii(s)[1:-1]
    return s if len(s) <= limit else s[:limit - 3] + "..."


def _comparable(a: dict, b: dict, current_sha256: str | None = None) -> list[str]:
    """Why two results files cannot be compared (empty: they can). `current_sha256`: that of the
    protocol file installed now, whose statistics (resamples, seed, cluster unit) the comparison
    would use; it must be the one both results were scored with."""
    why = []
    pa, pb = a["protocol"], b["protocol"]
    if pa["ref"] != pb["ref"]:
        why.append(f"A was scored with protocol {_shown(pa['ref'])}, B with {_shown(pb['ref'])}: results of different "
                   f"protocols or protocol versions are not comparable")
    elif pa["sha256"] != pb["sha256"]:
        why.append(f"protocol {_shown(pa['ref'])} differs between A and B (sha256 {_shown(pa['sha256'][:12])}... vs "
                   f"{_shown(pb['sha256'][:12])}...): the protocol file changed between the runs")
    elif current_sha256 is not None and current_sha256 != pa["sha256"]:
        why.append(f"protocol {_shown(pa['ref'])} changed since A and B were scored (sha256 "
                   f"{_shown(pa['sha256'][:12])}... in both, {current_sha256[:12]}... now): compare would resample "
                   f"with another file's statistics")
    for ex in sorted(set(a.get("extractors", {})) | set(b.get("extractors", {}))):
        ea, eb = a["extractors"].get(ex, {}), b["extractors"].get(ex, {})
        if ea.get("weights_sha256") != eb.get("weights_sha256") and "ok" == ea.get("status") == eb.get("status"):
            why.append(f"extractor {_shown(ex)} used different weights (sha256 {_shown(ea.get('weights_sha256'))[:12]}"
                       f"... vs {_shown(eb.get('weights_sha256'))[:12]}...): features are not comparable")
    sa, sb = (d["dataset"].get("split", "test") for d in (a, b))
    if sa != sb:
        why.append(f"A was scored on the {_shown(sa)} split, B on the {_shown(sb)} split")
    if a["sha256"]["ground_truth"] != b["sha256"]["ground_truth"] or \
            a["dataset"]["sequences"] != b["dataset"]["sequences"]:
        why.append(f"A and B were scored against different ground truth (dataset {a['dataset']['name']!r} "
                   f"vs {b['dataset']['name']!r}, or its frames changed)")
    return why


#: Seconds before `compare_results(progress=True)` draws its bar (on a terminal only): a comparison of
#: results with many frame metrics runs emcee for each (half a minute on 2 cores), a small one is done
#: before a bar would be worth reading.
PROGRESS_DELAY_S = 2.0


#: What `compare` reports (also in its JSON as `estimand`).
COMPARE_ESTIMAND = ("A and B: each metric's value exactly as `evaluate` reports it (per-frame metrics: the mean over "
                    "all frames; set metrics: computed on all features); advantage: the difference of those two "
                    "values; its interval: paired half-sampling that draws the same clusters for A and B and "
                    "recomputes both values")


def _frames_problem(a: dict, b: dict, names: tuple[str, str]) -> str | None:
    """Why the frame records of two results cannot be paired (None: they can): every frame of A
    must be in B, and the other way round, in the same sequence with the same ground truth. The
    recorded ground-truth digests agree even when a record was renamed or dropped afterwards, and
    pairing would then fail on the missing frame (it was a KeyError)."""
    ka, kb = ({(r["scene"], r["file"]): r for r in d["frames"]} for d in (a, b))
    for (src, dst), (na, nb) in (((ka, kb), names), ((kb, ka), names[::-1])):
        gone = [k for k in src if k not in dst]
        if gone:
            more = f" (and {len(gone) - 1} more)" if len(gone) > 1 else ""
            return (f"{nb}: frame '{_shown(gone[0][0] + '/' + gone[0][1])}' of {na} is not in its field "
                    f"'frames'{more}: renamed or missing (A and B must score the same frames)")
    seqs = a["dataset"]["sequences"]  # equal in A and B (`_comparable`)
    for key, ra in ka.items():
        rb, frame = kb[key], f"'{_shown(key[0] + '/' + key[1])}'"
        if ra["sequence"] != rb["sequence"]:
            return (f"{names[1]}: frame {frame} is in sequence '{_shown(seqs[rb['sequence']])}', in {names[0]} in "
                    f"'{_shown(seqs[ra['sequence']])}'")
        if ra["gt_sha256"] != rb["gt_sha256"]:
            return (f"{names[1]}: frame {frame} was scored against other ground truth (gt_sha256 "
                    f"{_shown(rb['gt_sha256'][:12])}..., in {names[0]} {_shown(ra['gt_sha256'][:12])}...)")
    return None


def _set_centre(name: str, f: dict, protocol, seed: int) -> float | None:
    """A set metric's interval centre (`MetricDef.centre`) from one side's features; None for the
    metrics without one."""
    spec = METRICS.get(name)
    if spec is None or not spec.centre:
        return None
    return float(load_entry_point(spec.centre)(np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64),
                                                protocol.metric(name), seed))


def _usable_replicates(doc: dict, m: dict, st, unit: str, k: int) -> list | None:
    """A results file's stored replicates of one metric, if made the way this comparison resamples."""
    s = doc.get("statistics")
    s = s if isinstance(s, dict) else {}
    reps = m.get("replicates")
    same = (s.get("interval") == INTERVAL_METHOD and s.get("resamples") == st.bootstrap_resamples
            and s.get("seed") == st.seed and s.get("cluster") == unit and s.get("clusters") == k)
    return reps if same and isinstance(reps, list) and len(reps) == st.bootstrap_resamples else None


def _frame_values(doc: dict, name: str,
                  order: list[tuple[str, str]]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Per-frame values [N] of `name` (null -> NaN), sequence numbers [N] and, for a pixel-weighted
    metric, the pixel counts [N] (else None), in the frame order `order`."""
    by = {(r["scene"], r["file"]): r for r in doc["frames"]}
    rows = [by[key] for key in order]
    weights = None
    if name in METRICS and METRICS[name].weighted:
        weights = np.array([r[f"{name}_n"] for r in rows], dtype=np.float64)
    return (np.array([np.nan if r[name] is None else r[name] for r in rows], dtype=np.float64),
            np.array([r["sequence"] for r in rows], dtype=np.int64), weights)


def _check_comparable(a: dict, b: dict, names: tuple[str, str], count_note: str | None):
    """The protocol A and B were scored with, or UserError saying why they cannot be compared
    (with their sample counts when those differ, `count_note`)."""
    from .errors import UserError
    from .protocol import load_protocol

    why = _comparable(a, b)
    if why:
        raise UserError("cannot compare: " + "; ".join(why + ([count_note] if count_note else [])))
    try:
        protocol = load_protocol(a["protocol"]["ref"])
    except UserError as e:  # an id or version this installation lacks: say which file names it
        raise UserError(f"{names[0]}: field 'protocol.ref': {e}") from None
    why = _comparable(a, b, protocol.sha256) or [p for p in [_frames_problem(a, b, names)] if p]
    if why:  # e.g. a submission scored in part: its counts are said too
        raise UserError("cannot compare: " + "; ".join(why + ([count_note] if count_note else [])))
    return protocol


def _paired_frame_samples(a: dict, b: dict, name: str, order: list[tuple[str, str]], cl_of_seq: np.ndarray):
    """For the per-frame metric `name`: a function of cluster weights c [R, K] returning the
    metric's values (A [R], B [R]) with the frames weighted by their cluster's weight."""
    fa, seq, wa = _frame_values(a, name, order)
    fb, _, wb = _frame_values(b, name, order)
    clusters = cl_of_seq[seq]
    pool = METRICS[name].pool if name in METRICS else "mean"

    def samples(f, w, c):
        return frame_metric_samples(f, clusters, c, w, pool)

    return lambda c: (samples(fa, wa, c), samples(fb, wb, c))


def _set_replicates(name: str, a: dict, b: dict, sidecars: Callable[[], tuple], protocol,
                    cl_of_seq: np.ndarray, k: int, counts: np.ndarray) -> tuple | None:
    """Paired replicates (A, B) of the set metric `name` and the centres of both intervals (None
    where unknown): the results' stored replicates when made the way this comparison resamples
    (the centres from the features for an older file without them), else resampled from the
    features sidecars; None when there are neither. `sidecars()` gives the features of A and B
    (each None where absent); it is called only here, when they are needed."""
    st, unit = protocol.statistics, protocol.statistics.cluster
    ma, mb = a["metrics"][name], b["metrics"][name]
    ra, rb = _usable_replicates(a, ma, st, unit, k), _usable_replicates(b, mb, st, unit, k)
    ex = ma["extractor"]

    def have() -> tuple | None:
        fa, fb = sidecars()
        return (fa, fb) if fa is not None and fb is not None and ex in fa and ex in fb else None

    if ra is not None and rb is not None:
        reps = tuple(np.array([np.nan if v is None else v for v in x], np.float64) for x in (ra, rb))
        centres = (ma.get("interval_centre"), mb.get("interval_centre"))
        has_centre = name in METRICS and bool(METRICS[name].centre)  # else `_set_centre` gives None anyway
        if None in centres and has_centre and (feats := have()):  # an older file without it: from the features
            centres = tuple(_set_centre(name, f[ex], protocol, st.seed) for f in feats)
        return reps, centres
    feats = have()
    if feats is None:
        return None
    feats_a, feats_b = feats
    reps = []
    for f in (feats_a[ex], feats_b[ex]):
        cl = cl_of_seq[np.asarray(f["seq"], np.int64)]
        fn = set_metric_bootstrap(name, f["sub"], f["gt"], cl, k, protocol.metric(name), st.seed)
        reps.append(set_metric_samples(fn, cl, cl, counts))
    return reps, tuple(_set_centre(name, f[ex], protocol, st.seed) for f in (feats_a, feats_b))


def _add_interval(r: dict, name: str, adv: float, reps, centres: tuple, level: float, k: int) -> None:
    """Into the comparison `r` of one metric: the interval of the advantage `adv` from the paired
    replicates `reps` (A, B), centred on the advantage of the two intervals' centres when both
    are known, and P(A better) over the replicates."""
    d = advantage(reps[0], reps[1], name)
    centre = None
    if None not in centres:  # both intervals' centres: the difference's is their advantage
        centre = float(advantage(np.array([centres[0]], np.float64), np.array([centres[1]], np.float64),
                                 name)[0])
        r["interval_centre"] = centre
    iv = interval_from_replicates(adv, d, level, k, centre)
    if iv is not None:
        r["bootstrap_interval"] = [iv[0], iv[1]]
        r["interval_widened"] = iv[2]
        r["p_a_better_bootstrap"] = float(np.mean(replicate_draws(adv if centre is None else centre, d, k) > 0))


def compare_results(a: dict, b: dict, feats_a: dict | None = None, feats_b: dict | None = None,
                    *, emcee_steps: int | None = None, names: tuple[str, str] = ("A", "B"),
                    sidecars: Callable[[], tuple] | None = None, progress: bool = False) -> dict:
    """Paired comparison of two results of the same protocol and ground truth, metric by metric.

    One estimand for A, B and A - B (`COMPARE_ESTIMAND`): A and B are the values `evaluate`
    reported, the advantage is their difference (> 0: A better), and its interval comes from
    paired half-sampling of clusters (the protocol's `[statistics] cluster`): the same clusters
    for A and B in each replicate, both values recomputed (per-frame metrics from the frames, set
    metrics from the stored `replicates` or else the features sidecars). Below MIN_CLUSTERS
    clusters there is no interval and no P(better) ("too few scenes (K=2)"). Per-frame metrics
    also get the Student-t summary of per-cluster differences (`bayes_summary`; its `estimand`
    says what it describes). When both results carry a `seeds` block (`reproduce --seeds N`),
    each compared metric also gets a t test on the seeds' headline values (`seeds.seed_test`: paired
    by seed when both ran the same seeds, else Welch's; under `metrics[m]["seeds"]`); `out["seeds"]` names the seeds,
    or says that only one has them.

    `names`: how messages name A and B (`compare` passes the two files).
    `sidecars`: instead of `feats_a`, `feats_b`, a function giving both (each None where absent),
    called at most once and only when a set metric has no usable stored replicates (results
    written by this version carry them, so their sidecars are never read).
    `progress`: a progress bar on stderr, drawn only on a terminal and after `PROGRESS_DELAY_S`.

    Raises:
        UserError: the results are not comparable (the message says why).
    """
    count_note = sample_count_warning([(names[0], a["metrics"]), (names[1], b["metrics"])])
    protocol = _check_comparable(a, b, names, count_note)
    files = names
    st = protocol.statistics
    steps = emcee_steps or st.emcee_steps
    burn = min(st.emcee_burn, steps // 3) if emcee_steps else st.emcee_burn
    unit = st.cluster
    seq_ids = a["dataset"]["sequences"]
    cl_of_seq, names = cluster_map(seq_ids, unit)
    k = len(names)
    few = too_few(k, unit)
    counts = None if few else replicate_counts(k, st.bootstrap_resamples, st.seed)
    order = sorted(((r["scene"], r["file"]) for r in a["frames"]))
    out = {"protocol": a["protocol"]["ref"], "a": a["submission"].get("method"), "b": b["submission"].get("method"),
           "cluster": unit, "clusters": k, "sequences": len(seq_ids), "too_few": few,
           "interval": INTERVAL_METHOD, "level": st.interval, "estimand": COMPARE_ESTIMAND,
           "sign": "advantage of A: A - B where higher is better, B - A where lower is better; > 0 means A is better",
           "metrics": {}}
    if count_note:  # the same frames and protocol leave no way to this today; a guard, said once
        out["warnings"] = [count_note]
    loaded: list[tuple] = []  # the sidecars, read once on first need

    def features() -> tuple:
        if not loaded:
            loaded.append(sidecars() if sidecars is not None else (feats_a, feats_b))
        return loaded[0]

    from .results import progress_bar

    bar = progress_bar(progress, total=len(a["metrics"]), desc="compare", unit="metric", delay=PROGRESS_DELAY_S)
    with bar:
        for name, ma in a["metrics"].items():
            _compare_metric(out, name, ma, a, b, features, protocol, st, unit, k, few, counts, order, cl_of_seq,
                            steps, burn)
            bar.update(1)
    add_seed_tests(out, a, b, files, st.interval)  # runs of several seeds (`reproduce --seeds N`)
    return out


def _compare_metric(out: dict, name: str, ma: dict, a: dict, b: dict, features, protocol, st, unit: str, k: int,
                    few, counts, order, cl_of_seq, steps: int, burn: int) -> None:
    """Into `out["metrics"][name]`: the comparison of metric `name` (`compare_results`)."""
    mb = b["metrics"].get(name)
    if ma.get("reference") or (name in METRICS and METRICS[name].reference):
        out["metrics"][name] = {"status": "skipped", "a": ma.get("value"), "note": f"{name} is a property of the "
                                "ground truth (the same for A and B): reported, not compared"}
        return
    if mb is None or ma["status"] != "ok" or mb["status"] != "ok":
        out["metrics"][name] = {"status": "skipped", "note": f"{name} unavailable in "
                                f"{'A' if ma['status'] != 'ok' else 'B'}"}
        return
    va, vb = float(ma["value"]), float(mb["value"])
    adv = float(advantage(np.array([va]), np.array([vb]), name)[0])
    r: dict = {"status": "ok", "metric": name, "kind": ma["kind"], "higher_is_better": higher_is_better(name),
               "a": va, "b": vb, "advantage": adv, "level": st.interval, "bootstrap_interval": None,
               "p_a_better_bootstrap": None}
    reps = None
    centres = (None, None)  # set metrics with random subsets (FD∞): their intervals' centres
    if ma["kind"] == "frame":
        samples = _paired_frame_samples(a, b, name, order, cl_of_seq)
        d = advantage(*samples(np.eye(k)), name)
        r["bayes"] = bayes_summary(d, unit=unit, walkers=st.emcee_walkers, steps=steps, burn=burn, seed=st.seed)
        if counts is not None:
            reps = samples(counts)
    else:
        r["bayes"] = {"fitted": False, "p_a_better": None, "hdi": None,
                      "note": f"set metric: no per-{unit} values; paired resampling only"}
        if counts is not None:
            got = _set_replicates(name, a, b, features, protocol, cl_of_seq, k, counts)
            if got is None:
                out["metrics"][name] = {"status": "skipped", "a": va, "b": vb, "advantage": adv,
                                        "note": "no replicates of the same resampling in the results and no "
                                                "features sidecars: set metrics are compared by resampling"}
                return
            reps, centres = got
    if few:
        r["interval_note"] = few
    else:
        _add_interval(r, name, adv, reps, centres, st.interval, k)
    r["advantage_mean"] = adv  # the name older readers use; the same number
    out["metrics"][name] = r
