"""Results files: reading (every field checked) and writing the JSON and its features sidecar.
A complete set of per-frame values and features becomes results in `summary.finalize`, shards in
`shards.merge`.

A results file is JSON (schema `skyeyes-bench/results@1`, docs/evaluate.md) with a sidecar
`<stem>.features.npz` holding the per-sequence features (submission and ground truth) of every
set-metric extractor, so intervals of FID/KID/FVD/KVD and paired comparisons can be recomputed
by resampling clusters (scenes or sequences, as the protocol says); each metric also carries
its half-sampling replicates, so two results pair without the sidecars. Partial (shard) files, `skyeyes-bench/partial@1`, have the same two
parts. `skyeyes_bench.evaluate` computes what goes in and re-exports the names here (and
`finalize`, `merge`).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import sys
import time
from pathlib import Path

import numpy as np

from . import fields, inputfiles, outputfiles, outputunit
from .errors import UserError, single_line
from .metricspec import METRICS, frame_metrics, metric_def

RESULTS_FORMAT = "skyeyes-bench/results@1"
PARTIAL_FORMAT = "skyeyes-bench/partial@1"


# --------------------------------------------------------------------------- small helpers


def progress_bar(progress: bool, **kw):
    """A progress bar on stderr, drawn only when stderr is a terminal (disable=None: tqdm's TTY test)."""
    from tqdm import tqdm

    return tqdm(disable=None if progress else True, file=sys.stderr, leave=False, **kw)


@contextlib.contextmanager
def timed_stage(timing: dict, name: str):
    t0 = time.perf_counter()
    yield
    timing[name] = round(timing.get(name, 0.0) + time.perf_counter() - t0, 4)


def lines_digest(lines: list[str]) -> str:
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


def quoted(text: str) -> str:
    """A name read from a file, quoted for a one-line message (newlines, bidi overrides escaped)."""
    return fields.short(text, 120)


def _results_problem(doc: dict, path: Path, partial: bool) -> None:
    """Raise a one-line UserError at the first field of a results (or partial) file that this
    version cannot use: wrong type, missing, NaN, a frame listed twice, or an index outside what
    the file itself holds."""
    fields.conform(str(path), doc, {**_RESULTS_SHAPE, **(_PARTIAL_SHAPE if partial else _FINAL_SHAPE)})
    n_seq = len(doc["dataset"]["sequences"])
    seen: dict[tuple[str, str], int] = {}
    names = frame_metrics()
    for i, r in enumerate(doc["frames"]):
        fields.integer(f"{path}: field 'frames[{i}].sequence'", r["sequence"], "a sequence number", 0, n_seq - 1)
        key = (r["scene"], r["file"])
        if key in seen:  # pairing (compare) and merging go by frame: one record each
            fields.fail(f"{path}: field 'frames[{i}]'",
                        f"frame {quoted(key[0] + '/' + key[1])} is listed twice (also frames[{seen[key]}])")
        seen[key] = i
        for name in names:
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
        if doc.get("seeds") is not None:  # `reproduce --seeds N`: each seed's headline values
            from .seeds import check_block

            check_block(str(path), doc["seeds"])
        if not isinstance(doc.get("statistics", {}), dict):
            fields.fail(f"{path}: field 'statistics'", f"expected an object, got {fields.short(doc['statistics'])}")
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
                                f"expected 'frame' or 'set', got {fields.short(m['kind'])}")
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
        raise UserError(f"{path}: field 'format' is {fields.short(got)}, expected {want!r}")
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
