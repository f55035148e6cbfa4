"""Score a submission: validate, per-frame metrics, features, set metrics, statistics, results.

```
results = evaluate("sub/", data=None, out="results.json")          # whole test split
part = evaluate("sub/", out="part-0.json", shard=(0, 4))          # sequences 0, 4, 8, ...
results = merge(["part-0.json", ...], out="results.json")          # == the unsharded numbers
```

A results file is JSON (schema `skyeyes-bench/results@1`, docs/evaluate.md) with a sidecar
`<stem>.features.npz` holding the per-sequence features (submission and ground truth) of every
set-metric extractor, so intervals of FID/KID/FVD/KVD and paired comparisons can be recomputed
by resampling sequences. Partial (shard) files have the same two parts.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, fields, fileio, paths, stats
from .errors import UserError, ValidationError
from .submission import SUBMISSION_FILE, expected_frames, frame_relpath, read_submission, validate_submission

RESULTS_FORMAT = "skyeyes-bench/results@1"
PARTIAL_FORMAT = "skyeyes-bench/partial@1"
#: Metric -> feature kind of its extractor.
_IMAGE_SET = ("fid", "kid")
_CLIP_SET = ("fvd", "kvd")
_FRAME_BATCH = 16


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


def _sha_or_missing(path: Path) -> str:
    return fileio.sha256_file(path) if path.exists() or path.is_symlink() else "missing"


def features_path(results_path: Path) -> Path:
    """`results.json` -> `results.features.npz` (the sidecar beside it)."""
    p = Path(results_path)
    stem = p.name[: -len(".json")] if p.name.endswith(".json") else p.name
    return p.with_name(stem + ".features.npz")


def builtin_protocol_ids() -> set[str]:
    """Ids of the protocols shipped with skyeyes-bench (official: no test-only extractors)."""
    from .protocol import available

    builtin = Path(__file__).parent / "_protocols"
    if not builtin.is_dir():
        builtin = Path(__file__).resolve().parent.parent / "protocols"
    return set(available(builtin)) if builtin.is_dir() else set()


def parse_shard(text: str | tuple | None) -> tuple[int, int] | None:
    """'I/N' -> (I, N) with 0 <= I < N."""
    if text is None or isinstance(text, tuple):
        return text
    try:
        i, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise UserError(f"--shard {text!r}: expected I/N, e.g. 0/4") from None
    if not (n >= 1 and 0 <= i < n):
        raise UserError(f"--shard {text!r}: expected 0 <= I < N")
    return i, n


def resolve_data(manifest: dict, protocol, data) -> Path:
    """The dataset folder: `data` if given, else `<cache>/data/<dataset name>`, else the
    protocol's default location; the error names the command that makes it."""
    if data is not None:
        return Path(data)
    name = manifest["dataset"]["name"]
    candidates = [paths.data_dir() / name]
    loc = protocol.data.default_location
    if loc.startswith("cache:"):
        candidates.append(paths.data_dir() / loc[len("cache:"):])
    for c in candidates:
        if (c / "dataset.json").is_file():
            return c
    if protocol.data.source == "synthtown":
        preset = name[len("synthtown-"):] if name.startswith("synthtown-") else "small"
        how = f"make it with `skyeyes-bench data synthtown --preset {preset}`"
    else:
        how = f"import it (`skyeyes-bench data --help`) and pass --data DIR"
    raise UserError(f"dataset {name!r} for {protocol.ref} not found (looked in "
                    f"{', '.join(str(c) for c in candidates)}); {how}")


def _clips(n_frames: int, length: int, stride: int) -> list[range]:
    """Clips of `length` consecutive frames starting every `stride` frames (none if too short)."""
    return [range(s, s + length) for s in range(0, n_frames - length + 1, max(1, stride))]


def _frame_batches(items: list, size: int):
    for i in range(0, len(items), size):
        yield items[i:i + size]


# --------------------------------------------------------------------------- evaluate


