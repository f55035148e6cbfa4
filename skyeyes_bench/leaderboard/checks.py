"""Every field of the leaderboard's inputs that becomes a path or page text, checked where it is
read (issue 35): results files (`add`, and `results/*.json` when the page is built), the committed
strip-frame lists with their test sequence (`frames/<key>/frames.json`) and the reported-numbers
TOML (`reported/*.toml`).

`results.read_results` checks that fields have the right JSON types; this adds what the
leaderboard needs on top: names that become folders are plain names, text that reaches the page
is one plain line (no control or bidirectional characters), hashes are hex of the right length,
`protocol.ref` is `id@N` with a bounded N, run times are finite and sum to a finite number.
Every failure is a one-line UserError naming the file, the field and what was expected.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from .. import fields, inputfiles, safe
from ..errors import UserError
from ..metricspec import METRICS
from .kinds import KINDS

#: Names that `leaderboard add` cannot file a result under: they are taken in `frames/<key>/`
#: (the ground-truth row's tiles and the list of chosen frames).
RESERVED = ("ground-truth", "frames.json")
#: `id@N`: a protocol id as protocol files name it (lowercase, digits, '-', '_', dots only between
#: parts, at most 64) and a version 1..999999 without leading zeros (a 5000-digit version is
#: refused here, before anything converts it to an integer).
REF = re.compile(r"(?=.{1,64}@)[a-z0-9][a-z0-9_-]*(?:\.[a-z0-9_-]+)*@[1-9][0-9]{0,5}")
#: Largest run time (fit + render seconds) shown and plotted: more than 30,000 years, far below
#: where a log axis from it overflows.
MAX_RUN_S = 1e12
#: Most strip frames (columns) a frames.json may list (`add` chooses 4).
MAX_STRIP_FRAMES = 32
#: Most frames of the test sequence a frames.json may list (`add` lists the first this many of a
#: longer sequence: 8 s at 8 frames per second).
MAX_SEQUENCE_FRAMES = 64
#: Most bootstrap resamples the marks' fallback rule draws (each a row of per-sequence values).
MAX_RESAMPLES = 100_000
#: Most components a results file may list for its method (`submission.config.components`).
MAX_COMPONENTS = 64


def _where(path, field: str) -> str:
    return f"{path}: field '{field}'"


def protocol_ref(where: str, value: Any) -> str:
    if not (isinstance(value, str) and len(value) <= 72 and REF.fullmatch(value)):
        raise UserError(f"{where}: expected a protocol reference 'ID@N' (ID: lowercase letters, digits, '-', '_', "
                        f"'.'; N: a version 1..999999), got {fields.short(value)}")
    return value


def filed_name(where: str, value: Any, what: str) -> str:
    """A name a result is filed under: `results/<name>.json` and `frames/<key>/<name>/`."""
    safe.plain_name(where, value, what)
    if value in RESERVED:
        raise UserError(f"{where}: {value!r} is taken by the strip's own files in frames/ (reserved: "
                        f"{', '.join(RESERVED)}); pass --name NAME to file it under another name")
    return value


def _optional_text(where: str, value: Any, what: str, max_len: int = 200) -> None:
    if value is not None:
        safe.plain_text(where, value, what, max_len=max_len)


def hardware(path, field: str, hw: Any) -> None:
    """`{"cpu", "cores", "gpu", ...}` or null; the parts that reach the page are plain text."""
    if hw is None:
        return
    if not isinstance(hw, dict):
        raise UserError(f"{_where(path, field)}: expected an object {{cpu, cores, gpu}} or null, got "
                        f"{fields.short(hw)}")
    for key in ("cpu", "gpu"):
        _optional_text(_where(path, f"{field}.{key}"), hw.get(key), "a hardware name")
    if hw.get("cores") is not None:
        fields.integer(_where(path, f"{field}.cores"), hw["cores"], "a core count", 1, 1 << 20)


def run_seconds(path, timings: Any, *, required: bool) -> tuple[float | None, float | None]:
    """(fit_s, render_s) of `submission.timings`: each a finite number >= 0 (or, unless `required`,
    null), and their sum at most MAX_RUN_S (two finite numbers can sum to inf)."""
    out = []
    for key in ("fit_s", "render_s"):
        v = timings.get(key) if isinstance(timings, dict) else None
        if v is None and not required:
            out.append(None)
            continue
        if not (fields.is_number(v) and 0 <= v <= MAX_RUN_S):
            what = "missing" if v is None else f"is {fields.short(v)}"
            raise UserError(f"{_where(path, f'submission.timings.{key}')} {what}; expected the seconds the submission "
                            f"reports (a number in 0..{MAX_RUN_S:g}): the leaderboard shows and plots run time (fit + "
                            f"render)")
        out.append(float(v))
    fit, ren = out
    if fit is not None and ren is not None and not fit + ren <= MAX_RUN_S:
        raise UserError(f"{_where(path, 'submission.timings')}: fit_s + render_s = {fit + ren:g} s, more than "
                        f"{MAX_RUN_S:g}; expected the run time of a run (fit + render seconds)")
    return fit, ren


def method_config(path, config: Any) -> None:
    """What the board prints from `submission.config`, when recorded: "kind", one of `kinds.KINDS`
    (the row's Kind column), and "components", a list of plain one-line strings (the row's line
    under its table). A config without them is a legacy run's: `kinds` derives both."""
    if not isinstance(config, dict):
        return
    kind = config.get("kind")
    if kind is not None and (not isinstance(kind, str) or kind not in KINDS):
        raise UserError(f"{_where(path, 'submission.config.kind')}: expected the row's kind, one of "
                        f"{', '.join(KINDS)}, got {fields.short(kind)}")
    comps = config.get("components")
    if comps is None:
        return
    if not (isinstance(comps, list) and len(comps) <= MAX_COMPONENTS):
        raise UserError(f"{_where(path, 'submission.config.components')}: expected a list of at most "
                        f"{MAX_COMPONENTS} strings, each a part the method runs, got {fields.short(comps)}")
    for i, c in enumerate(comps):
        safe.plain_text(_where(path, f"submission.config.components[{i}]"), c, "a part the method runs", max_len=500,
                        empty=False)


