"""A frame's optional layers (docs/formats.md): depth (float32 metres, OpenEXR) and semantics (8-bit
labels, PNG), each in a folder beside its images (`ground/000012.png` -> `ground_depth/000012.exr`).
Their file names, the check that a layer file holds what its name says, and reading one.
`skyeyes_bench.data.layout` reads datasets with these (and re-exports the public names).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import imagefiles, inputfiles
from ..errors import UserError

LAYERS = ("depth", "semantics")
_LAYER_EXT = {"depth": ".exr", "semantics": ".png"}
#: What a layer file holds (docs/formats.md): the format its extension names (the bytes such a file
#: starts with), the pixel formats (OpenImageIO's names) and channel counts accepted (None: any),
#: and what the message says was expected. OpenImageIO reads any format whatever the name, so a
#: 16-bit PNG named .exr would otherwise be read as depth in metres.
_LAYER_FORMATS = {
    "depth": ("OpenEXR", b"v/1\x01", ("float",), (1,),
              "an OpenEXR file of 1 float32 channel (planar depth in metres, inf = sky)"),
    "semantics": ("PNG", imagefiles.PNG_MAGIC, ("uint8",), None, "an 8-bit PNG of labels"),
}
#: The first bytes of formats a layer file may hold by mistake, to say what it holds.
_SIGNATURES = ((b"v/1\x01", "an OpenEXR image"), (imagefiles.PNG_MAGIC, "a PNG image"),
               (b"\x93NUMPY", "a NumPy .npy array"), (b"PK\x03\x04", "a zip archive (.npz?)"),
               (b"\xff\xd8\xff", "a JPEG image"), (b"II*\x00", "a TIFF image"), (b"MM\x00*", "a TIFF image"))


def layer_file(file: str, layer: str) -> str:
    """`ground/000012.png` -> `ground_depth/000012.exr` (same stem, docs/formats.md)."""
    folder, _, name = file.rpartition("/")
    return f"{folder}_{layer}/{Path(name).stem}{_LAYER_EXT[layer]}"


def layer_header(path: Path, layer: str) -> tuple[int, int]:
    """(width, height) of a `layer` file, after checking from its bytes and header that it holds
    what its name says (`_LAYER_FORMATS`); else a one-line UserError naming the file, what it
    holds and what was expected."""
    name, magic, pixel, channels, expected = _LAYER_FORMATS[layer]
    with inputfiles.open_regular(path) as f:
        head = f.read(8)
    if not head.startswith(magic):
        held = next((what for sig, what in _SIGNATURES if head.startswith(sig)), None)
        held = f"holds {held}, not the {name} its name says" if held else f"holds no {name} data (it starts with {head!r})"
        raise UserError(f"{path}: {held}; expected {expected}")
    w, h, c, fmt = imagefiles.image_header(path)
    if fmt not in pixel or (channels is not None and c not in channels):
        raise UserError(f"{path}: holds {c} channel{'s' if c != 1 else ''} of {fmt}, expected {expected}")
    return w, h


def read_layer(path: Path, layer: str) -> np.ndarray:
    """The pixels of a `layer` file checked by `layer_header`: depth float32 [H, W] metres, labels uint8 [H, W]."""
    layer_header(path, layer)
    return imagefiles.read_depth(path) if layer == "depth" else imagefiles.read_labels(path)
