"""Results files: a complete set of per-frame values and features -> results (`finalize`),
shards -> results (`merge`), and reading / writing the JSON and its features sidecar.

A results file is JSON (schema `skyeyes-bench/results@1`, docs/evaluate.md) with a sidecar
`<stem>.features.npz` holding the per-sequence features (submission and ground truth) of every
set-metric extractor, so intervals of FID/KID/FVD/KVD and paired comparisons can be recomputed
by resampling clusters (scenes or sequences, as the protocol says); each metric also carries
its half-sampling replicates, so two results pair without the sidecars. Partial (shard) files, `skyeyes-bench/partial@1`, have the same two
parts. `skyeyes_bench.evaluate` computes what goes in and re-exports the names here.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import fields, inputfiles, outputfiles, outputunit, stats
from .errors import UserError, ValidationError, single_line
from .metricspec import FRAME_METRICS, METRICS, metric_def
from .registry import load_entry_point

RESULTS_FORMAT = "skyeyes-bench/results@1"
PARTIAL_FORMAT = "skyeyes-bench/partial@1"


# --------------------------------------------------------------------------- small helpers


def _tqdm(progress: bool, **kw):
    """A progress bar on stderr, drawn only when stderr is a terminal (disable=None: tqdm's TTY test)."""
    from tqdm import tqdm

    return tqdm(disable=None if progress else True, file=sys.stderr, leave=False, **kw)


@contextlib.contextmanager
def _stage(timing: dict, name: str):
    t0 = time.perf_counter()
    yield
    timing[name] = round(timing.get(name, 0.0) + time.perf_counter() - t0, 4)


def _digest(lines: list[str]) -> str:
    return hashlib.sha256("".join(sorted(lines)).encode()).hexdigest()


def features_path(results_path: Path) -> Path:
    """`results.json` -> `results.features.npz` (the sidecar beside it)."""
    p = Path(results_path)
    stem = p.name[: -len(".json")] if p.name.endswith(".json") else p.name
    return p.with_name(stem + ".features.npz")


def default_out(submission_dir, shard: tuple[int, int] | None = None) -> Path:
    """`sub/` -> `sub.results.json` beside the folder (never inside it: that would be an extra file)."""
    sub = Path(submission_dir).resolve()
    tail = f".shard-{shard[0]}-of-{shard[1]}" if shard else ""
    return sub.with_name(f"{sub.name}{tail}.results.json")


# --------------------------------------------------------------------------- summary


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
    k_seq = len(seq_ids)
    frames = sorted(doc["frames"], key=lambda r: (r["sequence"], r["index"]))
    seqs = np.array([r["sequence"] for r in frames], dtype=np.int64)
    # The resampling unit: scenes (all sequences of a lane share one fitted model) or, for
    # protocols that say so (synthtown@1), sequences.
    cl_of_seq, cluster_names = stats.cluster_map(seq_ids, st.cluster)
    k = len(cluster_names)
    clusters = cl_of_seq[seqs]
    few = stats.too_few(k, st.cluster)
    counts = None if few else stats.replicate_counts(k, st.bootstrap_resamples, st.seed)
    res = dict(doc)
    res["format"] = RESULTS_FORMAT
    res["frames"] = frames
    res["sha256"] = {
        "submission_frames": _digest([f"{r['scene']}/{r['file']} {r['sha256']}\n" for r in frames]),
        "ground_truth": _digest([f"{r['scene']}/{r['file']} {r['gt_sha256']}\n" for r in frames]),
    }
    res["statistics"] = {
        "method": f"half-sampling of {st.cluster}s without replacement (paired submission/ground truth): each "
                  f"replicate recomputes the metric on {k // 2} of the {k} {st.cluster}s",
        "cluster": st.cluster, "clusters": k, "cluster_ids": cluster_names, "min_clusters": stats.MIN_CLUSTERS,
        "too_few": few, "resamples": st.bootstrap_resamples, "level": st.interval, "seed": st.seed,
        "interval": stats.INTERVAL_METHOD, "half_size": k // 2, "scale": stats.half_scale(k) if k >= 2 else None}

    def summarise(value: float, replicates: np.ndarray | None, floor: float | None = None,
                  centre: float | None = None) -> dict:
        """interval (null + reason below MIN_CLUSTERS; clipped at the metric's `floor`; about
        `centre` when the metric has one), replicates (6 significant digits)."""
        if replicates is None:
            return {"interval": None, "interval_note": few, "replicates": None}
        out: dict = {"replicates": stats.round_replicates(replicates)}
        if centre is not None and math.isfinite(centre):
            out["interval_centre"] = centre
        iv = stats.interval_from_replicates(value, replicates, st.interval, k, centre)
        if iv is None:
            out.update(interval=None, interval_note="no replicate is defined")
        else:
            # clipped at the floor, but never above the value (FID∞ extrapolates and may lie below 0)
            out["interval"] = [iv[0] if floor is None else max(iv[0], min(floor, value)), iv[1]]
            if iv[2]:
                out["interval_note"] = ("interval widened to contain the value: the half-sample draws lie on one "
                                        "side of it (a small-sample bias of this metric larger than its spread)")
        return out

    metrics: dict[str, dict] = {}
    per_seq: dict[str, dict] = {sid: {"frames": int((seqs == i).sum())} for i, sid in enumerate(seq_ids)}
    # over: means of values near 1e308 (only a hostile part holds them) are +-inf, without a warning
    with _stage(timing, "bootstrap_s"), np.errstate(over="ignore"):
        for name in FRAME_METRICS:
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
            reps = None if counts is None else stats.frame_metric_samples(v, clusters, counts, w, spec.pool)
            metrics[name] = {"status": "ok", "kind": "frame", "value": value, "level": st.interval,
                             "higher_is_better": spec.higher_is_better, "n": int(len(v)),
                             **summarise(value, reps)}
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
    timing.setdefault("set_metrics_s", 0.0)
    for m in protocol.metrics:
        spec = metric_def(m.name)
        if spec.kind != "set":
            continue
        if m.name in doc["unavailable"]:
            metrics[m.name] = {"status": "unavailable", **doc["unavailable"][m.name]}
            continue
        f = features[m.extractor]
        xs, xg = np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64)
        cl = cl_of_seq[np.asarray(f["seq"], np.int64)]
        if len(xs) < spec.min_rows:
            what = "clips" if spec.features == "clip" else "frames"
            metrics[m.name] = {"status": "unavailable", "reason": f"{len(xs)} {what} of {m.clip_length or 1} "
                               f"frames; need at least {spec.min_rows}",
                               "fix": "sequences must hold at least clip_length frames"}
            continue
        with _stage(timing, "set_metrics_s"):
            value = float(load_entry_point(spec.estimator)(xs, xg, m, st.seed))
        reps = centre = None
        if counts is not None:
            with _stage(timing, "bootstrap_s"):
                if spec.centre:  # an estimate with random subsets: its interval's centre (MetricDef.centre)
                    centre = float(load_entry_point(spec.centre)(xs, xg, m, st.seed))
                fn = stats.set_metric_bootstrap(m.name, xs, xg, cl, k, m, st.seed)
                bar = _tqdm(progress, total=len(counts), desc=f"resample {m.name}", unit="replicate")
                with bar:
                    reps = stats.set_metric_samples(fn, cl, cl, counts, progress=bar.update)
        metrics[m.name] = {"status": "ok", "kind": "set", "value": value, "level": st.interval,
                           "higher_is_better": spec.higher_is_better, "n": int(len(xs)),
                           "extractor": m.extractor, "unit": "clip" if spec.features == "clip" else "frame",
                           **summarise(value, reps, spec.lower_bound, centre)}
    res["metrics"] = {name: metrics[name] for name in protocol.metric_names if name in metrics}
    res["sequences"] = per_seq
    res.pop("unavailable", None)
    return res


# --------------------------------------------------------------------------- I/O


#: What `--force` may replace (`outputfiles.OutputKind`): an earlier results file (final or partial)
#: and its features sidecar (any zip: one without arrays starts PK\x05\x06).
RESULTS_OUTPUT = outputfiles.OutputKind("a results file", formats=(RESULTS_FORMAT, PARTIAL_FORMAT))
FEATURES_OUTPUT = outputfiles.OutputKind("a features sidecar", magic=b"PK")


def write_results(out: Path, doc: dict, features: dict) -> None:
    """Write the results JSON `out` and its features sidecar as one unit (`outputunit.write_unit`: both
    to temporary names, the sidecar renamed in first and the results last; callers hold the
    output's lock), so two runs never mix their files and a killed run is repeated without
    --force. The sidecar's bytes depend on the features alone (`outputunit.npz_bytes`), so a repeated
    run writes the same file."""
    fpath = features_path(out)
    arrays = {f"{ex_id}|{part}": np.asarray(f[part]) for ex_id, f in features.items() for part in ("sub", "gt", "seq")}
    blob = outputunit.npz_bytes(arrays)
    doc["features"] = {"file": fpath.name, "sha256": inputfiles.sha256_bytes(blob)}
    outputunit.write_unit(out, outputfiles.json_bytes(doc), {fpath: blob})


_RESULTS_SHAPE = {
    "format": str,
    "protocol": {"ref": str, "sha256": str},
    "dataset": {"name": str, "sequences": [str]},
    "submission": {"method": fields.Optional(str)},
    "extractors": {str: {"kind": str, "dim": int}},
    "frames": [{"scene": str, "file": str, "sequence": int, "index": int, "sha256": str, "gt_sha256": str}],
}
_FINAL_SHAPE = {
    "metrics": {str: {"status": str}},
    "sequences": {str: {str: fields.Optional(fields.Number)}},
    "sha256": {"ground_truth": str, "submission_frames": str},
}
_PARTIAL_SHAPE = {"shard": fields.Optional({"index": int, "count": int}),
                  "unavailable": {str: {"reason": str, "fix": str}}}


def _not_nan(where: str, value) -> None:
    """Results never hold NaN (an undefined value is null); +-inf is allowed (PSNR of exact frames)."""
    if isinstance(value, float) and math.isnan(value):
        fields.fail(where, "expected a number or null, got NaN (results write an undefined value as null)")


def _q(text: str) -> str:
    """A name read from a file, quoted for a one-line message (newlines, bidi overrides escaped)."""
    return fields._short(text, 120)


def _results_problem(doc: dict, path: Path, partial: bool) -> None:
    """Raise a one-line UserError at the first field of a results (or partial) file that this
    version cannot use: wrong type, missing, NaN, a frame listed twice, or an index outside what
    the file itself holds."""
    fields.conform(str(path), doc, {**_RESULTS_SHAPE, **(_PARTIAL_SHAPE if partial else _FINAL_SHAPE)})
    n_seq = len(doc["dataset"]["sequences"])
    seen: dict[tuple[str, str], int] = {}
    for i, r in enumerate(doc["frames"]):
        fields.integer(f"{path}: field 'frames[{i}].sequence'", r["sequence"], "a sequence number", 0, n_seq - 1)
        key = (r["scene"], r["file"])
        if key in seen:  # pairing (compare) and merging go by frame: one record each
            fields.fail(f"{path}: field 'frames[{i}]'",
                        f"frame {_q(key[0] + '/' + key[1])} is listed twice (also frames[{seen[key]}])")
        seen[key] = i
        for name in FRAME_METRICS:
            if name in r:
                weighted = metric_def(name).weighted  # a value per region, null when the region is empty
                fields.conform(str(path), r[name], fields.Optional(fields.Number) if weighted else fields.Number,
                               f"frames[{i}].{name}")
                _not_nan(f"{path}: field 'frames[{i}].{name}'", r[name])
                if weighted:
                    fields.integer(f"{path}: field 'frames[{i}].{name}_n'", r.get(f"{name}_n"),
                                   "the frame's pixel count of the region")
    shard = doc.get("shard")
    if partial and shard is not None:  # a shard holds at least one sequence: N <= sequences
        fields.integer(f"{path}: field 'shard.count'", shard["count"], "the number of shards", 1, max(n_seq, 1))
        fields.integer(f"{path}: field 'shard.index'", shard["index"], "the shard's number", 0, shard["count"] - 1)
    if not partial:
        if not isinstance(doc.get("statistics", {}), dict):
            fields.fail(f"{path}: field 'statistics'", f"expected an object, got {fields._short(doc['statistics'])}")
        for name, m in doc["metrics"].items():
            if m["status"] == "ok":
                fields.conform(str(path), m, {"kind": str, "value": fields.Number}, f"metrics.{name}")
                _not_nan(f"{path}: field 'metrics.{name}.value'", m["value"])
                if m.get("interval_centre") is not None:  # FD∞: the value with its subset noise averaged out
                    fields.conform(str(path), m, {"interval_centre": fields.Number}, f"metrics.{name}")
                    _not_nan(f"{path}: field 'metrics.{name}.interval_centre'", m["interval_centre"])
                # interval: [lo, hi], or null with the reason (too few clusters); replicates likewise
                for key, shape in (("interval", [fields.Number]), ("replicates", [fields.Optional(fields.Number)])):
                    if m.get(key) is not None:
                        fields.conform(str(path), m[key], shape, f"metrics.{name}.{key}")
                        for j, v in enumerate(m[key]):
                            _not_nan(f"{path}: field 'metrics.{name}.{key}[{j}]'", v)
                if m["kind"] not in ("frame", "set"):
                    fields.fail(f"{path}: field 'metrics.{name}.kind'",
                                f"expected 'frame' or 'set', got {fields._short(m['kind'])}")
                if m["kind"] == "frame":  # compared per sequence: every sequence holds a value
                    # (pixel-weighted metrics: null where the sequence has no pixel of the region)
                    weighted = name in METRICS and METRICS[name].weighted
                    seq_shape = fields.Optional(fields.Number) if weighted else fields.Number
                    for sid in doc["dataset"]["sequences"]:
                        fields.conform(str(path), doc["sequences"].get(sid), {name: seq_shape}, f"sequences.{sid}")
                        _not_nan(f"{path}: field 'sequences.{sid}.{name}'", doc["sequences"][sid][name])
                    # ... and compared per frame: every frame holds one too (a metric this version
                    # does not know is checked here, the known ones above)
                    for i, r in enumerate(doc["frames"]):
                        fields.conform(str(path), r, {name: seq_shape}, f"frames[{i}]")
                        _not_nan(f"{path}: field 'frames[{i}].{name}'", r[name])
                if m["kind"] == "set":
                    fields.conform(str(path), m, {"extractor": str}, f"metrics.{name}")


def _read_sidecar(fpath: Path, doc: dict, path: Path) -> dict[str, dict[str, np.ndarray]]:
    """The features sidecar, checked against the results file before any array is trusted: only
    stored (uncompressed) .npy members, so no member can inflate past the file's own size."""
    import zipfile

    try:
        with inputfiles.open_regular(fpath) as fh, zipfile.ZipFile(fh) as zf:
            for info in zf.infolist():
                if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                    raise UserError(f"{fpath}: member {info.filename!r} is not a stored .npy array (expected "
                                    f"the sidecar `evaluate` writes)")
        out: dict[str, dict[str, np.ndarray]] = {}
        with np.load(fpath, allow_pickle=False) as z:
            for key in z.files:
                ex_id, _, part = key.rpartition("|")
                out.setdefault(ex_id, {})[part] = z[key]
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, MemoryError) as e:
        raise UserError(f"{fpath}: not a features sidecar ({single_line(e)})") from None
    n_seq = len(doc["dataset"]["sequences"])
    for ex_id, f in out.items():
        info = doc["extractors"].get(ex_id)
        where = f"{fpath}: array '{ex_id}"
        if info is None:
            raise UserError(f"{where}|...': extractor not listed in {path.name}'s field 'extractors'")
        sub, gt, seq = f.get("sub"), f.get("gt"), f.get("seq")
        if any(a is None for a in (sub, gt, seq)):
            raise UserError(f"{where}|sub|gt|seq': one of the three arrays is missing")
        for part, a in (("sub", sub), ("gt", gt)):
            if a.dtype.kind != "f" or a.ndim != 2 or a.shape[1] != info["dim"] or len(a) != len(seq):
                raise UserError(f"{where}|{part}': expected float [{len(seq)}, {info['dim']}], got {a.dtype} "
                                f"{list(a.shape)}")
        if seq.dtype.kind not in "iu" or seq.ndim != 1 or (len(seq) and not (0 <= seq.min() and seq.max() < n_seq)):
            raise UserError(f"{where}|seq': expected sequence numbers in 0..{n_seq - 1}")
        for part, a in (("sub", sub), ("gt", gt)):
            if not np.isfinite(a).all():  # a network's features are finite; NaN broke the eigensolvers
                raise UserError(f"{where}|{part}': holds NaN or infinite values (expected the features `evaluate` "
                                f"writes)")
    return out