def evaluate(submission_dir, data=None, out=None, shard=None, force: bool = False,
             progress: bool = True) -> dict[str, Any]:
    """Score a submission folder against its protocol.

    Args:
        submission_dir: folder with `submission.json` and the frames.
        data: dataset folder (default: found from `submission.json`, see `resolve_data`).
        out: where to write the results JSON (and its `.features.npz` sidecar); None: don't write.
        shard: (I, N) or "I/N": evaluate only sequences k with k % N == I; the output is a
            partial result for `merge`.
        force: replace an existing `out`.
        progress: progress bars on stderr.
    Returns:
        The results dict (or the partial dict for a shard).
    Raises:
        ValidationError: every problem of the submission, before anything is computed or written.
    """
    from .data.layout import open_dataset
    from .protocol import load_protocol

    shard = parse_shard(shard)
    sub = Path(submission_dir)
    out = Path(out) if out is not None else None
    if out is not None:  # before any work: a refused output never costs a scoring run
        fileio.check_output(out, force=force, sidecars=[features_path(out)], outside=[sub])
    timing: dict[str, float] = {}
    t_start = time.perf_counter()
    with _stage(timing, "validate_s"):
        manifest = read_submission(sub)
        protocol = load_protocol(manifest["protocol"])
        ds = open_dataset(resolve_data(manifest, protocol, data))
        if out is not None:
            fileio.check_output(out, force=force, outside=[ds.root])
        _check_extractors(protocol)
        all_seqs = ds.sequences("test")
        seq_ids = [q.id for q in all_seqs]
        if shard is not None and shard[1] > len(all_seqs):
            raise UserError(f"--shard {shard[0]}/{shard[1]}: the test split has {len(all_seqs)} sequences, so "
                            f"at most {len(all_seqs)} shards (each shard scores whole sequences)")
        mine = [k for k in range(len(all_seqs)) if shard is None or k % shard[1] == shard[0]]
        frames = [(all_seqs[k].scene, f) for k in mine for f in all_seqs[k].frames]
        problems = validate_submission(sub, ds, protocol, manifest, frames=frames, progress=progress)
        if problems:
            raise ValidationError(f"submission {sub}", problems)
    # Each submitted frame is hashed once: for this part's records and for the whole-submission digest.
    sub_sha = {frame_relpath(sc, f): _sha_or_missing(sub / frame_relpath(sc, f)) for sc, f in expected_frames(ds)}
    doc: dict[str, Any] = {
        "format": PARTIAL_FORMAT,
        "tool": {"name": "skyeyes-bench", "version": __version__},
        "protocol": {"ref": protocol.ref, "sha256": protocol.sha256},
        "dataset": {"name": ds.name, "root": str(ds.root), "sequences": seq_ids,
                    "frames": len(expected_frames(ds)),
                    "resolution": sorted({f"{f.width}x{f.height}" for _, f in expected_frames(ds)}),
                    "official_resolution": f"{protocol.data.width}x{protocol.data.height}"},
        "submission": {"path": str(sub.resolve()), **{k: manifest.get(k) for k in (
            "method", "method_version", "created", "timings", "peak_memory_mb", "hardware", "config")},
            # every frame, not only this shard's: `merge` refuses parts of different submissions
            "frames_sha256": _digest([f"{rel} {sha}\n" for rel, sha in sub_sha.items()])},
        "shard": {"index": shard[0], "count": shard[1]} if shard else None,
    }
    seq_index = {sid: k for k, sid in enumerate(seq_ids)}
    records, unavailable = _frame_metrics(sub, frames, protocol, seq_index, sub_sha, timing, progress)
    features, extractors = _features(sub, frames, protocol, seq_index, unavailable, timing, progress)
    doc.update(frames=records, unavailable=unavailable, extractors=extractors)
    if shard is None:
        doc = finalize(doc, features, timing=timing, progress=progress)
    timing["total_s"] = round(time.perf_counter() - t_start, 4)
    doc["timing_s"] = timing
    if out is not None:
        write_results(out, doc, features)
    return doc


def _check_extractors(protocol) -> None:
    from .errors import UserError
    from .metrics.extractors import EXTRACTORS, assert_official, get_extractor

    if protocol.id in builtin_protocol_ids():
        for m in protocol.metrics:
            if m.extractor:
                assert_official(m.extractor, f"protocol {protocol.ref} metric {m.name}")
    # A protocol's resize mode must be the one its extractor implements: preprocessing is part
    # of the metric's definition, so a mismatch would silently score something else.
    for m in protocol.metrics:
        if m.extractor and m.resize and m.extractor in EXTRACTORS:
            have = get_extractor(m.extractor).resize
            if have is not None and have != m.resize:
                raise UserError(f"{protocol.path}: key 'metrics.{m.name}.resize' is {m.resize!r}, but extractor "
                                f"{m.extractor!r} implements {have!r}")


