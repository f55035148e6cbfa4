"""Submission format: what a method hands to `skyeyes-bench evaluate`.

```
<sub>/submission.json                      method, version, protocol id@N, timings, hardware, config
<sub>/<scene>/<frame.file>                 one 8-bit RGB PNG per ground camera of every test scene,
                                           e.g. sub/test-0-lane00/ground/000012.png, at the size
                                           the dataset gives for that frame
<sub>/EXPECTED_FRAMES.txt                  optional (written by `submission template`)
```

Methods write submissions with `SubmissionWriter` (atomic: a temporary folder renamed into place
when complete). `validate_submission` lists every problem at once; `evaluate` calls it first.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, fields, imagefiles, inputfiles, outputfiles
from .errors import UserError, ValidationError
from .splits import SCORED

SUBMISSION_FILE = "submission.json"
EXPECTED_FILE = "EXPECTED_FRAMES.txt"
FORMAT = "skyeyes-bench/submission@1"
#: The dataset split whose ground frames a submission holds: the test split of its dataset, or of
#: the view of a run on the validation split (`splits.scored_view`), whose "test" scenes are the
#: validation scenes; submission.json says which (`dataset.split`).
SPLIT = "test"
#: What `submission template` and `SubmissionWriter` write: `overwrite` (--force) replaces only an
#: empty folder or a folder holding a submission.json (`outputfiles.OutputKind`).
SUBMISSION_OUTPUT = outputfiles.OutputKind("a submission folder", folder=True, marker=SUBMISSION_FILE, formats=(FORMAT,))
#: cached_s: how much of fit_s + render_s was taken from caches (reported at its original cost).
_TIMING_KEYS = ("fit_s", "render_s", "per_frame_render_s", "cached_s")


def check_submission_out(out_dir, *, overwrite: bool, ds) -> None:
    """Refuse, in one line and before any work, a submission folder `out_dir` that may not be
    written: inside another submission (a parent folder holding a submission.json, found on the
    path as given and with its symlinks resolved: the new files would spoil that submission, whose
    evaluation then finds them), or what `outputfiles.check_output` refuses (the dataset, an existing
    folder without `overwrite`, anything but an earlier submission with it)."""
    out = Path(out_dir)
    if (parent := _enclosing_submission(out)) is not None:
        raise UserError(f"{out}: lies inside the submission {parent} (it holds {SUBMISSION_FILE}); writing "
                        "there would spoil that submission, so choose a folder outside it")
    outputfiles.check_output(out, force=overwrite, kind=SUBMISSION_OUTPUT, inputs=[ds.root], inputs_are="the dataset")


def _enclosing_submission(out: Path) -> Path | None:
    """The nearest folder above `out` that holds a submission.json, symlinks resolved (then as
    given), or None."""
    try:
        resolved = list(out.resolve().parents)
    except (OSError, RuntimeError):  # a symlink loop: check_output says so in one line
        resolved = []
    for parent in (*resolved, *Path(os.path.abspath(out)).parents):
        try:
            if (parent / SUBMISSION_FILE).exists():
                return parent
        except OSError:  # an unreadable folder holds nothing we can spoil
            continue
    return None


def expected_frames(ds) -> list[tuple[str, Any]]:
    """(scene name, ground Frame) for every ground camera of every test scene, in dataset order."""
    return [(scene.name, f) for scene in ds.split(SPLIT) for f in scene.ground]


def frame_relpath(scene: str, frame) -> str:
    """Where a submission stores `frame` of `scene`: `<scene>/<frame.file>` (POSIX)."""
    return f"{scene}/{frame.file}"


def detect_hardware() -> dict[str, Any]:
    """CPU model, core count, torch version (without importing torch), GPU if torch is loaded."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        from importlib.metadata import version

        torch_version = version("torch")
    except Exception:  # noqa: BLE001 - torch absent: just record None
        torch_version = None
    gpu = None
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(0)
    return {"cpu": cpu, "cores": os.cpu_count(), "gpu": gpu, "torch": torch_version,
            "python": platform.python_version(), "platform": platform.platform()}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _protocol_sha(ref: str) -> str | None:
    from .protocol import load_protocol

    try:
        return load_protocol(ref).sha256
    except UserError:
        return None


def _scores_same_data(ref: str, protocol) -> bool:
    """Whether a submission written for protocol `ref` holds the frames `protocol` scores: `ref` is
    `protocol` itself, the protocol whose data it scores, or another version of the same id
    that scores the same data (synthtown@3 and synthtown@4 both score synthtown@2's)."""
    from .protocol import load_protocol

    if ref in (protocol.ref, protocol.data_ref):
        return True
    if ref.partition("@")[0] != protocol.id:
        return False
    try:
        return load_protocol(ref).data_ref == protocol.data_ref
    except UserError:
        return False


