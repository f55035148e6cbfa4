"""Gallery picture: per lane, an aerial and a ground view with their depth and semantics."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import UserError


def colourise_depth(depth: np.ndarray) -> np.ndarray:
    """float [H, W] metres (inf = sky) -> float [H, W, 3]: inverse depth through 'magma', sky black."""
    from matplotlib import colormaps

    finite = np.isfinite(depth) & (depth > 0)
    inv = np.zeros_like(depth, dtype=np.float64)
    inv[finite] = 1.0 / depth[finite]
    if finite.any():
        lo, hi = np.percentile(inv[finite], [1, 99])
        inv = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = colormaps["magma"](inv)[..., :3]
    rgb[~finite] = 0.0
    return rgb


def tiles_from_dataset(root: Path, rows: int) -> list[dict]:
    """Pick up to `rows` lanes (test split first) and load their first aerial view (looking along the
    lane) and the middle frame of their `yaw000` ground sequence, with depth and semantics."""
    from ..layout import open_dataset

    ds = open_dataset(root)
    names = [s for split in ("test", "train") for s in ds.splits.get(split, ())]
    names += [s for s in ds.scenes if s not in names]
    out = []
    for name in names[:rows]:
        scene = ds.scenes[name]
        if not scene.aerial:
            continue
        seq = scene.sequences.get("yaw000") or next(iter(scene.sequences.values()))
        g = seq.frames[len(seq) // 2]
        a = scene.aerial[0]
        layers = [a.depth(), a.semantics(), g.depth(), g.semantics()]
        if any(x is None for x in layers):
            raise UserError(f"{scene.root}: gallery needs depth and semantics layers for aerial and ground frames")
        out.append({"name": name, "aerial": a.image(), "aerial_depth": layers[0], "aerial_sem": layers[1],
                    "ground": g.image(), "ground_depth": layers[2], "ground_sem": layers[3]})
    return out


def tiles_rendered(preset: str, seed: int, rows: int, size: int) -> list[dict]:
    """Render the same pairs straight from SynthTown (first lane of each town), at `size` pixels, 3x3 AA."""
    from dataclasses import replace

    from .generate import get_preset, lane_cameras, plan
    from .render import Scene, render

    p = replace(get_preset(preset), width=size, height=size)
    out = []
    for entry in plan(p, seed):
        scene = Scene.from_town(entry["town"], cull_m=p.cull_m)
        for li, lane in enumerate(entry["lanes"][:1]):
            ground, aerial = lane_cameras(lane, p, entry["town"])
            g = [c for s, i, c in ground if s == "yaw000"][p.frames // 2]
            a = aerial[0][2]
            ai, ad, al = render(scene, a, aa=3)
            gi, gd, gl = render(scene, g, aa=3)
            out.append({"name": entry["scenes"][li], "aerial": ai, "aerial_depth": ad, "aerial_sem": al,
                        "ground": gi, "ground_depth": gd, "ground_sem": gl})
        if len(out) >= rows:
            break
    return out[:rows]


def write_gallery(tiles: list[dict], out: Path) -> Path:
    """Compose the tiles into one PNG (matplotlib, Agg) with column titles and a label legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from ... import outputfiles
    from .render import LABELS, PALETTE, colourise_labels

    if not tiles:
        raise UserError("gallery: no lanes to show")
    cols = [("aerial", "aerial (52 m, pitch -45)"), ("aerial_depth", "aerial depth"), ("aerial_sem", "aerial semantics"),
            ("ground", "ground (2 m, yaw000)"), ("ground_depth", "ground depth"), ("ground_sem", "ground semantics")]
    h, w = tiles[0]["aerial"].shape[:2]
    tile = max(w, 160) / 100.0  # inches at dpi 100: small images are shown enlarged
    n = len(tiles)
    fig, axes = plt.subplots(n, len(cols), figsize=(len(cols) * tile / 0.965, n * tile * h / w + 0.75),
                             squeeze=False, dpi=100)
    for r, t in enumerate(tiles):
        for c, (key, title) in enumerate(cols):
            img = t[key]
            if key.endswith("_depth"):
                img = colourise_depth(img)
            elif key.endswith("_sem"):
                img = colourise_labels(img)
            ax = axes[r, c]
            ax.imshow(img, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=8)
            if c == 0:
                ax.set_ylabel(t["name"], fontsize=8)
    handles = [Patch(color=PALETTE[i] / 255.0, label=f"{i} {n}") for i, n in enumerate(LABELS)]
    fig.legend(handles=handles, loc="lower center", ncol=len(LABELS), fontsize=6.5, frameon=False)
    H = n * tile * h / w + 0.75
    fig.subplots_adjust(left=0.03, right=0.995, top=1 - 0.3 / H, bottom=0.4 / H, wspace=0.03, hspace=0.04)
    out = Path(out)
    with outputfiles.atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return out
