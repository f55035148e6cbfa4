"""Score a submission: validate, per-frame metrics, features; then `summary.finalize` adds the
set metrics and statistics and writes the results file.

The module is callable: `skyeyes_bench.evaluate("sub/", ...)` is `skyeyes_bench.api.evaluate`,
the public entry point (strict about missing metrics, no progress bars, writes nothing unless
`out=` is given; docs/evaluate.md, "Python API"). Below, the internal function it calls:

```
results = evaluate("sub/", data=None, out="results.json")          # whole test split
part = evaluate("sub/", out="part-0.json", shard=(0, 4))          # sequences 0, 4, 8, ...
results = merge(["part-0.json", ...], out="results.json")          # == the unsharded numbers
```

Which metrics exist and which function computes each comes from `metricspec`; the results file
format (and `read_results`, ...) from `results`, `finalize` from `summary` and `merge` from
`shards`, re-exported here.
"""

from __future__ import annotations

import contextlib
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, imagefiles, inputfiles, outputfiles, outputunit, paths
from .errors import UserError, ValidationError
from .metricspec import FRAME_METRICS, IMAGE_EXTRACTOR, SEQUENCE_METRICS, metric_def
from .registry import load_entry_point
from .results import (  # noqa: F401  (re-exported: callers import these from evaluate)
    FEATURES_OUTPUT, PARTIAL_FORMAT, RESULTS_FORMAT, RESULTS_OUTPUT, default_out, features_path, lines_digest,
    progress_bar, read_results, timed_stage, write_results)
from .shards import merge  # noqa: F401  (re-exported)
from .submission import expected_frames, frame_relpath, read_submission, validate_submission
from .summary import finalize, format_summary  # noqa: F401  (re-exported)

_FRAME_BATCH = 16


# --------------------------------------------------------------------------- small helpers


def _sha_or_missing(path: Path) -> str:
    return inputfiles.sha256_file(path) if path.exists() or path.is_symlink() else "missing"


def builtin_protocol_ids() -> set[str]:
    """Ids of the protocols shipped with skyeyes-bench (official: no test-only extractors)."""
    from .protocol import available

    return set(available(paths.builtin_protocols_dir()))


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
    """The dataset folder: `data` if given, else `<cache>/data/<dataset name>`, else (for a test
    submission) the protocol's default location; the error names the command that makes it."""
    if data is not None:
        return Path(data)
    name = manifest["dataset"]["name"]
    val = manifest["dataset"].get("split", "test") == "val"
    candidates = [paths.data_dir() / name]
    loc = protocol.data.default_location
    if loc.startswith("cache:") and not val:
        candidates.append(paths.data_dir() / loc[len("cache:"):])
    for c in candidates:
        if (c / "dataset.json").is_file():
            return c
    if protocol.data.source == "synthtown":
        preset = name[len("synthtown-"):] if name.startswith("synthtown-") else "small"
        how = f"make it with `skyeyes-bench data synthtown --preset {preset}{' --split val' if val else ''}`"
    else:
        how = f"import it (`skyeyes-bench data --help`) and pass --data DIR"
    raise UserError(f"dataset {name!r} for {protocol.ref} not found (looked in "
                    f"{', '.join(str(c) for c in candidates)}); {how}")


def open_inputs(sub: Path, data=None, protocol: str | None = None, split: str | None = None):
    """(submission.json, the protocol that scores it, the dataset) of the submission folder `sub`:
    `protocol` (`id@N`) or the one submission.json names; the dataset `data` or `resolve_data`'s,
    seen as the split the submission holds scores it (`splits.scored_view`: "test", or "val").
    `split`: the split the caller expects (None: the submission's own).
    Raises UserError / ValidationError for a manifest, protocol or dataset that cannot be used."""
    from .data.layout import open_dataset
    from .protocol import load_protocol
    from .splits import check_split, scored_view

    manifest = read_submission(sub)
    held = manifest["dataset"].get("split", "test")
    if split is not None and check_split(split) != held:
        raise UserError(f"{sub}/submission.json: field 'dataset.split' is {held!r}, --split asks for {split!r}")
    if protocol is not None:
        proto = load_protocol(protocol)
    else:
        try:
            proto = load_protocol(manifest["protocol"])
        except UserError as e:  # an unknown id or version: say which file names it
            raise UserError(f"{sub / 'submission.json'}: field 'protocol': {e}") from None
    return manifest, proto, scored_view(open_dataset(resolve_data(manifest, proto, data)), held, proto)