def read_results(path, *, features: bool = False, partial: bool = False) -> tuple[dict, dict | None]:
    """Read a results (or partial) JSON and optionally its features sidecar (sha256-checked).
    Every field used later is checked here; a bad one is a one-line UserError naming it."""
    path = Path(path)
    doc = inputfiles.read_json(path, allow_nan=True)  # a perfect frame's PSNR is Infinity
    want = PARTIAL_FORMAT if partial else RESULTS_FORMAT
    if not isinstance(doc, dict) or doc.get("format") != want:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise UserError(f"{path}: field 'format' is {fields._short(got)}, expected {want!r}")
    _results_problem(doc, path, partial)
    if not features:
        return doc, None
    info = doc.get("features") or {}
    if not isinstance(info, dict):
        raise UserError(f"{path}: field 'features' must be an object")
    name = info.get("file", features_path(path).name)
    if name != features_path(path).name:  # the name `evaluate` derives from `path` is fine whatever it holds
        fields.name(f"{path}: field 'features.file'", name, "the sidecar's file name beside it")
    fpath = path.with_name(name)
    if not fpath.is_file():
        raise UserError(f"{fpath}: features sidecar of {path.name} missing (needed to resample set metrics)")
    if info.get("sha256") and inputfiles.sha256_file(fpath) != info["sha256"]:
        raise UserError(f"{fpath}: sha256 differs from the one recorded in {path.name} (file changed)")
    return doc, _read_sidecar(fpath, doc, path)


