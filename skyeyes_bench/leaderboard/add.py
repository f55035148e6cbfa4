"""`skyeyes-bench leaderboard add RESULTS.json`: check a results file and file it as
`results/<name>.json`, with the strip frames and the test sequence's animation
(`frames/<key>/...`) when the submission and the dataset it was scored against are on this
machine."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

from .. import inputfiles, safe
from ..errors import UserError
from . import checks
from .plots import FRAMES_DIR, FRAMES_LIST, GROUND_TRUTH, save_tile, write_frames_list
from .sequence import SEQUENCE_FILE, save_sequence
from .tables import ADD_KEY, format_hardware, frames_key

#: Frames per strip (columns).
K_FRAMES = 4


def choose_frames(doc: dict, k: int = K_FRAMES) -> list[dict]:
    """k test frames chosen from the dataset's description alone (its sequence list and frame
    records, the same in every results file of that dataset), so every method shows the same
    frames: the middle frame (index position ⌊n/2⌋) of the first sequence of k evenly spaced
    scenes; with fewer than k scenes, of k evenly spaced sequences.

    Returns [{"scene", "file", "sequence", "index", "label", "tile"}] in column order.
    """
    seq_ids = doc["dataset"]["sequences"]
    by_seq: dict[int, list[dict]] = {}
    for r in doc["frames"]:
        by_seq.setdefault(r["sequence"], []).append(r)
    seqs = [q for q in range(len(seq_ids)) if q in by_seq]
    first_of_scene: dict[str, int] = {}
    for q in seqs:
        first_of_scene.setdefault(by_seq[q][0]["scene"], q)
    pool = list(first_of_scene.values()) if len(first_of_scene) >= k else seqs
    picks = sorted({pool[j * len(pool) // k] for j in range(k)}) if pool else []
    out = []
    for j, q in enumerate(picks):
        frames = sorted(by_seq[q], key=lambda r: r["index"])
        r = frames[len(frames) // 2]
        out.append({"scene": r["scene"], "file": r["file"], "sequence": seq_ids[q], "index": r["index"],
                    "label": f"{seq_ids[q]} #{r['index']}", "tile": f"{j}.png"})
    return out


def choose_sequence(doc: dict, frames: list[dict]) -> dict | None:
    """The test sequence shown as an animation, chosen like the strip frames from the dataset's
    description alone: the sequence of the first strip frame, its first MAX_SEQUENCE_FRAMES frames
    in index order (all of them in synthtown's 32-frame sequences).

    Returns {"scene", "sequence", "label", "frames": [{"file", "index"}]}; None when the first
    strip frame is not among the results' frame records.
    """
    first = frames[0] if frames else None
    rec = next((r for r in doc["frames"] if first and (r["scene"], r["file"]) == (first["scene"], first["file"])),
               None)
    if rec is None:
        return None
    mine = sorted((r for r in doc["frames"] if r["sequence"] == rec["sequence"] and r["scene"] == rec["scene"]),
                  key=lambda r: r["index"])[:checks.MAX_SEQUENCE_FRAMES]
    sid = doc["dataset"]["sequences"][rec["sequence"]]
    return {"scene": rec["scene"], "sequence": sid, "label": f"{sid} #{mine[0]['index']}–#{mine[-1]['index']}",
            "frames": [{"file": r["file"], "index": r["index"]} for r in mine]}


def _fail(path: Path, field: str, msg: str):
    raise UserError(f"{path}: field '{field}' {msg}")


def check_results(path: Path) -> dict:
    """The results document at `path`, or a one-line UserError naming the file, the field and
    what was expected."""
    from ..protocol import load_protocol
    from ..results import PARTIAL_FORMAT, RESULTS_FORMAT, read_results

    raw = inputfiles.read_json(path, allow_nan=True)
    if isinstance(raw, dict) and (raw.get("format") == PARTIAL_FORMAT or raw.get("shard")):
        _fail(path, "format" if raw.get("format") == PARTIAL_FORMAT else "shard",
              f"says these are partial results of one shard; expected complete results ({RESULTS_FORMAT!r}): "
              f"merge every shard first (`skyeyes-bench merge PARTS... --out results.json`)")
    doc, _ = read_results(path)
    checks.results_fields(doc, path)  # paths and page text, before anything uses them
    split = doc["dataset"].get("split", "test")
    if split != "test":
        _fail(path, "dataset.split", f"is {split!r}: results on the validation split are for choosing settings and "
              "are never ranked; file the test split's (docs/evaluate.md, 'The split')")
    ref = doc["protocol"]["ref"]
    try:
        proto = load_protocol(ref)
    except UserError as e:
        _fail(path, "protocol.ref", f"is {ref!r}: {e} (expected a protocol this skyeyes-bench knows)")
    if proto.sha256 != doc["protocol"]["sha256"]:
        _fail(path, "protocol.sha256", f"is {doc['protocol']['sha256'][:12]}…, but protocol {ref} is "
              f"{proto.sha256[:12]}… here: the protocol file changed since this result was scored")
    checks.run_seconds(path, doc["submission"].get("timings"), required=True)
    if not any(m.get("status") == "ok" for m in doc["metrics"].values()):
        _fail(path, "metrics", "holds no metric with status 'ok'; expected at least one scored metric")
    for name, m in doc["metrics"].items():
        reps = m.get("replicates")
        if reps is not None and not (isinstance(reps, list) and all(
                v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in reps)):
            _fail(path, f"metrics.{name}.replicates", "expected a list of bootstrap replicate values (numbers or "
                  "null)")
    return doc


def _tiles_problem(folder: Path, frames: list[dict], records: dict, sha_key: str) -> str | None:
    """Why the chosen frames of `folder` (a submission or a dataset root: `<scene>/<file>`) cannot
    be saved (None: each is there with the sha256 the results recorded)."""
    for f in frames:
        p = folder / f["scene"] / f["file"]
        if not p.is_file():
            return f"{p} not found"
        if inputfiles.sha256_file(p) != records[(f["scene"], f["file"])][sha_key]:
            return f"{p} differs from the frame that was scored (sha256)"
    return None


def _save_frames(folder: Path, frames: list[dict], sequence: dict | None, dst: Path, *, root: Path,
                 overwrite: bool) -> int | None:
    """Save the strip tiles of `frames` and (unless None) the sequence's animation from `folder`
    as the folder `dst`, atomically; returns the animation's size in bytes (None: not saved)."""
    size = None
    with safe.atomic_folder(dst, root=root, overwrite=overwrite) as tmp:
        for f in frames:
            save_tile(folder / f["scene"] / f["file"], tmp / f["tile"], root=root)
        if sequence is not None:
            size = save_sequence(folder, sequence, tmp / SEQUENCE_FILE, root=root)
    return size


def _kb(size: int | None) -> str:
    return f"{(size or 0) / 1024:.0f} KB"


def _hardware_here() -> dict:
    """This machine's hardware, with the names that reach the page made plain text (a CPU model
    string is whatever /proc/cpuinfo says)."""
    from ..submission import detect_hardware

    hw = detect_hardware()
    for key in ("cpu", "gpu"):
        if isinstance(hw.get(key), str):
            hw[key] = "".join(c for c in hw[key] if not safe.text_problem(c, 1))[:200] or None
    return hw


def _name_to_file(path: Path, doc: dict, name: str | None) -> str:
    """The name to file the result under: `name` (--name), else the submission's method; checked."""
    if name is None:
        name = doc["submission"].get("method")
        if name is None:
            _fail(path, "submission.method", "is null; pass --name NAME")
        checks.filed_name(f"{path}: field 'submission.method'", name, "a name to file the result under (or pass "
                          "--name)")
    else:
        checks.filed_name("--name", name, "the name to file the result under")
    return name


def _destinations(root: Path, doc: dict, name: str, force: bool) -> tuple[Path, Path, Path]:
    """Where the results file (`dest`), the frames of its protocol and dataset (`base`) and the strip
    frames of `name` (`mine`) go, checked before anything is written: (dest, base, mine)."""
    dest = root / "results" / f"{name}.json"
    if dest.is_dir():
        raise UserError(f"{dest}: is a folder; expected the results file filed as {name!r} (or nothing)")
    if dest.exists() and not force:
        raise UserError(f"{dest}: a result is already filed as {name!r}; pass --force to replace it or --name "
                        f"to file it under another name")
    base = root / FRAMES_DIR / frames_key(doc)
    mine = base / name
    for p in (dest, base / FRAMES_LIST, base / GROUND_TRUTH, base / GROUND_TRUTH / SEQUENCE_FILE, mine):
        safe.confined(p, root)  # again where each is written: this says so before any work
    if (mine.exists() or mine.is_symlink()) and not force:
        raise UserError(f"{mine}: strip frames are already saved under {name!r} (no result of that name is filed); "
                        f"pass --force to replace them or --name to file the result under another name")
    if mine.exists() and not mine.is_dir():
        raise UserError(f"{mine}: is a file; expected the folder of {name!r}'s strip frames (or nothing)")
    return dest, base, mine


def _strip_and_sequence(path: Path, doc: dict, listed: Path) -> tuple[list[dict], dict, bool, dict, list[dict]]:
    """The strip frames and the test sequence: those of the frames list `listed` if there is one,
    else chosen from `doc`; checked against the results' frame records.

    Returns (frames, sequence, whether the list lacks the sequence, records by (scene, file),
    the sequence's frames as [{"scene", "file"}]).
    """
    frames, seq = checks.frames_file(listed) if listed.is_file() else (choose_frames(doc), None)
    records = {(r["scene"], r["file"]): r for r in doc["frames"]}
    if not frames:
        _fail(path, "frames", "is empty; expected the records of the frames that were scored")
    if any((f["scene"], f["file"]) not in records for f in frames):
        raise UserError(f"{path}: field 'frames' lacks the strip frames listed in {listed}: not the dataset the "
                        f"other results of {doc['protocol']['ref']} were scored on")
    # a list written before sequences were saved gets one (its strip frames unchanged)
    add_seq = seq is None
    seq = seq or choose_sequence(doc, frames)
    assert seq is not None  # the first strip frame is among the records (checked above)
    seq_frames = [{"scene": seq["scene"], "file": f["file"]} for f in seq["frames"]]
    if any((f["scene"], f["file"]) not in records for f in seq_frames):
        raise UserError(f"{path}: field 'frames' lacks the test sequence's frames listed in {listed}: not the "
                        f"dataset the other results of {doc['protocol']['ref']} were scored on")
    return frames, seq, add_seq, records, seq_frames


def _added_fields(path: Path, doc: dict, lines: list[str]) -> dict:
    """What `add` records in the filed results (ADD_KEY): where the file came from, and this
    machine's hardware when the run recorded none (said so in `lines`, and on the page)."""
    added: dict = {"added_from": str(path.resolve())}
    if not format_hardware(doc["submission"].get("hardware")):
        added["hardware"] = _hardware_here()
        added["hardware_source"] = "the machine that ran `skyeyes-bench leaderboard add` (not recorded by the run)"
        lines.append(f"  hardware: not in the results; recorded this machine's ({format_hardware(added['hardware'])})")
    return added


def _undo(created: list[Path], restore: list[tuple[Path, bytes]], new_dirs: list[Path], *, root: Path) -> None:
    """After a failed write: remove what was created, restore the files changed, and remove the
    folders made (if left empty)."""
    for p in reversed(created):
        with contextlib.suppress(UserError):
            safe.remove(p, root=root)
    for p, old in restore:
        with contextlib.suppress(UserError):
            safe.write_bytes(p, old, root=root)
    for d in reversed(new_dirs):
        with contextlib.suppress(OSError):
            d.rmdir()  # only if empty: a folder this call made and left nothing in


def add_result(results_path, *, root, name: str | None = None, force: bool = False) -> list[str]:
    """File `results_path` as `<root>/results/<name>.json` and save its strip frames and the test
    sequence's animation.

    Returns the lines to print (what was filed, what the strip and the animation have or lack).
    Raises UserError (one line) for a file the leaderboard cannot use or an existing name; then
    nothing is left behind: every check runs before the first write, and what this call created
    is removed if a write fails. Every path written or deleted is checked to lie under `root`
    where it is written (`safe`). Without `force` nothing is replaced or deleted.
    """
    path, root = Path(results_path), Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found (pass --root DIR)")
    doc = check_results(path)
    name = _name_to_file(path, doc, name)
    safe.writable(root)
    # 1. where everything goes, checked before anything is written
    dest, base, mine = _destinations(root, doc, name, force)
    listed = base / FRAMES_LIST
    frames, seq, add_seq, records, seq_frames = _strip_and_sequence(path, doc, listed)
    gt, gt_src = base / GROUND_TRUTH, Path(doc["dataset"].get("root") or ".")
    gt_seq = gt / SEQUENCE_FILE
    sub_src = Path(doc["submission"].get("path") or ".")
    gt_why = None if gt.is_dir() else _tiles_problem(gt_src, frames, records, "gt_sha256")
    has_gt_seq = gt_seq.exists() or gt_seq.is_symlink()
    gt_seq_why = None if has_gt_seq else _tiles_problem(gt_src, seq_frames, records, "gt_sha256")
    why = _tiles_problem(sub_src, frames, records, "sha256")
    seq_why = _tiles_problem(sub_src, seq_frames, records, "sha256")
    lines = [f"{dest}: {doc['submission'].get('method')} on {doc['protocol']['ref']}"]
    # 2. hardware: the run's, else this machine's (said so in the file and on the page)
    added = _added_fields(path, doc, lines)
    # 3. write: the frames list (once per protocol and dataset; the sequence added to an older
    # one), the ground truth's and this method's strip frames and animation, then the results
    # file, last (atomic). A failure removes what this call created and restores the list it
    # changed (and only that), so no half-filed row is left.
    new_dirs = [d for d in (root / "results", root / FRAMES_DIR, base) if not d.exists()]
    created: list[Path] = []
    restore: list[tuple[Path, bytes]] = []
    try:
        if not listed.is_file() or add_seq:
            if listed.is_file():
                with inputfiles.open_regular(listed) as f:
                    restore.append((listed, f.read(inputfiles.MAX_JSON_BYTES)))
            else:
                created.append(listed)
            write_frames_list(listed, frames, root=root, sequence=seq)
        n_seq, gt_size = f"{len(seq['frames'])} frames of {seq['sequence']}", None
        if not gt.is_dir():
            if gt_why is None or gt_seq_why is None:
                gt_size = _save_frames(gt_src, frames if gt_why is None else [], seq if gt_seq_why is None else None,
                                       gt, root=root, overwrite=False)
                created.append(gt)
            lines.append(f"  strip: ground truth {'saved' if gt_why is None else 'has no frames (' + gt_why + ')'}")
        elif gt_seq_why is None and not has_gt_seq:
            gt_size = save_sequence(gt_src, seq, gt_seq, root=root)
            created.append(gt_seq)
        if not has_gt_seq:
            lines.append(f"  sequence: ground truth saved ({n_seq}, {_kb(gt_size)})" if gt_seq_why is None else
                         f"  sequence: ground truth has no animation ({gt_seq_why})")
        size = None
        if why is None or seq_why is None:
            size = _save_frames(sub_src, frames if why is None else [], seq if seq_why is None else None, mine,
                                root=root, overwrite=force)
            created.append(mine)
        elif mine.exists() or mine.is_symlink():  # --force with frames no longer here: drop the old ones
            safe.remove(mine, root=root)
        lines.append(f"  strip: {len(frames)} frames saved to {mine}" if why is None else
                     f"  strip: no frames for {name} ({why}); the page says so")
        lines.append(f"  sequence: {n_seq} saved to {mine / SEQUENCE_FILE} ({_kb(size)})" if seq_why is None else
                     f"  sequence: no animation for {name} ({seq_why}); the page says so")
        doc[ADD_KEY] = added
        write_results_file(dest, doc, root=root)
    except BaseException:
        _undo(created, restore, new_dirs, root=root)
        raise
    return lines


def write_results_file(dest: Path, doc: dict, *, root: Path) -> None:
    """The filed results JSON (the bytes `outputfiles.write_json` writes), confined to `root`."""
    with safe.atomic_file(dest, root=root) as tmp:
        tmp.write_text(json.dumps(doc, indent=2, sort_keys=False, allow_nan=True) + "\n")