def _clips(n_frames: int, length: int, stride: int) -> list[range]:
    """Clips of `length` consecutive frames starting every `stride` frames (none if too short)."""
    return [range(s, s + length) for s in range(0, n_frames - length + 1, max(1, stride))]


def _frame_batches(items: list, size: int):
    for i in range(0, len(items), size):
        yield items[i:i + size]


# --------------------------------------------------------------------------- evaluate


def evaluate(submission_dir, data=None, out=None, shard=None, force: bool = False,
             progress: bool = True, protocol: str | None = None, device: str | None = "cpu",
             split: str | None = None, allow_missing: bool = True) -> dict[str, Any]:
    """Score a submission folder against its protocol.

    (The public entry point is `skyeyes_bench.evaluate(...)`, `api.evaluate`: the same call with
    `allow_missing=False` and no progress bars by default.)

    Args:
        submission_dir: folder with `submission.json` and the frames.
        data: dataset folder (default: found from `submission.json`, see `resolve_data`).
        out: where to write the results JSON (and its `.features.npz` sidecar); None: don't write.
        shard: (I, N) or "I/N": evaluate only sequences k with k % N == I; the output is a
            partial result for `merge`.
        force: replace an existing `out`.
        progress: progress bars on stderr.
        protocol: score with this protocol (`id@N`) instead of the one `submission.json` names;
            it must score the same data (`data.dataset_protocol`), e.g. "synthtown@3" for a
            submission written for "synthtown@2" (same frames, more metrics).
        device: where the feature extractors (Inception, I3D, LPIPS) run: "cpu" (the default and
            the reference), "cuda", "cuda:N" or "auto" (CUDA when visible; `devices.resolve_device`).
            GPU features agree with the CPU's to float rounding, so scores may differ in their last
            digits; the device type is recorded as `extractors.<id>.device`, and features are cached
            per device type.
        split: the split the submission must hold, "test" or "val" (None: whichever it holds, as
            its submission.json says); a validation submission is scored on the validation scenes
            and its results say `dataset.split: "val"` (never ranked).
        allow_missing: a metric the protocol asks for that cannot be computed here (missing
            weights, a dataset without depth) is reported `"unavailable"` in the results (True), or
            refuses the run with `MissingMetrics` (False; `evaluate` on the command line unless
            `--allow-missing`): before any scoring where that is known up front
            (`missing_metrics`), else before anything is written.
    Returns:
        The results dict (or the partial dict for a shard).
    Raises:
        ValidationError: every problem of the submission, before anything is computed or written.
        MissingMetrics: with allow_missing=False, a required metric that cannot be computed.
        UserError: a device this machine lacks (before any work).
    """
    dev = _scoring_device(device)  # before any work: `--device cuda` without CUDA is one line, exit 2
    shard = parse_shard(shard)
    sub = Path(submission_dir)
    out = Path(out) if out is not None else None
    if out is not None:  # before any work: a refused output never costs a scoring run
        check_out(out, force, [sub])
    with contextlib.ExitStack() as held:  # the output's lock, taken once the dataset is known
        return _evaluate(sub, data, out, shard, force, progress, protocol, dev, held, split, allow_missing)