# --------------------------------------------------------------------------- merge


def _with_device(extractors) -> dict:
    """`extractors` with the `device` of each entry that names a network (`kind`) made explicit:
    parts written before `evaluate --device` existed carry none, and all of those ran on the CPU."""
    return {ex: {**info, "device": info.get("device", "cpu")} if isinstance(info, dict) and "kind" in info else info
            for ex, info in (extractors or {}).items()}


def _frame_records_problems(loaded: list[tuple[Path, dict, dict]]) -> list[str]:
    """What is wrong with the frame records (and feature rows) of parts that otherwise belong
    together: each frame in one part only, of a sequence of that part's shard and of its own scene;
    every frame metric the protocol asks for in every record (or listed unavailable); and all the
    records together the frames of the submission every part was scored from: their digest must
    equal `submission.frames_sha256`, which `evaluate` computes from the submitted files."""
    from .protocol import load_protocol

    first = loaded[0][1]
    seq_ids = first["dataset"]["sequences"]
    n = first["shard"]["count"]
    problems: list[str] = []
    owner: dict[tuple[str, str], Path] = {}
    for p, d, feats in loaded:
        mine = d["shard"]["index"]
        own: list[str] = []  # this part's problems; the first is reported (one edit, one line)
        for i, r in enumerate(d["frames"]):
            key, sid = (r["scene"], r["file"]), seq_ids[r["sequence"]]
            where = f"{p}: field 'frames[{i}]' (frame {_q(key[0] + '/' + key[1])})"
            if r["sequence"] % n != mine:
                own.append(f"{where}: of sequence {_q(sid)}, which shard {mine}/{n} does not score")
            elif stats.scene_of(sid) != r["scene"]:
                own.append(f"{where}: not in scene {_q(stats.scene_of(sid))} of its sequence {_q(sid)}")
            elif key in owner:
                own.append(f"{where}: also in {owner[key]}")
            owner.setdefault(key, p)
        records = np.bincount(np.array([r["sequence"] for r in d["frames"]], dtype=np.int64),
                              minlength=len(seq_ids))
        for ex_id, f in feats.items():
            other = f["seq"][f["seq"] % n != mine]
            rows = np.bincount(f["seq"], minlength=len(seq_ids))
            if len(other):
                own.append(f"{features_path(p)}: array {_q(ex_id + '|seq')} holds rows of sequence "
                           f"{_q(seq_ids[int(other[0])])}, which shard {mine}/{n} does not score")
            elif d["extractors"][ex_id].get("kind") == "image" and (rows != records).any():
                # one feature row per scored frame: a record added or removed afterwards shows here
                k = int(np.flatnonzero(rows != records)[0])
                own.append(f"{p}: field 'frames' holds {records[k]} records of sequence {_q(seq_ids[k])}, but "
                           f"{features_path(p).name} holds features of {rows[k]} of its frames: records were "
                           f"added or removed")
        problems += own[:1]
    if problems:
        return problems
    protocol = load_protocol(first["protocol"]["ref"])
    unavailable = {k for _, d, _ in loaded for k in d["unavailable"]}
    wanted = [name for name in FRAME_METRICS if protocol.metric(name) and name not in unavailable]
    for p, d, _ in loaded:
        for i, r in enumerate(d["frames"]):
            lack = [name for name in wanted if name not in r]
            if lack:
                return [f"{p}: field 'frames[{i}].{lack[0]}' missing (protocol {protocol.ref} scores it and the part "
                        f"does not list it unavailable)"]
    want = first["submission"].get("frames_sha256")
    got = _digest([f"{r['scene']}/{r['file']} {r['sha256']}\n" for _, d, _ in loaded for r in d["frames"]])
    if want is not None and got != want:
        return [_edited_part(loaded, want, got)]
    return []


