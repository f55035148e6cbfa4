"""`skyeyes-bench leaderboard add RESULTS.json`: check a results file and file it as
`results/<name>.json`, with the strip frames (`frames/<key>/...`) when the submission and the
dataset it was scored against are on this machine."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

from .. import fields, fileio
from ..errors import UserError
from .plots import FRAMES_DIR, FRAMES_LIST, GROUND_TRUTH, save_tile, write_frames_list
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


def _fail(path: Path, field: str, msg: str):
    raise UserError(f"{path}: field '{field}' {msg}")


def check_results(path: Path) -> dict:
    """The results document at `path`, or a one-line UserError naming the file, the field and
    what was expected."""
    from ..protocol import load_protocol
    from ..results import PARTIAL_FORMAT, RESULTS_FORMAT, read_results

    raw = fileio.read_json(path, allow_nan=True)
    if isinstance(raw, dict) and (raw.get("format") == PARTIAL_FORMAT or raw.get("shard")):
        _fail(path, "format" if raw.get("format") == PARTIAL_FORMAT else "shard",
              f"says these are partial results of one shard; expected complete results ({RESULTS_FORMAT!r}): "
              f"merge every shard first (`skyeyes-bench merge PARTS... --out results.json`)")
    doc, _ = read_results(path)
    ref = doc["protocol"]["ref"]
    try:
        proto = load_protocol(ref)
    except UserError as e:
        _fail(path, "protocol.ref", f"is {ref!r}: {e} (expected a protocol this skyeyes-bench knows)")
    if proto.sha256 != doc["protocol"]["sha256"]:
        _fail(path, "protocol.sha256", f"is {doc['protocol']['sha256'][:12]}…, but protocol {ref} is "
              f"{proto.sha256[:12]}… here: the protocol file changed since this result was scored")
    timings = doc["submission"].get("timings")
    for key in ("fit_s", "render_s"):
        v = timings.get(key) if isinstance(timings, dict) else None
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
            what = "missing" if v is None else f"is {fields._short(v)}"
            _fail(path, f"submission.timings.{key}", f"{what}; expected the seconds the submission reports (a "
                  f"number >= 0): the leaderboard shows and plots run time (fit + render)")
    if not any(m.get("status") == "ok" for m in doc["metrics"].values()):
        _fail(path, "metrics", "holds no metric with status 'ok'; expected at least one scored metric")
    for name, m in doc["metrics"].items():
        reps = m.get("replicates")
        if reps is not None and not (isinstance(reps, list) and all(
                v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in reps)):
            _fail(path, f"metrics.{name}.replicates", "expected a list of bootstrap replicate values (numbers or "
                  "null)")
    return doc


def _tiles_from(folder: Path, frames: list[dict], records: dict, sha_key: str, dst: Path, *,
                overwrite: bool) -> str | None:
    """Save the chosen frames of `folder` (a submission or a dataset root: `<scene>/<file>`) as
    small PNGs in `dst` if every one is there with the sha256 the results recorded; else say why not."""
    for f in frames:
        p = folder / f["scene"] / f["file"]
        if not p.is_file():
            return f"{p} not found"
        if fileio.sha256_file(p) != records[(f["scene"], f["file"])][sha_key]:
            return f"{p} differs from the frame that was scored (sha256)"
    with fileio.atomic_dir(dst, overwrite=overwrite) as tmp:
        for f in frames:
            save_tile(folder / f["scene"] / f["file"], tmp / f["tile"])
    return None


def add_result(results_path, *, root, name: str | None = None, force: bool = False) -> list[str]:
    """File `results_path` as `<root>/results/<name>.json` and save its strip frames.

    Returns the lines to print (what was filed, what the strip has or lacks).
    Raises UserError (one line) for a file the leaderboard cannot use or an existing name.
    """
    from ..submission import detect_hardware

    path, root = Path(results_path), Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found (pass --root DIR)")
    doc = check_results(path)
    if name is None:
        name = doc["submission"].get("method")
        if name is None:
            _fail(path, "submission.method", "is null; pass --name NAME")
        fields.name(f"{path}: field 'submission.method'", name, "a name to file the result under (or pass --name)")
    else:
        fields.name("--name", name, "the name to file the result under")
    dest = root / "results" / f"{name}.json"
    if dest.exists() and not force:
        raise UserError(f"{dest}: a result is already filed as {name!r}; pass --force to replace it or --name "
                        f"to file it under another name")
    lines = [f"{dest}: {doc['submission'].get('method')} on {doc['protocol']['ref']}"]
    # 1. hardware: the run's, else this machine's (said so in the file and on the page)
    added: dict = {"added_from": str(path.resolve())}
    if not format_hardware(doc["submission"].get("hardware")):
        added["hardware"] = detect_hardware()
        added["hardware_source"] = "the machine that ran `skyeyes-bench leaderboard add` (not recorded by the run)"
        lines.append(f"  hardware: not in the results; recorded this machine's ({format_hardware(added['hardware'])})")
    # 2. strip frames: the same frames for every method of this protocol and dataset
    base = root / FRAMES_DIR / frames_key(doc)
    listed = base / FRAMES_LIST
    frames = fileio.read_json(listed)["frames"] if listed.is_file() else choose_frames(doc)
    if not listed.is_file():
        write_frames_list(listed, frames)
    records = {(r["scene"], r["file"]): r for r in doc["frames"]}
    if any((f["scene"], f["file"]) not in records for f in frames):
        raise UserError(f"{path}: field 'frames' lacks the strip frames listed in {listed}: not the dataset the "
                        f"other results of {doc['protocol']['ref']} were scored on")
    gt = base / GROUND_TRUTH
    if not gt.is_dir():
        why = _tiles_from(Path(doc["dataset"].get("root") or "."), frames, records, "gt_sha256", gt, overwrite=False)
        lines.append(f"  strip: ground truth {'saved' if why is None else 'has no frames (' + why + ')'}")
    why = _tiles_from(Path(doc["submission"].get("path") or "."), frames, records, "sha256", base / name,
                      overwrite=force)
    if why is not None and (base / name).exists():  # --force with frames no longer here: drop the old ones
        shutil.rmtree(base / name)
    lines.append(f"  strip: {len(frames)} frames saved to {base / name}" if why is None else
                 f"  strip: no frames for {name} ({why}); the page says so")
    # 3. the results file, last (atomic), so a failure above leaves no half-filed row
    doc[ADD_KEY] = added
    fileio.write_json(dest, doc)
    return lines