def check_out(out: Path, force: bool, inputs: list[Path]) -> None:
    """`out` and its features sidecar may be written (`outputfiles.check_output`), outside `inputs`."""
    if not out.name:  # '.', '/': no file name to put the sidecar beside
        raise UserError(f"{out}: is a folder; expected the path of an output file")
    outputfiles.check_output(out, force=force, sidecars=[features_path(out)], outside=inputs, kind=RESULTS_OUTPUT,
                             sidecar_kind=FEATURES_OUTPUT)


def _evaluate(sub: Path, data, out: Path | None, shard, force: bool, progress: bool, protocol, dev,
              held: contextlib.ExitStack, split: str | None = None, allow_missing: bool = True) -> dict[str, Any]:
    from .metrics.extractors import on_device

    timing: dict[str, float] = {}
    t_start = time.perf_counter()
    with timed_stage(timing, "validate_s"):
        manifest, protocol, ds = open_inputs(sub, data, protocol, split)
        if out is not None:
            check_out(out, force, [sub, ds.root])  # the lock file beside `out` must not land in the dataset either
            held.enter_context(outputunit.output_lock(out))  # a second run to this --out: one line, exit 2
            check_out(out, force, [sub, ds.root])  # again, holding the lock: a run that just ended may have written it
        check_extractors(protocol)
        all_seqs = ds.sequences("test")
        seq_ids = [q.id for q in all_seqs]
        if shard is not None and shard[1] > len(all_seqs):
            raise UserError(f"--shard {shard[0]}/{shard[1]}: the {ds.scored} split has {len(all_seqs)} sequences, so "
                            f"at most {len(all_seqs)} shards (each shard scores whole sequences)")
        mine = [k for k in range(len(all_seqs)) if shard is None or k % shard[1] == shard[0]]
        frames = [(all_seqs[k].scene, f) for k in mine for f in all_seqs[k].frames]
        problems = validate_submission(sub, ds, protocol, manifest, frames=frames, progress=progress)
        if problems:
            raise ValidationError(f"submission {sub}", problems)
        if not allow_missing:  # before any scoring: what is known to be missing costs no run
            missing = missing_metrics(protocol, ds, sorted({s for s, _ in frames}))
            if missing:
                raise MissingMetrics(protocol.ref, missing)
    # Each submitted frame is hashed once: for this part's records and for the whole-submission digest.
    sub_sha = {frame_relpath(sc, f): _sha_or_missing(sub / frame_relpath(sc, f)) for sc, f in expected_frames(ds)}
    doc: dict[str, Any] = {
        "format": PARTIAL_FORMAT,
        "tool": {"name": "skyeyes-bench", "version": __version__},
        "protocol": {"ref": protocol.ref, "sha256": protocol.sha256},
        "dataset": {"name": ds.name, "root": str(ds.root), "split": ds.scored, "sequences": seq_ids,
                    "frames": len(expected_frames(ds)),
                    "resolution": sorted({f"{f.width}x{f.height}" for _, f in expected_frames(ds)}),
                    "official_resolution": f"{protocol.data.width}x{protocol.data.height}"},
        "submission": {"path": str(sub.resolve()), **{k: manifest.get(k) for k in (
            "method", "method_version", "protocol", "created", "timings", "peak_memory_mb", "hardware", "config")},
            # every frame, not only this shard's: `merge` refuses parts of different submissions
            "frames_sha256": lines_digest([f"{rel} {sha}\n" for rel, sha in sub_sha.items()])},
        "shard": {"index": shard[0], "count": shard[1]} if shard else None,
    }
    seq_index = {sid: k for k, sid in enumerate(seq_ids)}
    # The per-frame and per-sequence metric functions call LPIPS without a device argument:
    # `on_device` sends every extractor inside the block to `dev`.
    with on_device(dev):
        records, unavailable = _frame_metrics(sub, frames, protocol, seq_index, sub_sha, timing, progress)
        _sequence_metrics(sub, ds, frames, protocol, records, unavailable, timing, progress)
        features, extractors = _features(sub, frames, protocol, seq_index, unavailable, timing, progress, dev)
    doc.update(frames=records, unavailable=unavailable, extractors=extractors)
    if shard is None:
        doc = finalize(doc, features, timing=timing, progress=progress)
    if not allow_missing:  # what only the scoring found (too few clips, ...): nothing is written
        gone = {n: m for n, m in doc.get("metrics", {}).items() if m["status"] != "ok"} if shard is None else unavailable
        if gone:
            raise MissingMetrics(protocol.ref, {n: {"reason": m.get("reason", ""), "fix": m.get("fix", "")}
                                                for n, m in gone.items()})
    timing["total_s"] = round(time.perf_counter() - t_start, 4)
    doc["timing_s"] = timing
    if out is not None:
        check_out(out, force, [sub, ds.root])  # at the point of writing too, and at each rename:
        with outputfiles.reading(sub, ds.root):
            write_results(out, doc, features)
    return doc