def _frame_metrics(sub: Path, frames, protocol, seq_index, sub_sha: dict[str, str], timing, progress):
    """Per-frame PSNR / SSIM / LPIPS (those the protocol asks for) and file hashes (the
    submission's from `sub_sha`, relative path -> sha256, hashed once by the caller)."""
    from .metrics import MetricUnavailable, lpips, psnr, ssim

    names = [m for m in stats.FRAME_METRICS if protocol.metric(m)]
    unavailable: dict[str, dict] = {}
    records = []
    bar = _tqdm(progress, total=len(frames), desc="per-frame metrics", unit="frame")
    with _stage(timing, "frame_metrics_s"), bar:
        for batch in _frame_batches(frames, _FRAME_BATCH):
            preds = np.stack([fileio.read_image(sub / frame_relpath(s, f)) for s, f in batch])  # [B, H, W, 3]
            gts = np.stack([f.image() for _, f in batch])  # [B, H, W, 3]
            values: dict[str, np.ndarray] = {}
            if "psnr" in names:
                values["psnr"] = psnr(preds, gts)
            if "ssim" in names:
                spec = protocol.metric("ssim")
                kw = {k: getattr(spec, k) for k in ("window", "sigma", "k1", "k2") if getattr(spec, k) is not None}
                values["ssim"] = ssim(preds, gts, **kw)
            if "lpips" in names and "lpips" not in unavailable:
                net = _lpips_net(protocol.metric("lpips").extractor)
                try:
                    values["lpips"] = lpips(preds, gts, net=net)
                except MetricUnavailable as e:
                    unavailable["lpips"] = {"reason": e.reason, "fix": e.fix}
            for i, (scene, f) in enumerate(batch):
                rec = {"scene": scene, "file": f.file, "sequence": seq_index[f"{scene}/{f.sequence}"],
                       "index": int(f.index),
                       "sha256": sub_sha[frame_relpath(scene, f)],
                       "gt_sha256": fileio.sha256_file(f.path)}
                for name, v in values.items():
                    rec[name] = float(v[i])
                records.append(rec)
            bar.update(len(batch))
    return records, unavailable


def _lpips_net(extractor: str | None) -> str:
    return {"lpips-alex-v0.1": "alex", "lpips-vgg-v0.1": "vgg"}.get(extractor or "lpips-alex-v0.1", "alex")


def _features(sub: Path, frames, protocol, seq_index, unavailable, timing, progress):
    """Features of the submission and ground truth for every set-metric extractor.

    Returns ({"<extractor>": {"sub": [N, D], "gt": [N, D], "seq": [N]}}, {extractor: info})."""
    from .metrics import MetricUnavailable
    from .metrics.cache import extract_clip_features, extract_image_features
    from .metrics.extractors import get_extractor

    wanted: dict[str, list] = {}  # extractor -> metric specs
    for m in protocol.metrics:
        if m.name in _IMAGE_SET + _CLIP_SET:
            wanted.setdefault(m.extractor, []).append(m)
    for m in protocol.metrics:  # LPIPS weights are named too, though extracted inside lpips()
        if m.name == "lpips" and m.extractor:
            wanted.setdefault(m.extractor, [])
    features: dict[str, dict[str, np.ndarray]] = {}
    extractors: dict[str, dict] = {}
    with _stage(timing, "features_s"):
        for ex_id, specs in wanted.items():
            try:
                ex = get_extractor(ex_id)
                extractors[ex_id] = {"kind": ex.kind, "dim": ex.dim, "weights_sha256": ex.weights_sha256}
            except MetricUnavailable as e:
                extractors[ex_id] = {"status": "unavailable", "reason": e.reason}
                for m in specs:
                    unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
                continue
            if not specs:  # LPIPS: its network runs inside lpips(); record the weights it used
                extractors[ex_id]["status"] = "unavailable" if "lpips" in unavailable else "ok"
                continue
            try:
                if ex.kind == "image":
                    sub_paths = [sub / frame_relpath(s, f) for s, f in frames]
                    gt_paths = [f.path for _, f in frames]
                    seq = np.array([seq_index[f"{s}/{f.sequence}"] for s, f in frames], dtype=np.int64)
                    fs = extract_image_features(ex_id, sub_paths, progress=progress)
                    fg = extract_image_features(ex_id, gt_paths, progress=progress)
                else:
                    spec = specs[0]
                    if len({(m.clip_length, m.clip_stride) for m in specs}) > 1:
                        raise UserError(f"protocol {protocol.ref}: metrics {', '.join(m.name for m in specs)} share "
                                        f"extractor {ex_id} but not clip_length/clip_stride")
                    clips_sub, clips_gt, seq_l = [], [], []
                    by_seq: dict[int, list] = {}
                    for s, f in frames:
                        by_seq.setdefault(seq_index[f"{s}/{f.sequence}"], []).append((s, f))
                    for k in sorted(by_seq):
                        fr = sorted(by_seq[k], key=lambda sf: sf[1].index)
                        for c in _clips(len(fr), spec.clip_length, spec.clip_stride or spec.clip_length):
                            clips_sub.append([sub / frame_relpath(*fr[i]) for i in c])
                            clips_gt.append([fr[i][1].path for i in c])
                            seq_l.append(k)
                    seq = np.array(seq_l, dtype=np.int64)
                    if not clips_sub:
                        fs = fg = np.zeros((0, ex.dim))
                    else:
                        fs = extract_clip_features(ex_id, clips_sub, progress=progress)
                        fg = extract_clip_features(ex_id, clips_gt, progress=progress)
            except MetricUnavailable as e:
                extractors[ex_id]["status"] = "unavailable"
                for m in specs:
                    unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
                continue
            extractors[ex_id]["status"] = "ok"
            features[ex_id] = {"sub": np.asarray(fs), "gt": np.asarray(fg), "seq": seq}
    return features, extractors


