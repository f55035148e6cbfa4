"""The leaderboard's test sequence: one fixed test sequence per protocol and dataset, watched, not
only scored, so flicker is seen (issue 36).

`leaderboard add` saves the sequence's frames of the submission (and, once, of the ground truth)
as one small animated WebP, `frames/<key>/<name>/sequence.webp`; the page build draws one
composite animation per measured table, `strips/<table>-sequence.webp`: the ground truth first,
then each method that has a saved sequence, one labelled tile each, all in step (separate <img>
animations start at different times, so flicker could not be compared frame to frame).

Lossy WebP (Pillow; libwebp). Each file takes the first quality of a fixed ladder whose bytes fit
its budget, so the same frames give the same bytes on the same Pillow and libwebp. Another
libwebp may encode the same frames to other bytes, and lossy decoded pixels cannot tell "another
encoder" from "other inputs" (measured: re-encoding the composite at another effort moves 16 x 16
blocks by up to 16 levels; swapping one row for a slightly sharper render, by 13). So the
composite records its provenance in EXIF: the sha256 of its inputs and the encoder (Pillow and
libwebp versions); `same_sequence` accepts other bytes only from another encoder with the same
inputs (`--check`: the PNG plots' "other encoder, same pixels", for a lossy format).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..errors import UserError
from .plots import FRAMES_DIR, FRAMES_LIST, GROUND_TRUTH, TILE, fit_text, label_font
from .tables import Table

#: The animation of one row, in its folder `frames/<key>/<name>/` (and `ground-truth/`).
SEQUENCE_FILE = "sequence.webp"
#: Milliseconds per frame: 8 frames per second.
FRAME_MS = 125
#: Encoder effort (libwebp `method`, 0..6): 6 took 20 times as long on the composite for 8 % fewer bytes.
EFFORT = 4
#: (qualities tried in order, largest file wanted). Measured on synthtown@3's first test sequence
#: (test-0-lane00/yaw000, 32 frames of 128 x 128; docs/leaderboard.md): a row of the ground truth
#: 77 KB at quality 80, blurred 34 KB at 80, grainy and flickering (noise sd 12) 107 KB at 60,
#: constant 1 KB; a composite of 3 rows 190 KB at 60, of 11 rows 399 KB at 40 (6.6 s to encode).
ROW_QUALITIES, ROW_MAX_BYTES = (80, 70, 60, 50), 120_000
COMPOSITE_QUALITIES, COMPOSITE_MAX_BYTES = (60, 50, 40, 30), 450_000
#: Composite layout (pixels): at most COLUMNS tiles of TILE px a row, GAP apart, each under a
#: LABEL_H band with its row's name.
COLUMNS, GAP, LABEL_H = 6, 4, 16
#: Most FRAME_MS steps an animation read without a frame count may show.
MAX_STEPS = 10_000
#: Largest WebP file read (a saved row is at most ROW_MAX_BYTES unless its last quality missed).
MAX_WEBP_BYTES = 16 << 20
#: What the composite draws, in its inputs digest: bump it when `compose` draws differently, so a
#: composite encoded elsewhere (another libwebp) is not taken for the new drawing.
LAYOUT = 1
#: EXIF tags of the composite's provenance: ImageDescription (inputs), Software (encoder).
_INPUTS_TAG, _ENCODER_TAG = 0x010E, 0x0131
_INPUTS = "skyeyes-bench leaderboard sequence; inputs sha256 "


def encoder() -> str:
    """The Pillow and libwebp versions that encode here (the same frames, the same bytes)."""
    import PIL
    from PIL import features

    return f"Pillow {PIL.__version__}, libwebp {features.version('webp')}"


def encode_webp(frames: list[np.ndarray], qualities: tuple[int, ...], max_bytes: int, *,
                exif: dict[int, str] | None = None) -> bytes:
    """An animated, looping lossy WebP of `frames` (uint8 [H, W, 3] each, one size), FRAME_MS
    each: the first of `qualities` whose file has at most `max_bytes` (else the last). Pure and
    deterministic on one Pillow/libwebp. Identical consecutive frames are stored once with their
    durations summed (a still WebP when all are identical): `decode_webp` expands them again.
    `exif`: tag -> text written as EXIF (no timestamp is written)."""
    from PIL import Image

    assert frames and all(f.shape == frames[0].shape and f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3
                          for f in frames), "frames: uint8 [H, W, 3], one size"
    images = [Image.fromarray(f) for f in frames]
    extra = {}
    if exif:
        tags = Image.Exif()
        for tag, text in exif.items():
            tags[tag] = text
        extra["exif"] = tags.tobytes()
    for q in qualities:
        buf = io.BytesIO()
        images[0].save(buf, format="WEBP", save_all=True, append_images=images[1:], duration=FRAME_MS, loop=0,
                       lossless=False, quality=q, method=EFFORT, **extra)
        data = buf.getvalue()
        if len(data) <= max_bytes:
            break
    return data


def decode_webp(data: bytes, where: str, *, max_side: int = 8192, frames: int | None = None) -> list[np.ndarray]:
    """The frames (uint8 [H, W, 3]) of WebP `data`, one per FRAME_MS step (a frame shown for k
    steps is returned k times; a still WebP stands for `frames` equal frames). With `frames`, the
    count must be that. Every problem is a one-line UserError starting with `where`."""
    from PIL import Image

    if not (len(data) >= 12 and data[:4] == b"RIFF" and data[8:12] == b"WEBP"):
        raise UserError(f"{where}: not a WebP file; expected the animation `leaderboard add` saves")
    limit = frames if frames is not None else MAX_STEPS
    out: list[np.ndarray] = []
    try:
        im = Image.open(io.BytesIO(data), formats=["WEBP"])
        w, h = im.size
        if not (0 < w <= max_side and 0 < h <= max_side):
            raise UserError(f"{where}: animation of {w}x{h} pixels; expected at most {max_side} on a side")
        n = getattr(im, "n_frames", 1)
        if n > limit:
            raise UserError(f"{where}: holds {n} frames; expected at most {limit}")
        for i in range(n):
            im.seek(i)
            im.load()
            rgb = np.asarray(im.convert("RGB"))
            if n == 1 and not getattr(im, "is_animated", False):  # a still: every frame alike
                steps = frames or 1
            else:
                steps = max(1, round((im.info.get("duration") or 0) / FRAME_MS))
            out += [rgb] * min(steps, limit + 1 - len(out))
            if len(out) > limit:
                break
    except UserError:
        raise
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as e:
        raise UserError(f"{where}: cannot decode WebP ({' '.join(str(e).split()) or type(e).__name__})") from None
    if len(out) > limit or (frames is not None and len(out) != frames):
        raise UserError(f"{where}: shows {len(out)} frames of {FRAME_MS} ms; expected "
                        f"{frames if frames is not None else f'at most {limit}'}")
    return out


def read_webp_bytes(path: Path, *, root: Path) -> bytes:
    """The bytes of the WebP file at `path`: a regular file inside `root` (a link out of it, a
    pipe or a folder is refused in one line) of at most MAX_WEBP_BYTES."""
    from .. import inputfiles

    with inputfiles.open_regular(path, root=root) as f:
        data = f.read(MAX_WEBP_BYTES + 1)
    if len(data) > MAX_WEBP_BYTES:
        raise UserError(f"{path}: larger than {MAX_WEBP_BYTES >> 20} MB; expected a small animation")
    return data


def sequence_tiles(folder: Path, sequence: dict) -> list[np.ndarray]:
    """The sequence's frames from `folder` (a submission or a dataset root: `<scene>/<file>`) as
    uint8 [h, w, 3] tiles, longest side at most TILE px (never enlarged), all the first's size."""
    from PIL import Image

    from .. import imagefiles

    tiles: list[np.ndarray] = []
    for f in sequence["frames"]:
        img = Image.fromarray(imagefiles.to_uint8(imagefiles.read_image(folder / sequence["scene"] / f["file"])))
        if not tiles:
            img.thumbnail((TILE, TILE), Image.Resampling.LANCZOS)
        elif img.size != (tiles[0].shape[1], tiles[0].shape[0]):
            img = img.resize((tiles[0].shape[1], tiles[0].shape[0]), Image.Resampling.LANCZOS)
        tiles.append(np.asarray(img))
    return tiles


