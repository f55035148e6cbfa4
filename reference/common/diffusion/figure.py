"""The figure of a diffusion run: per frame of a sequence, the nearest aerial view, the condition,
the generated frame and the ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reference.common.priors import nearest_aerial
from skyeyes_bench import outputfiles
from skyeyes_bench.data.layout import Scene, Sequence


def write_figure(path: Path, scene: Scene, sequence: Sequence, conds: list[np.ndarray],
                 generated: list[np.ndarray], n: int, *, condition: str = "prior") -> None:
    """Rows: nearest aerial view, condition (prior), generated, ground truth; `n` frames spread
    over the sequence. Ground-truth pixels are read here, after generation, for display only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = np.unique(np.linspace(0, len(sequence) - 1, min(n, len(sequence))).round().astype(int))
    rows = [("aerial (nearest)", [nearest_aerial(scene, sequence.frames[i]).image() for i in idx]),
            (condition, [conds[i][..., :3] for i in idx]),  # the colour of a condition with more channels
            ("generated", [generated[i] for i in idx]),
            ("ground truth", [sequence.frames[i].image() for i in idx])]
    fig, axes = plt.subplots(len(rows), len(idx), figsize=(1.6 * len(idx), 1.7 * len(rows)), squeeze=False)
    for r, (label, imgs) in enumerate(rows):
        for col, (i, im) in enumerate(zip(idx, imgs)):
            ax = axes[r][col]
            ax.imshow(np.clip(im, 0, 1))
            ax.set_xticks([]), ax.set_yticks([])
            if col == 0:
                ax.set_ylabel(label, fontsize=7)
            if r == 0:
                ax.set_title(f"{sequence.name} #{i}", fontsize=7)
    fig.tight_layout()
    with outputfiles.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