# --------------------------------------------------------------------------- summary


def finalize(doc: dict, features: dict, *, timing: dict | None = None, progress: bool = False) -> dict:
    """Turn a complete (all sequences) partial into results: per-sequence values, summaries with
    clustered-bootstrap intervals, set metrics. Pure given its inputs (deterministic seeds)."""
    from .metrics import FeatureStats, frechet_distance, kernel_mmd
    from .protocol import load_protocol

    timing = {} if timing is None else timing
    protocol = load_protocol(doc["protocol"]["ref"])
    if protocol.sha256 != doc["protocol"]["sha256"]:
        raise UserError(f"protocol {protocol.ref} changed since these values were computed (sha256 "
                        f"{doc['protocol']['sha256'][:12]}... then, {protocol.sha256[:12]}... now)")
    st = protocol.statistics
    seq_ids = doc["dataset"]["sequences"]
    k = len(seq_ids)
    frames = sorted(doc["frames"], key=lambda r: (r["sequence"], r["index"]))
    clusters = np.array([r["sequence"] for r in frames], dtype=np.int64)
    counts = stats.resample_counts(stats.resample_indices(k, st.bootstrap_resamples, st.seed), k)
    res = dict(doc)
    res["format"] = RESULTS_FORMAT
    res["frames"] = frames
    res["sha256"] = {
        "submission_frames": _digest([f"{r['scene']}/{r['file']} {r['sha256']}\n" for r in frames]),
        "ground_truth": _digest([f"{r['scene']}/{r['file']} {r['gt_sha256']}\n" for r in frames]),
    }
    res["statistics"] = {"method": "clustered bootstrap over sequences (paired submission/ground truth)",
                         "resamples": st.bootstrap_resamples, "level": st.interval, "seed": st.seed,
                         "interval": "percentile"}
    metrics: dict[str, dict] = {}
    per_seq: dict[str, dict] = {sid: {"frames": int((clusters == i).sum())} for i, sid in enumerate(seq_ids)}
    with _stage(timing, "bootstrap_s"):
        for name in stats.FRAME_METRICS:
            if not protocol.metric(name):
                continue
            if name in doc["unavailable"]:
                metrics[name] = {"status": "unavailable", **doc["unavailable"][name]}
                continue
            v = np.array([r[name] for r in frames], dtype=np.float64)
            samples = stats.frame_metric_samples(v, clusters, counts)
            lo, hi = stats.percentile_interval(samples, st.interval)
            value = float(np.mean(v)) if not np.isposinf(v).any() else math.inf
            metrics[name] = {"status": "ok", "kind": "frame", "value": value, "interval": [lo, hi],
                             "level": st.interval, "higher_is_better": stats.higher_is_better(name),
                             "n": int(len(v))}
            if name == "psnr":
                metrics[name]["infinite_frames"] = int(np.isposinf(v).sum())
                seqv = stats.sequence_psnr(v, clusters, k)
            else:
                seqv = np.bincount(clusters, weights=v, minlength=k) / np.bincount(clusters, minlength=k)
            for i, sid in enumerate(seq_ids):
                per_seq[sid][name] = float(seqv[i])
    timing.setdefault("set_metrics_s", 0.0)
    for m in protocol.metrics:
        if m.name not in _IMAGE_SET + _CLIP_SET:
            continue
        if m.name in doc["unavailable"]:
            metrics[m.name] = {"status": "unavailable", **doc["unavailable"][m.name]}
            continue
        f = features[m.extractor]
        xs, xg, seq = np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64), f["seq"]
        if len(xs) < 2:
            what = "clips" if m.name in _CLIP_SET else "frames"
            metrics[m.name] = {"status": "unavailable",
                               "reason": f"{len(xs)} {what} of {m.clip_length or 1} frames; need at least 2",
                               "fix": "sequences must hold at least clip_length frames"}
            continue
        with _stage(timing, "set_metrics_s"):
            if m.name in ("fid", "fvd"):
                a, b = FeatureStats(xs.shape[1]), FeatureStats(xs.shape[1])
                a.update(xs)
                b.update(xg)
                value = frechet_distance(a.mean(), a.cov(), b.mean(), b.cov())
                fn = stats.FrechetBootstrap(xs, xg)
            else:
                value = kernel_mmd(xs, xg, subset_size=m.subset_size, num_subsets=m.num_subsets or 1, seed=st.seed)
                fn = stats.MMDBootstrap(xs, xg, seq, seq, k)
        with _stage(timing, "bootstrap_s"):
            bar = _tqdm(progress, total=len(counts), desc=f"bootstrap {m.name}", unit="resample")
            with bar:
                samples = stats.set_metric_samples(fn, seq, seq, counts, progress=bar.update)
            samples = samples[np.isfinite(samples)]  # resamples with < 2 rows are undefined
            lo, hi = stats.percentile_interval(samples, st.interval) if len(samples) else (math.nan, math.nan)
        metrics[m.name] = {"status": "ok", "kind": "set", "value": float(value), "interval": [lo, hi],
                           "level": st.interval, "higher_is_better": False, "n": int(len(xs)),
                           "extractor": m.extractor, "unit": "clip" if m.name in _CLIP_SET else "frame",
                           "resample_mean": float(np.mean(samples)) if len(samples) else math.nan}
        if not lo <= value <= hi:
            metrics[m.name]["note"] = (
                "value outside its percentile interval: a resample repeats sequences, and repeated "
                "frames bias set metrics on small sets (the interval shows the spread, not a bias-free range)")
    res["metrics"] = {name: metrics[name] for name in protocol.metric_names if name in metrics}
    res["sequences"] = per_seq
    res.pop("unavailable", None)
    return res


