"""`evaluate`: score a submission folder, stage by stage, into a partial document (a shard) or
a results document (`summary.finalize`), written atomically under the output's lock."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import __version__, inputfiles, outputfiles, outputunit
from ..errors import UserError, ValidationError
from ..results import PARTIAL_FORMAT, lines_digest, timed_stage, write_results
from ..submission import expected_frames, frame_relpath, validate_submission
from ..summary import finalize
from .context import ScoringRun
from .features import features
from .frames import score_frames, score_sequences
from .inputs import MissingMetrics, check_extractors, check_out, missing_metrics, open_inputs, parse_shard, scoring_device


@dataclass(frozen=True)
class ScoringRequest:
    """What one `evaluate` call asks for (its arguments, checked; see `evaluate`)."""

    sub: Path
    data: Any
    out: Path | None
    shard: tuple[int, int] | None
    force: bool
    progress: bool
    protocol: str | None
    device: Any  # torch.device
    split: str | None
    allow_missing: bool


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
    # the device before any work: `--device cuda` without CUDA is one line, exit 2
    req = ScoringRequest(device=scoring_device(device), shard=parse_shard(shard), sub=Path(submission_dir),
                         data=data, out=Path(out) if out is not None else None, force=force, progress=progress,
                         protocol=protocol, split=split, allow_missing=allow_missing)
    if req.out is not None:  # before any work: a refused output never costs a scoring run
        check_out(req.out, force, [req.sub])
    with contextlib.ExitStack() as held:  # the output's lock, taken once the dataset is known
        return _score(req, held)


def _score(req: ScoringRequest, held: contextlib.ExitStack) -> dict[str, Any]:
    """The stages of `evaluate`, in order: open and check the inputs, the frame metrics, the
    features; then the summary (unless a shard), the refusal of missing metrics, the file."""
    from ..metrics.extractors import on_device

    timing: dict[str, float] = {}
    t_start = time.perf_counter()
    with timed_stage(timing, "validate_s"):
        manifest, protocol, ds, seq_ids, frames = _open(req, held)
    # Each submitted frame is hashed once: for this part's records and for the whole-submission digest.
    sub_sha = frame_hashes(req.sub, ds)
    run = ScoringRun(sub=req.sub, ds=ds, protocol=protocol, seq_ids=seq_ids, frames=frames, sub_sha=sub_sha,
                     device=req.device, progress=req.progress, timing=timing)
    doc = _partial_doc(run, manifest, req.shard)
    # The per-frame and per-sequence metric functions call LPIPS without a device argument:
    # `on_device` sends every extractor inside the block to the run's device.
    with on_device(req.device):
        score_frames(run)
        score_sequences(run)
        feats, extractors = features(run)
    doc.update(frames=run.records, unavailable=run.unavailable, extractors=extractors)
    if req.shard is None:
        doc = finalize(doc, feats, timing=run.timing, progress=req.progress)
    if not req.allow_missing:  # what only the scoring found (too few clips, ...): nothing is written
        _refuse_missing(doc, run, req.shard)
    run.timing["total_s"] = round(time.perf_counter() - t_start, 4)
    doc["timing_s"] = run.timing
    if req.out is not None:
        check_out(req.out, req.force, [req.sub, ds.root])  # at the point of writing too, and at each rename:
        with outputfiles.reading(req.sub, ds.root):
            write_results(req.out, doc, feats)
    return doc


def _open(req: ScoringRequest, held: contextlib.ExitStack):
    """(submission.json, protocol, dataset, its sequence ids, the (scene, frame)s this run scores),
    the output locked in `held`; every problem of the submission raised before any scoring."""
    manifest, protocol, ds = open_inputs(req.sub, req.data, req.protocol, req.split)
    if req.out is not None:
        check_out(req.out, req.force, [req.sub, ds.root])  # the lock file beside `out` must not land in the dataset either
        held.enter_context(outputunit.output_lock(req.out))  # a second run to this --out: one line, exit 2
        check_out(req.out, req.force, [req.sub, ds.root])  # again, holding the lock: a run that just ended may have written it
    check_extractors(protocol)
    all_seqs = ds.sequences("test")
    shard = req.shard
    if shard is not None and shard[1] > len(all_seqs):
        raise UserError(f"--shard {shard[0]}/{shard[1]}: the {ds.scored} split has {len(all_seqs)} sequences, so "
                        f"at most {len(all_seqs)} shards (each shard scores whole sequences)")
    mine = [k for k in range(len(all_seqs)) if shard is None or k % shard[1] == shard[0]]
    frames = [(all_seqs[k].scene, f) for k in mine for f in all_seqs[k].frames]
    problems = validate_submission(req.sub, ds, protocol, manifest, frames=frames, progress=req.progress)
    if problems:
        raise ValidationError(f"submission {req.sub}", problems)
    if not req.allow_missing:  # before any scoring: what is known to be missing costs no run
        missing = missing_metrics(protocol, ds, sorted({s for s, _ in frames}))
        if missing:
            raise MissingMetrics(protocol.ref, missing)
    return manifest, protocol, ds, [q.id for q in all_seqs], frames


def _partial_doc(run: ScoringRun, manifest: dict, shard: tuple[int, int] | None) -> dict[str, Any]:
    """The partial document's head: tool, protocol, dataset, submission (with the digest of every
    frame, not only this shard's: `merge` refuses parts of different submissions), shard."""
    ds, protocol = run.ds, run.protocol
    return {
        "format": PARTIAL_FORMAT,
        "tool": {"name": "skyeyes-bench", "version": __version__},
        "protocol": {"ref": protocol.ref, "sha256": protocol.sha256},
        "dataset": {"name": ds.name, "root": str(ds.root), "split": ds.scored, "sequences": run.seq_ids,
                    "frames": len(expected_frames(ds)),
                    "resolution": sorted({f"{f.width}x{f.height}" for _, f in expected_frames(ds)}),
                    "official_resolution": f"{protocol.data.width}x{protocol.data.height}"},
        "submission": {"path": str(run.sub.resolve()), **{k: manifest.get(k) for k in (
            "method", "method_version", "protocol", "created", "timings", "peak_memory_mb", "hardware", "config")},
            "frames_sha256": frames_digest(run.sub_sha)},
        "shard": {"index": shard[0], "count": shard[1]} if shard else None,
    }


def _refuse_missing(doc: dict, run: ScoringRun, shard) -> None:
    """MissingMetrics for the metrics the scoring could not compute (results: not "ok"; a shard:
    the unavailable ones)."""
    gone = {n: m for n, m in doc.get("metrics", {}).items() if m["status"] != "ok"} if shard is None else run.unavailable
    if gone:
        raise MissingMetrics(run.protocol.ref, {n: {"reason": m.get("reason", ""), "fix": m.get("fix", "")}
                                                for n, m in gone.items()})


def frame_hashes(sub: Path, ds) -> dict[str, str]:
    """Relative path -> sha256 of every frame dataset `ds` expects in submission folder `sub`
    ("missing" where there is none), in `expected_frames` order."""
    return {frame_relpath(sc, f): _sha_or_missing(Path(sub) / frame_relpath(sc, f)) for sc, f in expected_frames(ds)}


def frames_digest(sub_sha: dict[str, str]) -> str:
    """The whole submission's digest over `frame_hashes` (results' `submission.frames_sha256`)."""
    return lines_digest([f"{rel} {sha}\n" for rel, sha in sub_sha.items()])


def _sha_or_missing(path: Path) -> str:
    return inputfiles.sha256_file(path) if path.exists() or path.is_symlink() else "missing"
