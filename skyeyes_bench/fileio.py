"""File I/O at the edges: atomic writes, JSON, 8-bit sRGB PNG and float32 EXR depth.

Everything that writes goes through a temporary file in the destination folder followed by
`os.replace`, so a crash never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import stat
import struct
import tempfile
import zlib
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from .errors import UserError

#: Largest image we agree to decode (pixels). Guards against decompression bombs.
MAX_PIXELS = 8192 * 8192


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it to `path`, else delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; on success move it to `path` as a whole.

    An existing `path` is refused unless `overwrite` (then it is replaced only after the new
    content is complete).
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise UserError(f"{path}: already exists; pass --force to replace it")
    if path.exists() and not path.is_dir():
        raise UserError(f"{path}: is a file; expected a folder (or a path that does not exist)")
    creatable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


class AtomicFolderWriter:
    """Base of the writers that fill a folder all at once (datasets, submissions).

    Inside `with`, `self.root` is a temporary sibling of `final`. On a clean exit after
    `finish()` (which a subclass defines and which must set `self._finished = True`), and once
    `_before_commit()` has raised nothing, the folder is moved to `final`; on an exception, a
    missing `finish()` or a failed check, it is deleted and nothing appears at `final`.
    """

    def __init__(self, final: str | os.PathLike, *, overwrite: bool = False):
        self.final = Path(final)
        self.overwrite = overwrite
        self._ctx: contextlib.AbstractContextManager[Path] | None = None
        self._finished = False

    def __enter__(self):
        self._ctx = atomic_dir(self.final, overwrite=self.overwrite)
        self.root = self._ctx.__enter__()
        return self

    def _before_commit(self) -> None:
        """Last check of the complete temporary folder; raise to keep it from `final`."""

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                if not self._finished:
                    raise RuntimeError(f"{type(self).__name__} closed without finish(): nothing was written")
                self._before_commit()
            except BaseException as err:
                self._ctx.__exit__(type(err), err, None)  # deletes the temporary folder
                raise
        return self._ctx.__exit__(exc_type, exc, tb)


def check_output(path: str | os.PathLike, *, force: bool = False, sidecars=(), outside=(), inputs=(),
                 inputs_are: str = "the inputs") -> Path:
    """Refuse, before any work, an output file that could not be written or must not be:
    a folder, an existing file (or sidecar) without `force`, a parent that is a file or not
    writable, a place inside one of the `outside` folders (e.g. the submission being scored,
    where it would become an extra file), or one of the `inputs` files (`inputs_are` names them)."""
    path = Path(path)
    mine = (path, *map(Path, sidecars))
    taken = {Path(p).resolve() for p in inputs}
    for p in mine:
        if p.resolve() in taken:
            raise UserError(f"{path}: is one of {inputs_are}; write the output elsewhere")
    for p in mine:
        if p.is_dir():
            raise UserError(f"{p}: is a folder; expected the path of an output file")
        if (p.exists() or p.is_symlink()) and not force:
            raise UserError(f"{p}: already exists; pass --force to replace it")
    for root in outside:
        if Path(root).exists() and inside(path, root):
            raise UserError(f"{path}: lies inside {root}; write the output elsewhere")
    return creatable(path)


def creatable(path: str | os.PathLike) -> Path:
    """`path` if its nearest existing ancestor is a writable folder, else a one-line UserError
    (a parent that is a file used to surface as NotADirectoryError after the work was done)."""
    path = Path(path)
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"{path}: cannot be created ({parent} is a file, not a folder)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{path}: cannot be created ({parent} is not writable)")
    return path


def write_json(path: str | os.PathLike, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, allow_nan=True) + "\n")


#: Largest JSON file read (bytes): far above any manifest or results file, far below memory.
MAX_JSON_BYTES = 256 << 20
#: Deepest nesting of arrays and objects accepted in a JSON file (ours nest 5 deep).
MAX_JSON_DEPTH = 64

_FILE_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def inside(path: str | os.PathLike, root: str | os.PathLike) -> bool:
    """Whether `path`, with every symlink resolved, lies inside `root` (resolved too)."""
    try:
        Path(path).resolve().relative_to(Path(root).resolve())
        return True
    except ValueError:
        return False


def open_regular(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> BinaryIO:
    """Open a regular file for reading, never blocking: a folder, named pipe, socket or device is
    refused (a named pipe would block a plain open forever); with `root`, the path with its
    symlinks resolved must lie inside `root`. Every refusal is a one-line UserError."""
    path = Path(path)
    if "\x00" in str(path):
        raise UserError(f"{str(path)!r}: path holds a NUL character")
    if root is not None and not inside(path, root):
        raise UserError(f"{path}: leaves {root} (through '..' or a symlink)")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except OSError as e:
        raise UserError(f"{path}: cannot open ({e.strerror})") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = next((name for test, name in _FILE_KINDS if test(mode)), "not a regular file")
        raise UserError(f"{path}: is {kind}, expected a regular file")
    return os.fdopen(fd, "rb")


def check_regular(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> Path:
    """`path` if `open_regular` accepts it (for readers that open by name, e.g. image decoders)."""
    with open_regular(path, root=root):
        return Path(path)


def json_problem(obj: Any, allow_nan: bool) -> str | None:
    """Too deep a nesting, or (unless allow_nan) the first non-finite number, with its field."""
    stack: list[tuple[Any, str, int]] = [(obj, "", 1)]
    while stack:
        o, where, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            return f"nested more than {MAX_JSON_DEPTH} levels deep (at field '{where}')"
        if isinstance(o, dict):
            items = [(v, f"{where}.{k}" if where else str(k)) for k, v in o.items()]
        elif isinstance(o, list):
            items = [(v, f"{where}[{i}]") for i, v in enumerate(o)]
        else:
            if not allow_nan and isinstance(o, float) and not math.isfinite(o):
                return (f"field '{where}' is {o!r}: JSON numbers are finite (NaN, Infinity and overflowing "
                        f"numbers are refused)")
            continue
        stack.extend((v, w, depth + 1) for v, w in reversed(items))
    return None


def read_json(path: str | os.PathLike, *, root: str | os.PathLike | None = None, allow_nan: bool = False) -> Any:
    """The one JSON reader for files that come from outside: a regular file (see `open_regular`),
    at most MAX_JSON_BYTES, UTF-8, valid JSON, nested at most MAX_JSON_DEPTH deep, numbers that
    fit a float. NaN and Infinity (not JSON, but Python writes them) only with `allow_nan`
    (results files, whose PSNR of a perfect frame is Infinity). Every failure is one UserError line."""
    with open_regular(path, root=root) as f:
        size = os.fstat(f.fileno()).st_size
        if size > MAX_JSON_BYTES:
            raise UserError(f"{path}: {size} bytes, more than the {MAX_JSON_BYTES} a JSON file may hold here")
        data = f.read(MAX_JSON_BYTES + 1)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UserError(f"{path}: not UTF-8 text (byte {e.start}); expected a JSON file") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON here (nested more than {MAX_JSON_DEPTH} levels deep)") from None
    except ValueError as e:  # an integer of more than 4300 digits
        raise UserError(f"{path}: not valid JSON here ({_one_line(e)})") from None
    if problem := json_problem(obj, allow_nan):
        raise UserError(f"{path}: {problem}")
    return obj


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open_regular(path) as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------- images


def _oiio():
    import OpenImageIO as oiio  # noqa: N813  (heavy import, kept lazy)

    return oiio


def _one_line(msg: str) -> str:
    """OpenImageIO errors span several lines; user errors are one line."""
    return "; ".join(part.strip() for part in str(msg).splitlines() if part.strip())


def image_header(path: str | os.PathLike) -> tuple[int, int, int, str]:
    """(width, height, channels, pixel format) from the file header, without decoding pixels."""
    oiio = _oiio()
    check_regular(path)  # the decoder opens by name: a named pipe would block it forever
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"{path}: cannot open image ({_one_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        return spec.width, spec.height, spec.nchannels, str(spec.format)
    finally:
        inp.close()


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def png_problem(data: bytes) -> str | None:
    """What is wrong with the bytes of a PNG file, checked before any decoder sees them (libpng
    prints its own lines to stderr on a truncated or corrupt file): every chunk complete with a
    matching CRC up to IEND, an IHDR within the pixel limit, and compressed image data that
    inflates to exactly the rows the header promises (never more: no decompression bomb)."""
    if data[:8] != PNG_MAGIC:
        return "not a PNG file"
    pos, ihdr, idat = 8, None, []
    while True:
        if pos + 12 > len(data):
            return "truncated PNG (the file ends before its IEND chunk)"
        n, typ = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + n
        if end > len(data):
            return f"truncated PNG (chunk {typ.decode('latin-1')!r} runs past the end of the file)"
        if zlib.crc32(data[pos + 4:pos + 8 + n]) != struct.unpack(">I", data[end - 4:end])[0]:
            return f"corrupt PNG (chunk {typ.decode('latin-1')!r} fails its CRC)"
        if typ == b"IHDR":
            ihdr = data[pos + 8:pos + 8 + n]
        elif typ == b"IDAT":
            idat.append(data[pos + 8:pos + 8 + n])
        elif typ == b"IEND":
            break
        pos = end
    if ihdr is None or len(ihdr) != 13:
        return "corrupt PNG (no valid IHDR chunk)"
    w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", ihdr)
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16) or interlace not in (0, 1):
        return f"corrupt PNG (IHDR: bit depth {depth}, colour type {colour}, interlace {interlace})"
    if w == 0 or h == 0 or w * h > MAX_PIXELS:
        return f"image of {w}x{h} outside 1..{MAX_PIXELS} pixels"
    bits = _PNG_CHANNELS[colour] * depth
    if interlace == 0:
        expected = h * (1 + (w * bits + 7) // 8)
    else:  # Adam7: seven passes, each a sub-image with its own filter bytes
        expected = 0
        for x0, y0, dx, dy in ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4),
                               (1, 0, 2, 2), (0, 1, 1, 2)):
            pw, ph = (w - x0 + dx - 1) // dx, (h - y0 + dy - 1) // dy
            if pw and ph:
                expected += ph * (1 + (pw * bits + 7) // 8)
    inflate = zlib.decompressobj()
    try:
        rows = inflate.decompress(b"".join(idat), expected + 1)
    except zlib.error as e:
        return f"corrupt PNG (image data: {e})"
    if len(rows) > expected or inflate.unconsumed_tail:
        return f"corrupt PNG (image data inflates past the {expected} bytes of a {w}x{h} image)"
    if not inflate.eof or len(rows) < expected:
        return f"truncated PNG (image data holds {len(rows)} of the {expected} bytes of a {w}x{h} image)"
    return None


def _read_pixels(path: str | os.PathLike, fmt: str) -> np.ndarray:
    oiio = _oiio()
    with open_regular(path) as f:  # never a named pipe (the decoder opens by name and would block)
        head = f.read(8)
        if head == PNG_MAGIC:
            if problem := png_problem(head + f.read(4 * MAX_PIXELS * 2 + (1 << 20))):
                raise UserError(f"{path}: cannot decode image ({problem})")
    # PNG alpha is unassociated; without this OpenImageIO premultiplies colour by alpha on read,
    # so dropping alpha would leave darkened RGB.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise UserError(f"{path}: cannot open image ({_one_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        if spec.width * spec.height > MAX_PIXELS:
            raise UserError(
                f"{path}: image of {spec.width}x{spec.height} exceeds the {MAX_PIXELS} pixel limit"
            )
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None or (hasattr(pixels, "size") and pixels.size == 0):
            raise UserError(f"{path}: cannot decode image ({_one_line(inp.geterror()) or 'truncated?'})")
        if inp.has_error:
            raise UserError(f"{path}: cannot decode image ({_one_line(inp.geterror())})")
    finally:
        inp.close()
    return np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)


def read_image_uint8(path: str | os.PathLike) -> np.ndarray:
    """8-bit image as uint8 [H, W, C] (C as stored)."""
    return _read_pixels(path, "uint8")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """8-bit sRGB image as float32 [H, W, 3] in [0, 1]. Grey is expanded, alpha dropped."""
    px = read_image_uint8(path)
    if px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    elif px.shape[2] == 4:
        px = px[..., :3]
    elif px.shape[2] != 3:
        raise UserError(f"{path}: expected an RGB image, got {px.shape[2]} channels")
    return px.astype(np.float32) / 255.0


def to_uint8(img: np.ndarray) -> np.ndarray:
    """float [0,1] -> uint8 with rounding; uint8 passes through."""
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _write_pixels(path: str | os.PathLike, pixels: np.ndarray, fmt: str, attrs: dict | None = None) -> None:
    oiio = _oiio()
    path = Path(path)
    assert pixels.ndim == 3, pixels.shape  # [H, W, C]: a 2-D array scrambles 1-channel writes
    h, w, c = pixels.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))  # format chosen from the final name's extension
        if out is None:
            raise UserError(f"{path}: cannot write this image format ({_one_line(oiio.geterror())})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        for k, v in (attrs or {}).items():
            spec.attribute(k, v)
        if not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot open for writing: {out.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise OSError(f"{path}: write failed: {out.geterror()}")


def write_image(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write an 8-bit PNG from float [0,1] or uint8, [H, W, 3] or [H, W] (grey / labels)."""
    px = to_uint8(img)
    if px.ndim == 2:
        px = px[..., None]
    _write_pixels(path, px, "uint8")


def write_labels(path: str | os.PathLike, labels: np.ndarray) -> None:
    """Write integer labels [H, W] (0..255) as a 1-channel 8-bit PNG."""
    assert labels.ndim == 2, labels.shape
    if labels.min(initial=0) < 0 or labels.max(initial=0) > 255:
        raise ValueError("labels must lie in 0..255")
    _write_pixels(path, labels.astype(np.uint8)[..., None], "uint8")


def read_labels(path: str | os.PathLike) -> np.ndarray:
    return _read_pixels(path, "uint8")[..., 0]


def write_depth(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Write float32 depth [H, W] in metres as a 1-channel EXR (inf allowed for sky)."""
    assert depth.ndim == 2, depth.shape  # [H, W]
    # An empty DateTime keeps OpenImageIO from stamping the write time into the EXR header, so
    # the same depth gives byte-identical files (SynthTown's determinism promise).
    _write_pixels(path, depth.astype(np.float32)[..., None], "float", {"compression": "zip", "DateTime": ""})


def read_depth(path: str | os.PathLike) -> np.ndarray:
    """float32 depth [H, W] in metres from an EXR (first channel)."""
    return _read_pixels(path, "float")[..., 0].astype(np.float32)