# --------------------------------------------------------------------------- I/O


def write_results(out: Path, doc: dict, features: dict) -> None:
    """Write the features sidecar, then the JSON that names it (both atomically)."""
    fpath = features_path(out)
    arrays: dict[str, np.ndarray] = {}
    for ex_id, f in features.items():
        for part in ("sub", "gt", "seq"):
            arrays[f"{ex_id}|{part}"] = np.asarray(f[part])
    with fileio.atomic_path(fpath, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    doc["features"] = {"file": fpath.name, "sha256": fileio.sha256_file(fpath)}
    fileio.write_json(out, doc)


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
_PARTIAL_SHAPE = {"shard": fields.Optional({"index": int, "count": int}), "unavailable": {str: dict}}


def _results_problem(doc: dict, path: Path, partial: bool) -> None:
    """Raise a one-line UserError at the first field of a results (or partial) file that this
    version cannot use: wrong type, missing, or an index outside what the file itself holds."""
    fields.conform(str(path), doc, {**_RESULTS_SHAPE, **(_PARTIAL_SHAPE if partial else _FINAL_SHAPE)})
    n_seq = len(doc["dataset"]["sequences"])
    for i, r in enumerate(doc["frames"]):
        fields.integer(f"{path}: field 'frames[{i}].sequence'", r["sequence"], "a sequence number", 0, n_seq - 1)
        for name in stats.FRAME_METRICS:
            if name in r:
                fields.conform(str(path), r[name], fields.Number, f"frames[{i}].{name}")
    shard = doc.get("shard")
    if partial and shard is not None:  # a shard holds at least one sequence: N <= sequences
        fields.integer(f"{path}: field 'shard.count'", shard["count"], "the number of shards", 1, max(n_seq, 1))
        fields.integer(f"{path}: field 'shard.index'", shard["index"], "the shard's number", 0, shard["count"] - 1)
    if not partial:
        for name, m in doc["metrics"].items():
            if m["status"] == "ok":
                fields.conform(str(path), m, {"kind": str, "value": fields.Number}, f"metrics.{name}")
                if m["kind"] not in ("frame", "set"):
                    fields.fail(f"{path}: field 'metrics.{name}.kind'",
                                f"expected 'frame' or 'set', got {fields._short(m['kind'])}")
                if m["kind"] == "frame":  # compared per sequence: every sequence holds a value
                    for sid in doc["dataset"]["sequences"]:
                        fields.conform(str(path), doc["sequences"].get(sid), {name: fields.Number},
                                       f"sequences.{sid}")
                if m["kind"] == "set":
                    fields.conform(str(path), m, {"extractor": str}, f"metrics.{name}")


def _read_sidecar(fpath: Path, doc: dict, path: Path) -> dict[str, dict[str, np.ndarray]]:
    """The features sidecar, checked against the results file before any array is trusted: only
    stored (uncompressed) .npy members, so no member can inflate past the file's own size."""
    import zipfile

    try:
        with fileio.open_regular(fpath) as fh, zipfile.ZipFile(fh) as zf:
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
        raise UserError(f"{fpath}: not a features sidecar ({fileio._one_line(e)})") from None
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
    return out


def read_results(path, *, features: bool = False, partial: bool = False) -> tuple[dict, dict | None]:
    """Read a results (or partial) JSON and optionally its features sidecar (sha256-checked).
    Every field used later is checked here; a bad one is a one-line UserError naming it."""
    path = Path(path)
    doc = fileio.read_json(path, allow_nan=True)  # a perfect frame's PSNR is Infinity
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
    fields.name(f"{path}: field 'features.file'", name, "the sidecar's file name beside it")
    fpath = path.with_name(name)
    if not fpath.is_file():
        raise UserError(f"{fpath}: features sidecar of {path.name} missing (needed to resample set metrics)")
    if info.get("sha256") and fileio.sha256_file(fpath) != info["sha256"]:
        raise UserError(f"{fpath}: sha256 differs from the one recorded in {path.name} (file changed)")
    return doc, _read_sidecar(fpath, doc, path)


def default_out(submission_dir, shard: tuple[int, int] | None = None) -> Path:
    """`sub/` -> `sub.results.json` beside the folder (never inside it: that would be an extra file)."""
    sub = Path(submission_dir).resolve()
    tail = f".shard-{shard[0]}-of-{shard[1]}" if shard else ""
    return sub.with_name(f"{sub.name}{tail}.results.json")


# --------------------------------------------------------------------------- merge


def merge(parts, out=None, *, force: bool = False, progress: bool = True) -> dict:
    """Merge the partial results of `evaluate --shard I/N` (all N of them) into results that
    equal an unsharded run."""
    out = Path(out) if out is not None else None
    if out is not None:
        fileio.check_output(out, force=force, sidecars=[features_path(out)], inputs=parts,
                            inputs_are="the parts being merged")
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
    doc = dict(first)
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
        write_results(out, res, features)
    return res


def format_summary(res: dict) -> str:
    """Human-readable lines for the terminal."""
    lines = [f"{res['submission'].get('method')} {res['submission'].get('method_version') or ''} on "
             f"{res['protocol']['ref']} ({res['dataset']['name']}, {len(res['frames'])} frames, "
             f"{len(res['dataset']['sequences'])} sequences)"]
    for name, m in res["metrics"].items():
        if m["status"] != "ok":
            lines.append(f"  {name:<6} unavailable: {m['reason']} (fix: {m['fix']})")
            continue
        lo, hi = m["interval"]
        arrow = "higher is better" if m["higher_is_better"] else "lower is better"
        extra = f"  ({m['infinite_frames']} exact frames)" if m.get("infinite_frames") else ""
        if m.get("note"):
            extra += f"  [note: {m['note']}]"
        lines.append(f"  {name:<6} {m['value']:.4g}  [{lo:.4g}, {hi:.4g}] {int(m['level'] * 100)}%  "
                     f"({arrow}){extra}")
    t = res.get("timing_s", {})
    lines.append("  evaluator time: " + ", ".join(f"{k} {v:.2f}" for k, v in t.items() if isinstance(v, float)))
    return "\n".join(lines)