def make_manifest(ds, *, method: str, method_version: str, config: dict | None, timings: dict | None,
                  peak_memory_mb: float | None, hardware: dict | None) -> dict[str, Any]:
    """The content of `submission.json` for a submission of dataset `ds`."""
    from .protocol import current_for_data

    n = len(expected_frames(ds))
    # New submissions are scored with the latest protocol that scores this data (synthtown@2's
    # data -> synthtown@3: the same frames with the depth-based metrics too).
    current = current_for_data(ds.protocol)
    return {
        "format": FORMAT,
        "method": method,
        "method_version": str(method_version),
        "protocol": current,
        "protocol_sha256": _protocol_sha(current),
        "dataset": {"name": ds.name, "split": ds.scored, "frames": n},
        "created": _now(),
        "tool_version": __version__,
        "timings": dict(timings or {}),
        "peak_memory_mb": peak_memory_mb,
        "hardware": hardware if hardware is not None else detect_hardware(),
        "config": dict(config or {}),
    }


class SubmissionWriter(outputfiles.AtomicFolderWriter):
    """Write a submission atomically.

    ```
    with SubmissionWriter(out, dataset=ds, method="sugar", method_version="0.1", config={...}) as w:
        for scene, frame in expected_frames(ds):
            w.add(scene, frame, image)          # float [H, W, 3] in [0, 1], or uint8
        w.finish(timings={"fit_s": 12.0, "render_s": 3.1, "per_frame_render_s": [...]},
                 peak_memory_mb=2100.0)
    ```
    Nothing appears at `out` unless `finish()` ran and the block exited without an exception; `out`
    may not be, hold or lie inside the dataset, and `overwrite` replaces only an earlier submission
    (`SUBMISSION_OUTPUT`), both checked here, before any work, and again as the folder is moved in.
    """

    kind = SUBMISSION_OUTPUT

    def __init__(self, out_dir, *, dataset, method: str, method_version: str = "", config: dict | None = None,
                 overwrite: bool = False):
        fields.name("method name", method, "the method's name")
        check_submission_out(out_dir, overwrite=overwrite, ds=dataset)
        super().__init__(out_dir, overwrite=overwrite, inputs=[dataset.root])
        self.ds = dataset
        self.method, self.method_version, self.config = method, str(method_version), dict(config or {})
        self._expected = {(s, f.file): f for s, f in expected_frames(dataset)}
        self._written: set[tuple[str, str]] = set()

    def add(self, scene_name: str, frame, image: np.ndarray) -> Path:
        """Write the image for ground `frame` of `scene_name`. image: float [H, W, 3] in [0,1] or uint8."""
        key = (scene_name, frame.file)
        if key not in self._expected:
            raise UserError(f"{scene_name}/{frame.file}: not a ground frame of a {self.ds.scored} scene of dataset "
                            f"{self.ds.name!r}")
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise UserError(f"{scene_name}/{frame.file}: expected an image [H, W, 3], got shape {img.shape}")
        if img.shape[:2] != (frame.height, frame.width):
            raise UserError(f"{scene_name}/{frame.file}: image is {img.shape[1]}x{img.shape[0]}, the camera "
                            f"is {frame.width}x{frame.height}")
        if img.dtype != np.uint8 and not np.isfinite(img).all():
            raise UserError(f"{scene_name}/{frame.file}: image holds NaN or inf")
        path = self.root / frame_relpath(scene_name, frame)
        path.parent.mkdir(parents=True, exist_ok=True)
        imagefiles.write_image(path, img)
        self._written.add(key)
        return path

    def finish(self, timings: dict | None = None, peak_memory_mb: float | None = None,
               hardware: dict | None = None) -> None:
        """Check completeness and write `submission.json`. timings: fit_s, render_s (seconds),
        per_frame_render_s (list of seconds)."""
        missing = [f"{s}/{f}" for (s, f) in self._expected if (s, f) not in self._written]
        if missing:
            raise UserError(f"submission {self.final}: {len(missing)} of {len(self._expected)} frames not "
                            f"added (first: {missing[0]})")
        timings = dict(timings or {})
        unknown = set(timings) - set(_TIMING_KEYS)
        if unknown:
            raise UserError(f"timings: unknown keys {sorted(unknown)} (known: {', '.join(_TIMING_KEYS)})")
        manifest = make_manifest(self.ds, method=self.method, method_version=self.method_version,
                                 config=self.config, timings=timings, peak_memory_mb=peak_memory_mb,
                                 hardware=hardware)
        # the method's own numbers pass the same check as a submission read from disk
        problems = _manifest_problems(manifest, self.final / SUBMISSION_FILE)
        if nonfinite := inputfiles.json_problem(manifest, allow_nan=False):
            problems.append(f"{self.final / SUBMISSION_FILE}: {nonfinite}")
        if problems:
            raise ValidationError(f"submission {self.final}", problems)
        outputfiles.write_json(self.root / SUBMISSION_FILE, manifest)
        self._finished = True