def _edited_part(loaded: list[tuple[Path, dict, dict]], want: str, got: str) -> str:
    """The one line that says which part's frame records do not add up to the submission. When a
    part's submission folder is here, each record's sha256 is checked against the file it names
    (only regular files inside that folder) and the first part that differs is named; else every
    part is, as one of them."""
    for p, d, _ in loaded:
        folder = d["submission"].get("path")
        if not (isinstance(folder, str) and folder and Path(folder, "submission.json").is_file()):
            continue
        for i, r in enumerate(d["frames"]):
            where = f"{p}: field 'frames[{i}]' (frame {_q(r['scene'] + '/' + r['file'])})"
            try:
                with inputfiles.open_regular(Path(folder, r["scene"], r["file"]), root=folder) as fh:
                    if os.fstat(fh.fileno()).st_size > _MAX_FRAME_BYTES:
                        continue
                    h = hashlib.sha256()
                    while block := fh.read(1 << 20):
                        h.update(block)
                    sha = h.hexdigest()
            except UserError:
                return (f"{where}: no such frame in the submission {_q(folder)} it was scored from: the record "
                        f"was edited")
            if sha != r["sha256"]:
                return (f"{where}: sha256 {ascii(r['sha256'][:12])[1:-1]}... recorded, {sha[:12]}... in the submission "
                        f"{_q(folder)}: the record was edited")
    names = ", ".join(str(p) for p, _, _ in loaded)
    return (f"merge: the frame records of one of {names} were edited: together they hash to {got[:12]}..., not to "
            f"the {want[:12]}... of the submission every part records (field 'submission.frames_sha256')")