class MissingMetrics(UserError):
    """Metrics the protocol asks for that cannot be computed here, and `allow_missing` is off.

    Attributes:
        missing: {metric name: {"reason", "fix"}}, as the results would report them.
    """

    def __init__(self, ref: str, missing: dict[str, dict]):
        self.missing = dict(missing)
        names = list(self.missing)
        first = self.missing[names[0]]
        why = first.get("reason") or "unavailable"
        fix = f"; fix: {first['fix']}" if first.get("fix") else ""
        super().__init__(f"protocol {ref} requires {', '.join(names)}, which cannot be computed here "
                         f"({names[0]}: {why}{fix}); pass --allow-missing (allow_missing=True in Python) to "
                         f"score the other metrics and report {'these' if len(names) > 1 else 'it'} unavailable")


def missing_metrics(protocol, ds, scenes: list[str]) -> dict[str, dict]:
    """The metrics of `protocol` known before any scoring not to be computable on the `scenes` of
    `ds`: an extractor whose weight files are missing or wrong, a depth layer the dataset lacks.
    {name: {"reason", "fix"}}, the words the results would report them with."""
    from .metrics import MetricUnavailable
    from .metrics.extractors import get_extractor

    out: dict[str, dict] = {}
    for m in protocol.metrics:
        if m.extractor:
            try:
                get_extractor(m.extractor).require()  # the weights' sha256, memoised: no network is loaded
            except MetricUnavailable as e:
                out[m.name] = {"reason": e.reason, "fix": e.fix}
    depth = [m.name for m in protocol.metrics if m.name in SEQUENCE_METRICS and m.name not in out]
    out.update(_missing_depth(ds, scenes, depth))
    return out


def _missing_depth(ds, scenes: list[str], names: list[str]) -> dict[str, dict]:
    """{name: {"reason", "fix"}} for each depth-based metric of `names` whose depth layers some of
    `scenes` lack."""
    out: dict[str, dict] = {}
    for name in names:
        missing = [f"{s}/{v}_depth/" for s in scenes for v in metric_def(name).depth
                   if not ds.scenes[s].layers()[f"{v}_depth"]]
        if missing:
            out[name] = {
                "reason": f"the dataset has no depth layer {missing[0]}" + (
                    f" (and {len(missing) - 1} more)" if len(missing) > 1 else "") + f": {name} needs it",
                "fix": "score a dataset with ground and aerial depth (SynthTown writes it; importers write it when "
                       "the capture has depth)"}
    return out


def _scoring_device(device):
    """`--device` resolved (`devices.resolve_device`) to a device that computes numbers."""
    from .devices import resolve_device

    dev = resolve_device(device)
    if dev.type == "meta":
        raise UserError(f"--device {device}: the meta device holds no data, so it cannot compute features "
                        "(expected auto, cpu, cuda or cuda:N)")
    return dev