def save_sequence(folder: Path, sequence: dict, dst: Path, *, root: Path) -> int:
    """Write the sequence's frames of `folder` as `dst` (an animated WebP under `root`), atomically
    with the user's umask; returns its size in bytes."""
    from .. import safe

    data = encode_webp(sequence_tiles(folder, sequence), ROW_QUALITIES, ROW_MAX_BYTES)
    safe.write_bytes(dst, data, root=root)
    return len(data)


# --------------------------------------------------------------------------- the composite


def sequence_name(t: Table) -> str:
    return f"strips/{t.file_key}-sequence.webp"


def table_sequence(root: Path, t: Table) -> dict | None:
    """The test sequence `leaderboard add` chose for t's protocol and dataset (None: none yet)."""
    p = Path(root) / FRAMES_DIR / t.frames_key / FRAMES_LIST
    if not p.is_file():
        return None
    from .checks import frames_file

    return frames_file(p)[1]


def sequence_rows(root: Path, t: Table) -> list[tuple[str, Path | None]]:
    """(label, its saved animation or None) for the ground truth and each row of t, in page order."""
    base = Path(root) / FRAMES_DIR / t.frames_key
    out = []
    for label, sub in [("ground truth", GROUND_TRUTH), *[(r.method, r.name) for r in t.rows]]:
        p = base / sub / SEQUENCE_FILE
        # anything there counts (a pipe, a folder, a link out is refused where it is read, in one line)
        out.append((label, p if p.exists() or p.is_symlink() else None))
    return out