# --------------------------------------------------------------------------- reading


_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_PROTOCOL_REF = re.compile(r"^[a-z0-9][a-z0-9._-]*@[1-9]\d{0,8}$")


def _manifest_problems(m: Any, file: Path) -> list[str]:
    """Every problem of a submission.json object (the edge: nothing later sees an unchecked field)."""
    if not isinstance(m, dict):
        return [f"{file}: expected a JSON object"]
    problems = []

    def check(fn, key: str, *args, **kw):
        try:
            fn(f"{file}: field '{key}'", *args, **kw)
        except UserError as e:
            problems.append(str(e))

    if m.get("format") != FORMAT:
        problems.append(f"{file}: field 'format' is {fields.short(m.get('format'))}, expected {FORMAT!r}")
    check(fields.name, "method", m.get("method"), "the method's name")
    check(fields.string, "protocol", m.get("protocol"), "a protocol '<id>@<N>'", pattern=_PROTOCOL_REF)
    if m.get("protocol_sha256") is not None:
        check(fields.string, "protocol_sha256", m.get("protocol_sha256"), "null or a sha256 (64 hex digits)",
              pattern=_SHA256)
    for key in ("method_version", "created", "tool_version"):
        if key in m and not isinstance(m[key], str):
            problems.append(f"{file}: field '{key}' must be a string, got {fields.short(m[key])}")
    ds = m.get("dataset")
    if not isinstance(ds, dict) or not isinstance(ds.get("name"), str) or not ds.get("name"):
        problems.append(f"{file}: field 'dataset.name' missing (the dataset the frames were made for)")
    elif ds.get("split", "test") not in SCORED:
        problems.append(f"{file}: field 'dataset.split' is {fields.short(ds.get('split'))}, expected one of "
                        f"{', '.join(map(repr, SCORED))}")
    for key in ("hardware", "config"):
        if m.get(key) is not None and not isinstance(m[key], dict):
            problems.append(f"{file}: field '{key}' must be an object, got {fields.short(m[key])}")
    t = m.get("timings", {})
    if not isinstance(t, dict):
        problems.append(f"{file}: field 'timings' must be an object with {', '.join(_TIMING_KEYS)}")
    else:
        for k in t:
            if k not in _TIMING_KEYS:
                problems.append(f"{file}: field 'timings.{k}' unknown (known: {', '.join(_TIMING_KEYS)})")
        for k in ("fit_s", "render_s", "cached_s"):
            if k in t:
                check(fields.number, f"timings.{k}", t[k], "a number of seconds >= 0", 0, lo_open=False)
        pf = t.get("per_frame_render_s", [])
        if not (isinstance(pf, list) and all(fields.is_number(v) and v >= 0 for v in pf)):
            problems.append(f"{file}: field 'timings.per_frame_render_s' must be a list of seconds >= 0, "
                            f"got {fields.short(pf)}")
    if m.get("peak_memory_mb") is not None:
        check(fields.number, "peak_memory_mb", m["peak_memory_mb"], "a number of MB >= 0 or null", 0,
              lo_open=False)
    return problems


def read_submission(sub_dir) -> dict[str, Any]:
    """Read and check `submission.json` (not the frames). Raises UserError / ValidationError."""
    sub = Path(sub_dir)
    if not sub.is_dir():
        raise UserError(f"{sub}: not a folder (expected a submission folder holding {SUBMISSION_FILE})")
    file = sub / SUBMISSION_FILE
    if not file.is_file():
        raise UserError(f"{file}: missing (every submission has one; `skyeyes-bench submission template` "
                        f"shows the format)")
    m = inputfiles.read_json(file)
    problems = _manifest_problems(m, file)
    if problems:
        raise ValidationError(f"submission {sub}", problems)
    return m