def check_extractors(protocol) -> None:
    """A built-in protocol names official extractors only, and each metric's `resize` is the one its
    extractor implements; else UserError."""
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
    """Per-frame metrics the protocol asks for (PSNR, SSIM, LPIPS: each by the function its
    `metricspec` entry names) and file hashes (the submission's from `sub_sha`, relative path ->
    sha256, hashed once by the caller)."""
    from .metrics import MetricUnavailable

    specs = [protocol.metric(name) for name in FRAME_METRICS if protocol.metric(name) and metric_def(name).per_frame]
    functions = {m.name: load_entry_point(metric_def(m.name).per_frame) for m in specs}
    unavailable: dict[str, dict] = {}
    records = []
    bar = progress_bar(progress, total=len(frames), desc="per-frame metrics", unit="frame")
    with timed_stage(timing, "frame_metrics_s"), bar:
        for batch in _frame_batches(frames, _FRAME_BATCH):
            preds = np.stack([imagefiles.read_image(sub / frame_relpath(s, f)) for s, f in batch])  # [B, H, W, 3]
            gts = np.stack([f.image() for _, f in batch])  # [B, H, W, 3]
            values: dict[str, np.ndarray] = {}  # name -> [B]
            for m in specs:
                if m.name in unavailable:  # missing weights: reported once, not retried per batch
                    continue
                try:
                    values[m.name] = functions[m.name](preds, gts, m)
                except MetricUnavailable as e:
                    unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
            for i, (scene, f) in enumerate(batch):
                rec = {"scene": scene, "file": f.file, "sequence": seq_index[f"{scene}/{f.sequence}"],
                       "index": int(f.index),
                       "sha256": sub_sha[frame_relpath(scene, f)],
                       "gt_sha256": inputfiles.sha256_file(f.path)}
                for name, v in values.items():
                    rec[name] = float(v[i])
                records.append(rec)
            bar.update(len(batch))
    return records, unavailable


def _sequence_metrics(sub: Path, ds, frames, protocol, records: list[dict], unavailable: dict, timing,
                      progress) -> None:
    """The frame metrics computed a sequence at a time from the ground truth's depth and poses
    (`metricspec.MetricDef.per_sequence`: seen / unseen regions, warp consistency), written into
    `records`: the value (null for an empty region) and, for pixel-weighted metrics, `<name>_n`."""
    from .estimators import SequenceData
    from .metrics import MetricUnavailable
    from .metrics.masks import seen_masks

    specs = [protocol.metric(n) for n in SEQUENCE_METRICS if protocol.metric(n)]
    groups: dict[str, list] = {}  # entry point -> the specs it computes together
    for m in specs:
        groups.setdefault(metric_def(m.name).per_sequence, []).append(m)
    scenes = sorted({s for s, _ in frames})
    for entry, ms in list(groups.items()):
        gone = _missing_depth(ds, scenes, [m.name for m in ms])
        if gone:
            unavailable.update(gone)
            del groups[entry]
    if not groups:
        return
    by_seq: dict[tuple[str, str], list] = {}
    for s, f in frames:
        by_seq.setdefault((s, f.sequence), []).append(f)
    rec_of = {(r["scene"], r["file"]): r for r in records}
    timing.setdefault("masks_s", 0.0)
    bar = progress_bar(progress, total=len(by_seq), desc="depth metrics", unit="sequence")
    with timed_stage(timing, "sequence_metrics_s"), bar:
        for (scene, _), fs in by_seq.items():
            fs = sorted(fs, key=lambda f: f.index)
            masks: dict[float, np.ndarray] = {}

            def seen(tol: float, scene=scene, fs=fs, masks=masks) -> np.ndarray:
                if tol not in masks:
                    with timed_stage(timing, "masks_s"):
                        masks[tol] = seen_masks(ds.scenes[scene], fs, tol)
                return masks[tol]

            data = SequenceData(preds=np.stack([imagefiles.read_image(sub / frame_relpath(scene, f)) for f in fs]),
                                gts=np.stack([f.image() for f in fs]), depths=np.stack([f.depth() for f in fs]),
                                cameras=[f.camera() for f in fs], seen=seen)
            for entry, ms in groups.items():
                if all(m.name in unavailable for m in ms):
                    continue
                try:
                    values = load_entry_point(entry)(data, ms)
                except MetricUnavailable as e:  # missing weights: reported once, not retried per sequence
                    for m in ms:
                        unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
                    continue
                for name, (v, n) in values.items():
                    for i, f in enumerate(fs):
                        rec = rec_of[(scene, f.file)]
                        rec[name] = None if np.isnan(v[i]) else float(v[i])
                        if n is not None:
                            rec[f"{name}_n"] = int(n[i])
            bar.update(1)