def _rel_path(where: str, value: Any, what: str) -> None:
    if not (isinstance(value, str) and 0 < len(value) <= 1024 and all(
            safe.NAME.fullmatch(part) and ".." not in part for part in value.split("/"))):
        raise UserError(f"{where}: expected {what} (a relative path of plain names such as 'ground/000012.png'), "
                        f"got {fields.short(value)}")


def results_fields(doc: dict, path) -> None:
    """Check the fields of a results document (already through `read_results`) that the
    leaderboard turns into paths, folder names or page text."""
    w = lambda field: _where(path, field)  # noqa: E731
    protocol_ref(w("protocol.ref"), doc["protocol"]["ref"])
    safe.hex_digest(w("protocol.sha256"), doc["protocol"]["sha256"], "the protocol file's sha256")
    for key in ("ground_truth", "submission_frames"):
        safe.hex_digest(w(f"sha256.{key}"), doc["sha256"][key])
    ds = doc["dataset"]
    safe.plain_text(w("dataset.name"), ds["name"], "the dataset's name", empty=False)
    for i, sid in enumerate(ds["sequences"]):
        safe.plain_text(w(f"dataset.sequences[{i}]"), sid, "a sequence id", empty=False)
    if ds.get("root") is not None:
        safe.plain_text(w("dataset.root"), ds["root"], "the dataset folder it was scored against", max_len=4096)
    s = doc["submission"]
    _optional_text(w("submission.method"), s.get("method"), "the method's name")
    _optional_text(w("submission.method_version"), s.get("method_version"), "the method's version")
    if s.get("path") is not None:
        safe.plain_text(w("submission.path"), s["path"], "the submission folder that was scored", max_len=4096)
    hardware(path, "submission.hardware", s.get("hardware"))
    method_config(path, s.get("config"))
    run_seconds(path, s.get("timings"), required=False)
    peak = s.get("peak_memory_mb")
    if peak is not None:
        fields.number(w("submission.peak_memory_mb"), peak, "the peak memory in MB (a finite number >= 0)", 0,
                      lo_open=False)
    added = doc.get("leaderboard")
    if added is not None:
        if not isinstance(added, dict):
            raise UserError(f"{w('leaderboard')}: expected what `leaderboard add` records (an object), got "
                            f"{fields.short(added)}")
        hardware(path, "leaderboard.hardware", added.get("hardware"))
    for ex_id, info in doc["extractors"].items():
        safe.plain_name(w(f"extractors.{fields.short(ex_id, 40)}"), ex_id, "an extractor id")
        if info.get("weights_sha256") is not None:
            safe.hex_digest(w(f"extractors.{ex_id}.weights_sha256"), info["weights_sha256"], "the weights' sha256")
    for name, m in doc["metrics"].items():
        if name in METRICS:
            for key in ("interval_note", "interval_reason"):
                _optional_text(w(f"metrics.{name}.{key}"), m.get(key), "why the metric has no interval", 500)
    st = doc.get("statistics")
    if st is not None:
        if not isinstance(st, dict):
            raise UserError(f"{w('statistics')}: expected an object, got {fields.short(st)}")
        if "resamples" in st:
            fields.integer(w("statistics.resamples"), st["resamples"], "the number of resamples", 1, MAX_RESAMPLES)
        if "seed" in st:
            fields.integer(w("statistics.seed"), st["seed"], "the resampling seed", 0, (1 << 64) - 1)
        if st.get("clusters") is not None:
            fields.integer(w("statistics.clusters"), st["clusters"], "the number of clusters", 0, 1 << 31)
        if "level" in st:
            fields.number(w("statistics.level"), st["level"], "the interval's level (a number in (0, 1))", 0, 1)
    for i, r in enumerate(doc["frames"]):
        safe.plain_name(w(f"frames[{i}].scene"), r["scene"], "a scene name")
        _rel_path(w(f"frames[{i}].file"), r["file"], "the frame's file in its scene")
        safe.hex_digest(w(f"frames[{i}].sha256"), r["sha256"], "the submitted frame's sha256")
        safe.hex_digest(w(f"frames[{i}].gt_sha256"), r["gt_sha256"], "the ground-truth frame's sha256")


