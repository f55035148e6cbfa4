"""Shards -> results (`merge`): the partial results of `evaluate --shard I/N`, checked to belong
together (one protocol, dataset, submission and device; every shard once; each frame record in
its own shard and the records adding up to the submission), merged into the results of one run."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from . import inputfiles, outputfiles, outputunit, stats
from .errors import UserError, ValidationError
from .metricspec import frame_metrics
from .results import (FEATURES_OUTPUT, RESULTS_OUTPUT, lines_digest, quoted, features_path, read_results,
                      write_results)
from .summary import finalize


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
    first = loaded[0][1]
    problems = _field_problems(loaded) + _shard_problems(loaded)
    if problems:
        raise ValidationError("merge", problems)
    problems = _frame_records_problems(loaded)
    if problems:
        raise ValidationError("merge", problems)
    doc = dict(first)
    doc["extractors"] = _with_device(first["extractors"])  # one device, named even by older parts
    doc["frames"] = [r for _, d, _ in loaded for r in d["frames"]]
    doc["unavailable"] = {k: v for _, d, _ in loaded for k, v in d["unavailable"].items()}
    features = _merged_features(first, loaded)
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


def _field_problems(loaded: list[tuple[Path, dict, dict]]) -> list[str]:
    """Where a part's protocol, dataset, submission or extractors differ from the first part's
    (the dataset's root and the submission's path may: each machine has its own), one line each."""
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
    return problems


def _shard_problems(loaded: list[tuple[Path, dict, dict]]) -> list[str]:
    """Parts that are not shards of the first part's count, a shard given twice, shards missing."""
    n = (loaded[0][1].get("shard") or {}).get("count")
    problems = []
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
    return problems


def _merged_features(first: dict, loaded: list[tuple[Path, dict, dict]]) -> dict[str, dict[str, np.ndarray]]:
    """The parts' features of each extractor in canonical order: by sequence, clips in order."""
    features: dict[str, dict[str, np.ndarray]] = {}
    for ex_id in first["extractors"]:
        got = [f[ex_id] for _, _, f in loaded if ex_id in f]
        if not got:
            continue
        seq = np.concatenate([g["seq"] for g in got])
        order = np.argsort(seq, kind="stable")  # canonical order: by sequence, clips in order
        features[ex_id] = {part: np.concatenate([g[part] for g in got])[order] for part in ("sub", "gt")}
        features[ex_id]["seq"] = seq[order]
    return features


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
            where = f"{p}: field 'frames[{i}]' (frame {quoted(key[0] + '/' + key[1])})"
            if r["sequence"] % n != mine:
                own.append(f"{where}: of sequence {quoted(sid)}, which shard {mine}/{n} does not score")
            elif stats.scene_of(sid) != r["scene"]:
                own.append(f"{where}: not in scene {quoted(stats.scene_of(sid))} of its sequence {quoted(sid)}")
            elif key in owner:
                own.append(f"{where}: also in {owner[key]}")
            owner.setdefault(key, p)
        records = np.bincount(np.array([r["sequence"] for r in d["frames"]], dtype=np.int64),
                              minlength=len(seq_ids))
        for ex_id, f in feats.items():
            other = f["seq"][f["seq"] % n != mine]
            rows = np.bincount(f["seq"], minlength=len(seq_ids))
            if len(other):
                own.append(f"{features_path(p)}: array {quoted(ex_id + '|seq')} holds rows of sequence "
                           f"{quoted(seq_ids[int(other[0])])}, which shard {mine}/{n} does not score")
            elif d["extractors"][ex_id].get("kind") == "image" and (rows != records).any():
                # one feature row per scored frame: a record added or removed afterwards shows here
                k = int(np.flatnonzero(rows != records)[0])
                own.append(f"{p}: field 'frames' holds {records[k]} records of sequence {quoted(seq_ids[k])}, but "
                           f"{features_path(p).name} holds features of {rows[k]} of its frames: records were "
                           f"added or removed")
        problems += own[:1]
    if problems:
        return problems
    protocol = load_protocol(first["protocol"]["ref"])
    unavailable = {k for _, d, _ in loaded for k in d["unavailable"]}
    wanted = [name for name in frame_metrics() if protocol.metric(name) and name not in unavailable]
    for p, d, _ in loaded:
        for i, r in enumerate(d["frames"]):
            lack = [name for name in wanted if name not in r]
            if lack:
                return [f"{p}: field 'frames[{i}].{lack[0]}' missing (protocol {protocol.ref} scores it and the part "
                        f"does not list it unavailable)"]
    want = first["submission"].get("frames_sha256")
    got = lines_digest([f"{r['scene']}/{r['file']} {r['sha256']}\n" for _, d, _ in loaded for r in d["frames"]])
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
            where = f"{p}: field 'frames[{i}]' (frame {quoted(r['scene'] + '/' + r['file'])})"
            try:
                with inputfiles.open_regular(Path(folder, r["scene"], r["file"]), root=folder) as fh:
                    if os.fstat(fh.fileno()).st_size > _MAX_FRAME_BYTES:
                        continue
                    h = hashlib.sha256()
                    while block := fh.read(1 << 20):
                        h.update(block)
                    sha = h.hexdigest()
            except UserError:
                return (f"{where}: no such frame in the submission {quoted(folder)} it was scored from: the record "
                        f"was edited")
            if sha != r["sha256"]:
                return (f"{where}: sha256 {ascii(r['sha256'][:12])[1:-1]}... recorded, {sha[:12]}... in the submission "
                        f"{quoted(folder)}: the record was edited")
    names = ", ".join(str(p) for p, _, _ in loaded)
    return (f"merge: the frame records of one of {names} were edited: together they hash to {got[:12]}..., not to "
            f"the {want[:12]}... of the submission every part records (field 'submission.frames_sha256')")


#: A submitted frame is an 8-bit PNG; a larger file named by a part is not hashed (it is not one).
_MAX_FRAME_BYTES = 1 << 30