def validate_submission(sub_dir, ds, protocol, manifest: dict, *, frames=None, decode: bool = True,
                        progress: bool = False) -> list[str]:
    """Every problem of a submission against dataset `ds` and `protocol` (empty list: valid).

    Checks: protocol and dataset match; every expected frame present, no extra files; every path
    stays inside the submission folder (symlinks included); each image is an 8-bit RGB PNG of
    the camera's size, not absurdly large (decompression bomb), and decodes completely.

    Args:
        frames: the (scene, Frame) pairs to check (default: every expected frame); a shard
            checks only its own frames but always the whole folder for extra/escaping files.
        decode: decode every image fully (catches truncated files).
        progress: a progress bar on stderr over the frames.
    """
    sub = Path(sub_dir)
    root = sub.resolve()
    problems = _match_problems(sub / SUBMISSION_FILE, ds, protocol, manifest)
    all_expected = expected_frames(ds)
    expected = {frame_relpath(s, f): f for s, f in all_expected}
    extra, escaped = _walk_problems(sub, root, ds, expected)
    problems.extend(extra)
    check = frames if frames is not None else all_expected
    problems.extend(_frame_problems(sub, root, check, escaped, decode=decode, progress=progress))
    return problems


def _match_problems(mfile: Path, ds, protocol, manifest: dict) -> list[str]:
    """What of the manifest `mfile` does not match `protocol` and dataset `ds` (the protocol and
    its file's sha256, the dataset's protocol, split and name)."""
    problems: list[str] = []
    # A protocol also scores submissions written for another that scores the same data: the one
    # whose data it is (synthtown@3 scores synthtown@2's frames) or a sibling version (a
    # synthtown@4 submission scored as synthtown@3, to file it in that table). Its
    # protocol_sha256 is then checked against that protocol's file.
    written_for = manifest["protocol"] if _scores_same_data(manifest["protocol"], protocol) else protocol.ref
    if manifest["protocol"] != written_for:
        problems.append(f"{mfile}: field 'protocol' is {manifest['protocol']!r}, the evaluation uses "
                        f"{protocol.ref!r}, which scores the data of {protocol.data_ref!r} (and submissions "
                        f"written for any protocol that scores that data)")
    sha = manifest.get("protocol_sha256")
    want = protocol.sha256 if written_for == protocol.ref else _protocol_sha(written_for)
    if sha and want and sha != want:
        problems.append(f"{mfile}: field 'protocol_sha256' does not match protocol {written_for} "
                        f"({sha[:12]}... vs {want[:12]}...): the protocol file changed")
    if ds.protocol != protocol.data_ref:
        problems.append(f"{ds.root}/dataset.json: dataset is for protocol {ds.protocol!r}, the submission "
                        f"for {protocol.ref!r}" + (f" (which scores data made for {protocol.data_ref!r})"
                                                  if protocol.data_ref != protocol.ref else ""))
    if manifest["dataset"].get("split", "test") != ds.scored:
        problems.append(f"{mfile}: field 'dataset.split' is {manifest['dataset'].get('split', 'test')!r}, the "
                        f"dataset is seen as its {ds.scored!r} split")
    if manifest["dataset"]["name"] != ds.name:
        problems.append(f"{mfile}: field 'dataset.name' is {manifest['dataset']['name']!r}, the dataset is "
                        f"{ds.name!r}")
    return problems


def _walk_problems(sub: Path, root: Path, ds, expected: dict) -> tuple[list[str], set[str]]:
    """Walk the submission folder `sub` (resolved: `root`) for each symlink that leaves it and each
    extra file (not in `expected`, the relative paths of the expected frames, nor a manifest).
    Returns (the problems, the relative paths of the escaping links)."""
    problems: list[str] = []
    escaped: set[str] = set()
    for dirpath, dirnames, filenames in os.walk(sub, followlinks=False):
        d = Path(dirpath)
        for name in dirnames + filenames:
            p = d / name
            rel = p.relative_to(sub).as_posix()
            if p.is_symlink() and not inputfiles.inside(p, root):
                problems.append(f"{p}: symlink leaves the submission folder (points to {os.readlink(p)})")
                escaped.add(rel)
                continue
            if name in dirnames:
                continue
            if rel not in expected and rel not in (SUBMISSION_FILE, EXPECTED_FILE):
                problems.append(f"{p}: extra file (not a ground frame of a {ds.scored} scene of {ds.name!r})")
    return problems, escaped