def frames_list(path: Path) -> list[dict]:
    """The strip frames listed in `frames/<key>/frames.json` (`frames_file`)."""
    return frames_file(path)[0]


def frames_file(path: Path) -> tuple[list[dict], dict | None]:
    """The strip frames and the test sequence (None in a list written before sequences were
    saved) of `frames/<key>/frames.json`, checked.

    frames: 1..MAX_STRIP_FRAMES records {scene, file, sequence, index, label, tile}, where scene
    and file name a frame inside a scene folder, label is plain text and tile a plain PNG file name
    (unique). sequence: {scene, sequence, label, frames: 1..MAX_SEQUENCE_FRAMES records {file,
    index}}, each file a frame inside the scene folder (unique), label plain text.
    """
    raw = inputfiles.read_json(path)
    frames = raw.get("frames") if isinstance(raw, dict) else None
    tiles = set()
    for f, w in _records(path, "frames", frames, MAX_STRIP_FRAMES, "strip frames"):
        safe.plain_name(w("scene"), f.get("scene"), "a scene name")
        safe.plain_text(w("sequence"), f.get("sequence"), "a sequence id", max_len=1000)
        safe.plain_text(w("label"), f.get("label"), "the column's label", max_len=1000)
        tile = safe.plain_name(w("tile"), f.get("tile"), "the tile's file name")
        if not tile.endswith(".png") or tile in tiles:
            raise UserError(f"{w('tile')}: expected a file name ending in '.png', unique in the list, got {tile!r}")
        tiles.add(tile)
    return frames, _sequence(path, raw.get("sequence"))