def _features(sub: Path, frames, protocol, seq_index, unavailable, timing, progress, device):
    """Features of the submission and ground truth for every set-metric extractor, computed on
    `device` (a torch device; its type is recorded in each extractor's info).

    Returns ({"<extractor>": {"sub": [N, D], "gt": [N, D], "seq": [N]}}, {extractor: info})."""
    from .metrics import MetricUnavailable
    from .metrics.cache import extract_clip_features, extract_image_features
    from .metrics.extractors import get_extractor

    wanted: dict[str, list] = {}  # extractor -> set-metric specs
    for m in protocol.metrics:
        if metric_def(m.name).kind == "set":
            wanted.setdefault(m.extractor, []).append(m)
    # A frame metric's network (LPIPS) runs inside its per-frame function; its weights are named too.
    frame_users: dict[str, list[str]] = {}
    for m in protocol.metrics:
        if metric_def(m.name).kind == "frame" and m.extractor:
            wanted.setdefault(m.extractor, [])
            frame_users.setdefault(m.extractor, []).append(m.name)
    features: dict[str, dict[str, np.ndarray]] = {}
    extractors: dict[str, dict] = {}
    with timed_stage(timing, "features_s"):
        for ex_id, specs in wanted.items():
            try:
                ex = get_extractor(ex_id)
                extractors[ex_id] = {"kind": ex.kind, "dim": ex.dim, "weights_sha256": ex.weights_sha256,
                                     "device": device.type}
            except MetricUnavailable as e:
                extractors[ex_id] = {"status": "unavailable", "reason": e.reason}
                for m in specs:
                    unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
                continue
            if not specs:  # a frame metric's network: record the weights it used
                gone = any(name in unavailable for name in frame_users[ex_id])
                extractors[ex_id]["status"] = "unavailable" if gone else "ok"
                continue
            try:
                if ex.kind == IMAGE_EXTRACTOR:
                    sub_paths = [sub / frame_relpath(s, f) for s, f in frames]
                    gt_paths = [f.path for _, f in frames]
                    seq = np.array([seq_index[f"{s}/{f.sequence}"] for s, f in frames], dtype=np.int64)
                    fs = extract_image_features(ex_id, sub_paths, progress=progress, device=device)
                    fg = extract_image_features(ex_id, gt_paths, progress=progress, device=device)
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
                        fs = extract_clip_features(ex_id, clips_sub, progress=progress, device=device)
                        fg = extract_clip_features(ex_id, clips_gt, progress=progress, device=device)
            except MetricUnavailable as e:
                extractors[ex_id]["status"] = "unavailable"
                for m in specs:
                    unavailable[m.name] = {"reason": e.reason, "fix": e.fix}
                continue
            extractors[ex_id]["status"] = "ok"
            features[ex_id] = {"sub": np.asarray(fs), "gt": np.asarray(fg), "seq": seq}
    return features, extractors


# --------------------------------------------------------------------------- the module, callable


class _CallableModule(types.ModuleType):
    """This module, callable as `api.evaluate`. `skyeyes_bench.evaluate` names both this module and
    the public function (importing a submodule sets the package's attribute to it, whatever
    `skyeyes_bench.__init__` offered), so the module answers the call itself."""

    def __call__(self, submission, data=None, **kwargs):
        from .api import evaluate as public

        return public(submission, data, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