#: A submitted frame is an 8-bit PNG; a larger file named by a part is not hashed (it is not one).
_MAX_FRAME_BYTES = 1 << 30


def merge(parts, out=None, *, force: bool = False, progress: bool = True) -> dict:
    """Merge the partial results of `evaluate --shard I/N` (all N of them) into results that
    equal an unsharded run. Parts whose features were computed on different device types
    (`extractors.<id>.device`; absent = "cpu") are refused: the merged file records one device."""
    out = Path(out) if out is not None else None
    # Neither the results nor their sidecar may be a part or a part's sidecar (`--out p0` would
    # write p0.features.npz, part p0.json's sidecar); --force replaces only earlier results.
    inputs = [*map(Path, parts), *(features_path(Path(p)) for p in parts if Path(p).name)]

    def check_out() -> None:
        outputfiles.check_output(out, force=force, sidecars=[features_path(out)], inputs=inputs,
                            inputs_are="the parts being merged (or their sidecars)", kind=RESULTS_OUTPUT,
                            sidecar_kind=FEATURES_OUTPUT)

    if out is not None:
        if not out.name:  # '.', '/': no file name to put the sidecar beside
            raise UserError(f"{out}: is a folder; expected the path of an output file")
        check_out()  # before any work
    if not parts:
        raise UserError("merge: no partial results given")
    loaded = [(Path(p), *read_results(p, features=True, partial=True)) for p in parts]
    first_path, first, _ = loaded[0]
    problems = []
    for key in ("protocol", "dataset", "submission", "extractors"):
        for p, d, _ in loaded[1:]:
            a, b = first.get(key), d.get(key)
            if key == "submission":  # the folder may sit at a different path on each machine
                a, b = ({k: v for k, v in (x or {}).items() if k != "path"} for x in (a, b))
            if key == "dataset":
                a, b = ({k: v for k, v in (x or {}).items() if k != "root"} for x in (a, b))
            if key == "extractors":
                a, b = _with_device(a), _with_device(b)
                other = next((ex for ex in a if "device" in a[ex] and "device" in b.get(ex, {})
                              and a[ex]["device"] != b[ex]["device"]), None)
                if other is not None:  # one line that says what differs, not just 'extractors differs'
                    problems.append(f"{p}: extractor {other} ran on {b[other]['device']}, in {first_path.name} on "
                                    f"{a[other]['device']}: shards scored on different devices are not merged (GPU "
                                    f"features agree with CPU ones only to float rounding); score every shard with "
                                    f"the same --device")
                    continue
            if key == "submission" and a.get("frames_sha256") != b.get("frames_sha256"):
                problems.append(f"{p}: field 'submission.frames_sha256' differs from {first_path.name}'s: the "
                                f"parts scored different frames (not the same submission)")
            elif a != b:
                problems.append(f"{p}: field '{key}' differs from {first_path.name}'s")
    n = (first.get("shard") or {}).get("count")
    seen: dict[int, Path] = {}
    for p, d, _ in loaded:
        s = d.get("shard")
        if not s or s.get("count") != n:
            problems.append(f"{p}: shard {s} is not one of {n} shards")
            continue
        if s["index"] in seen:
            problems.append(f"{p}: shard {s['index']}/{n} given twice (also {seen[s['index']]})")
        seen[s["index"]] = p
    if n is not None and len(seen) == len(loaded):
        missing = sorted(set(range(n)) - set(seen))
        if missing:
            problems.append(f"merge: shards {', '.join(f'{i}/{n}' for i in missing)} missing")
    if problems:
        raise ValidationError("merge", problems)
    problems = _frame_records_problems(loaded)
    if problems:
        raise ValidationError("merge", problems)
    doc = dict(first)
    doc["extractors"] = _with_device(first["extractors"])  # one device, named even by older parts
    doc["frames"] = [r for _, d, _ in loaded for r in d["frames"]]
    doc["unavailable"] = {k: v for _, d, _ in loaded for k, v in d["unavailable"].items()}
    features: dict[str, dict[str, np.ndarray]] = {}
    for ex_id in first["extractors"]:
        got = [f[ex_id] for _, _, f in loaded if ex_id in f]
        if not got:
            continue
        seq = np.concatenate([g["seq"] for g in got])
        order = np.argsort(seq, kind="stable")  # canonical order: by sequence, clips in order
        features[ex_id] = {part: np.concatenate([g[part] for g in got])[order] for part in ("sub", "gt")}
        features[ex_id]["seq"] = seq[order]
    timing = {"merged_shards_s": {str(d["shard"]["index"]): d.get("timing_s", {}) for _, d, _ in loaded}}
    doc["shard"] = None
    res = finalize(doc, features, timing=timing, progress=progress)
    res["timing_s"] = timing
    if out is not None:
        # as evaluate: a second merge to this --out is one line; the inputs are checked again as
        # the files are renamed in
        with outputunit.output_lock(out), outputfiles.reading(*inputs):
            check_out()
            write_results(out, res, features)
    return res


# --------------------------------------------------------------------------- terminal


def format_summary(res: dict) -> str:
    """Human-readable lines for the terminal."""
    lines = [f"{res['submission'].get('method')} {res['submission'].get('method_version') or ''} on "
             f"{res['protocol']['ref']} ({res['dataset']['name']}, {len(res['frames'])} frames, "
             f"{len(res['dataset']['sequences'])} sequences)"]
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
