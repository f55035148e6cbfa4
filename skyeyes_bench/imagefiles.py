"""Image files: 8-bit sRGB PNG and float32 EXR depth, read and written through OpenImageIO;
PNG bytes checked before any decoder sees them (`png_problem`); semantic labels."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from .errors import UserError, single_line
from .inputfiles import check_regular, open_regular
from .outputfiles import atomic_path

#: Largest image we agree to decode (pixels). Guards against decompression bombs.
MAX_PIXELS = 8192 * 8192


def _oiio():
    import OpenImageIO as oiio  # noqa: N813  (heavy import, kept lazy)

    return oiio


def image_header(path: str | os.PathLike) -> tuple[int, int, int, str]:
    """(width, height, channels, pixel format) from the file header, without decoding pixels."""
    oiio = _oiio()
    check_regular(path)  # the decoder opens by name: a named pipe would block it forever
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"{path}: cannot open image ({single_line(oiio.geterror()) or 'unknown format'})")
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
        raise UserError(f"{path}: cannot open image ({single_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        if spec.width * spec.height > MAX_PIXELS:
            raise UserError(
                f"{path}: image of {spec.width}x{spec.height} exceeds the {MAX_PIXELS} pixel limit"
            )
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None or (hasattr(pixels, "size") and pixels.size == 0):
            raise UserError(f"{path}: cannot decode image ({single_line(inp.geterror()) or 'truncated?'})")
        if inp.has_error:
            raise UserError(f"{path}: cannot decode image ({single_line(inp.geterror())})")
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
            raise UserError(f"{path}: cannot write this image format ({single_line(oiio.geterror())})")
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