def _records(path: Path, field: str, records: Any, most: int, what: str):
    """`records` checked as a list of 1..`most` frame objects, each with `file` (a frame inside
    its scene folder) and `index` (an integer): yields (record, where), where(name) naming the
    record's field `name` in errors."""
    if not (isinstance(records, list) and 1 <= len(records) <= most):
        raise UserError(f"{_where(path, field)}: expected a list of 1..{most} {what}, got {fields.short(records)}")
    for i, f in enumerate(records):
        if not isinstance(f, dict):
            raise UserError(f"{_where(path, f'{field}[{i}]')}: expected an object, got {fields.short(f)}")
        w = lambda name, i=i: _where(path, f"{field}[{i}].{name}")  # noqa: E731
        _rel_path(w("file"), f.get("file"), "the frame's file in its scene")
        fields.integer(w("index"), f.get("index"), "the frame's index in its sequence")
        yield f, w


def _sequence(path: Path, seq: Any) -> dict | None:
    if seq is None:
        return None
    if not isinstance(seq, dict):
        raise UserError(f"{_where(path, 'sequence')}: expected the test sequence (an object), got {fields.short(seq)}")
    safe.plain_name(_where(path, "sequence.scene"), seq.get("scene"), "a scene name")
    safe.plain_text(_where(path, "sequence.sequence"), seq.get("sequence"), "a sequence id", max_len=1000, empty=False)
    safe.plain_text(_where(path, "sequence.label"), seq.get("label"), "the sequence's label", max_len=1000)
    files = set()
    for f, w in _records(path, "sequence.frames", seq.get("frames"), MAX_SEQUENCE_FRAMES, "frames of the sequence"):
        if f["file"] in files:
            raise UserError(f"{w('file')}: {f['file']!r} is listed twice; expected each frame of the sequence once")
        files.add(f["file"])
    return seq


def reported_file(path: Path) -> dict:
    """A reported-numbers TOML, checked: what reaches the page is plain text, every score a finite
    number, `decimals` a small integer, `metrics` known metric names."""
    raw = inputfiles.read_toml(path, "a TOML file of reported numbers")
    w = lambda field: _where(path, field)  # noqa: E731
    for k in ("title", "protocol", "status", "citation", "metrics", "rows"):
        if k not in raw:
            raise UserError(f"{path}: missing key '{k}'")
    if raw["status"] != "reported":
        raise UserError(f"{path}: key 'status' must be \"reported\", got {fields.short(raw['status'])}")
    safe.plain_text(w("title"), raw["title"], "the table's title", empty=False)
    protocol_ref(w("protocol"), raw["protocol"])
    safe.plain_text(w("citation"), raw["citation"], "the paper it is copied from", max_len=1000, empty=False)
    _optional_text(w("note"), raw.get("note"), "a note on the table", 2000)
    if raw.get("decimals") is not None:
        fields.integer(w("decimals"), raw["decimals"], "the decimals the paper prints", 0, 10)
    metrics = raw["metrics"]
    if not (isinstance(metrics, list) and metrics and all(isinstance(m, str) for m in metrics)
            and len(set(metrics)) == len(metrics)):
        raise UserError(f"{w('metrics')}: expected a list of metric names (each once), got {fields.short(metrics)}")
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise UserError(f"{path}: unknown metrics {fields.short(sorted(unknown))} (known: {', '.join(METRICS)})")
    rows = raw["rows"]
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise UserError(f"{w('rows')}: expected a list of tables ([[rows]]), got {fields.short(rows)}")
    for i, r in enumerate(rows):
        if "method" not in r:
            raise UserError(f"{path}: rows[{i}] has no 'method'")
        safe.plain_text(w(f"rows[{i}].method"), r["method"], "the method's name", empty=False)
        _optional_text(w(f"rows[{i}].reference"), r.get("reference"), "the method's reference", 500)
        for m in metrics:
            v = r.get(m)
            if v is not None and not (fields.is_number(v) and math.isfinite(v)):
                raise UserError(f"{w(f'rows[{i}].{m}')}: expected the score the paper prints (a finite number, or "
                                f"leave the key out), got {fields.short(v)}")
    return raw