def _frame_problems(sub: Path, root: Path, check, escaped: set[str], *, decode: bool, progress: bool) -> list[str]:
    """The problems of the expected frames `check` ((scene, Frame) pairs) in the submission folder
    `sub` (resolved: `root`): a path leaving the folder (unless under a link in `escaped`, reported
    already), a bad image (`image_problems`), and one line for every frame missing."""
    problems: list[str] = []
    missing = []
    from tqdm import tqdm

    for scene, frame in tqdm(check, desc="validate", unit="frame", disable=None if progress else True, leave=False,
                             file=sys.stderr):
        rel = frame_relpath(scene, frame)
        p = sub / rel
        if not inputfiles.inside(p, root):
            reported = any(rel == e or rel.startswith(e + "/") for e in escaped)
            if (p.exists() or p.is_symlink()) and not reported:
                problems.append(f"{p}: path leaves the submission folder")
            continue
        if not p.exists():
            missing.append(rel)
            continue
        problems.extend(image_problems(p, frame.width, frame.height, decode=decode, root=root))
    if missing:
        shown = ", ".join(missing[:5]) + (f", ... ({len(missing) - 5} more)" if len(missing) > 5 else "")
        problems.append(f"{sub}: {len(missing)} expected frame(s) missing: {shown}")
    return problems


_PNG_COLOUR = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


def image_problems(path: Path, width: int, height: int, *, decode: bool = True,
                   root: Path | None = None) -> list[str]:
    """Problems of one submitted frame: not a decodable 8-bit RGB PNG of width x height.

    The size, bit depth and colour type come from the PNG header (IHDR) read by hand, so an
    absurd size (decompression bomb) is refused before any decoder allocates memory.
    """
    import struct

    try:
        with inputfiles.open_regular(path, root=root) as f:  # never a named pipe or a file outside
            head = f.read(33)
    except UserError as e:
        return [str(e)]
    except OSError as e:
        return [f"{path}: unreadable ({e.strerror})"]
    if head[:8] != imagefiles.PNG_MAGIC:
        return [f"{path}: not a PNG file"]
    if len(head) < 33 or head[12:16] != b"IHDR":
        return [f"{path}: truncated or corrupt PNG (no IHDR header)"]
    w, h, depth, colour = struct.unpack(">IIBB", head[16:26])
    if w * h > imagefiles.MAX_PIXELS:
        return [f"{path}: absurd image size {w}x{h} (limit {imagefiles.MAX_PIXELS} pixels; expected {width}x{height})"]
    out = []
    if (w, h) != (width, height):
        out.append(f"{path}: image is {w}x{h}, expected {width}x{height}")
    if colour != 2:
        out.append(f"{path}: expected an RGB image (PNG colour type 2), got {_PNG_COLOUR.get(colour, colour)}")
    if depth != 8:
        out.append(f"{path}: expected 8 bits per channel, got {depth}")
    if out or not decode:
        return out
    try:
        imagefiles.read_image_uint8(path)
    except UserError as e:
        return [str(e)]
    return []


def _expected_listing(frames) -> str:
    lines = [f"{frame_relpath(s, f)}\t{f.width}x{f.height}\t{f.sequence}\t{f.index}\n" for s, f in frames]
    return "# path\tsize\tsequence\tindex  (one 8-bit RGB PNG each)\n" + "".join(lines)


def write_template(ds, out_dir, *, from_ground_truth: bool = False, overwrite: bool = False) -> Path:
    """A valid skeleton: `submission.json` and the list of expected frame paths; with
    `from_ground_truth`, a complete submission made of the ground-truth frames (scores perfectly)."""
    frames = expected_frames(ds)
    if from_ground_truth:
        w = SubmissionWriter(out_dir, dataset=ds, method="ground-truth", method_version=__version__,
                             config={"note": "the ground-truth frames themselves (perfect submission)"},
                             overwrite=overwrite)
        with w:
            import shutil

            for scene, f in frames:
                dst = w.root / frame_relpath(scene, f)
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(f.path, dst)  # byte-identical: no re-encoding
                w._written.add((scene, f.file))
            (w.root / EXPECTED_FILE).write_text(_expected_listing(frames))
            w.finish(timings={"fit_s": 0.0, "render_s": 0.0, "per_frame_render_s": [0.0] * len(frames)},
                     peak_memory_mb=0.0)
        return Path(out_dir)
    check_submission_out(out_dir, overwrite=overwrite, ds=ds)
    with outputfiles.atomic_dir(out_dir, overwrite=overwrite, kind=SUBMISSION_OUTPUT, inputs=[ds.root]) as tmp:
        manifest = make_manifest(ds, method="my-method", method_version="0.0", config={"example": True},
                                 timings={"fit_s": 0.0, "render_s": 0.0, "per_frame_render_s": []},
                                 peak_memory_mb=None, hardware=None)
        outputfiles.write_json(tmp / SUBMISSION_FILE, manifest)
        (tmp / EXPECTED_FILE).write_text(_expected_listing(frames))
    return Path(out_dir)