def compose(tiles: list[tuple[str, list[np.ndarray]]]) -> list[np.ndarray]:
    """Frames of the composite: one TILE x TILE cell per (label, frames) in a grid of at most
    COLUMNS a row, the label above its cell, each frame scaled to fit its cell (nearest when
    enlarged) and centred. Every entry holds the same number of frames. Pure.

    Returns uint8 [H, W, 3] per frame, H = rows * (LABEL_H + TILE) + (rows - 1) * GAP and
    W = cols * TILE + (cols - 1) * GAP.
    """
    from PIL import Image, ImageDraw

    assert tiles and len({len(fs) for _, fs in tiles}) == 1, "every row: the same number of frames"
    cols = min(len(tiles), COLUMNS)
    rows = -(-len(tiles) // cols)
    base = Image.new("RGB", (cols * TILE + (cols - 1) * GAP, rows * (LABEL_H + TILE) + (rows - 1) * GAP),
                     (255, 255, 255))
    draw, font = ImageDraw.Draw(base), label_font()
    cells = []
    for i, (label, frames) in enumerate(tiles):
        x, y = (i % cols) * (TILE + GAP), (i // cols) * (LABEL_H + TILE + GAP)
        draw.text((x + 2, y + 1), fit_text(draw, label, font, TILE - 4), fill=(0, 0, 0), font=font)
        h, w = frames[0].shape[:2]
        scale = min(TILE / w, TILE / h)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        cells.append(((x + (TILE - size[0]) // 2, y + LABEL_H + (TILE - size[1]) // 2), size, frames))
    out = []
    for k in range(len(tiles[0][1])):
        img = base.copy()
        for at, size, frames in cells:
            tile = Image.fromarray(frames[k])
            if tile.size != size:
                tile = tile.resize(size, Image.Resampling.NEAREST if size[0] > tile.width else
                                   Image.Resampling.LANCZOS)
            img.paste(tile, at)
        out.append(np.asarray(img))
    return out


def render_sequence(root: Path, t: Table) -> bytes | None:
    """The composite animation of table t (WebP bytes), or None when no row of it (ground truth
    included) has a saved sequence. A saved animation that is not one (not a WebP, too large,
    another frame count, a link out of `root`) is a one-line UserError."""
    sequence = table_sequence(root, t)
    if sequence is None:
        return None
    import hashlib
    import json

    n = len(sequence["frames"])
    rows = [(label, p) for label, p in sequence_rows(root, t) if p is not None]
    if not rows:
        return None
    tiles, digests = [], []
    for label, p in rows:
        data = read_webp_bytes(p, root=root)
        tiles.append((label, decode_webp(data, str(p), frames=n, max_side=TILE)))
        digests.append([label, hashlib.sha256(data).hexdigest()])
    inputs = json.dumps({"layout": LAYOUT, "tile": TILE, "columns": COLUMNS, "gap": GAP, "label_h": LABEL_H,
                         "frame_ms": FRAME_MS, "effort": EFFORT, "qualities": COMPOSITE_QUALITIES,
                         "max_bytes": COMPOSITE_MAX_BYTES, "sequence": sequence, "rows": digests}, sort_keys=True)
    return encode_webp(compose(tiles), COMPOSITE_QUALITIES, COMPOSITE_MAX_BYTES,
                       exif={_INPUTS_TAG: _INPUTS + hashlib.sha256(inputs.encode()).hexdigest(),
                             _ENCODER_TAG: encoder()})


def provenance(data: bytes) -> tuple[str, str] | None:
    """(inputs sha256, encoder) that a composite records in its EXIF; None if it records none
    (or is no WebP). Reads the header and metadata only, no pixels."""
    from PIL import Image

    if not (len(data) >= 12 and data[:4] == b"RIFF" and data[8:12] == b"WEBP"):
        return None
    try:
        exif = Image.open(io.BytesIO(data), formats=["WEBP"]).getexif()
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError):
        return None
    inputs, enc = exif.get(_INPUTS_TAG), exif.get(_ENCODER_TAG)
    if not (isinstance(inputs, str) and inputs.startswith(_INPUTS) and isinstance(enc, str)):
        return None
    return inputs[len(_INPUTS):], enc


def same_sequence(on_disk: bytes, generated: bytes) -> bool:
    """Whether the composite on disk is what the inputs generate: the same bytes; or, encoded by
    another Pillow/libwebp (which may write other bytes for the same frames), a WebP that decodes
    and records the same inputs. From the same encoder, other bytes are other inputs or drawing."""
    if on_disk == generated:
        return True
    mine, theirs = provenance(generated), provenance(on_disk)
    if mine is None or theirs is None or theirs[1] == mine[1] or theirs[0] != mine[0]:
        return False
    try:
        return len(decode_webp(on_disk, "on disk")) == len(decode_webp(generated, "generated"))
    except UserError:
        return False
