"""Multiresolution hash encoding (Müller, Evans, Schied, Keller: "Instant Neural Graphics
Primitives with a Multiresolution Hash Encoding", SIGGRAPH 2022, sec. 3), in pure torch.

Per level l of L: a grid of resolution N_l = floor(N_min * b^l), b = exp((ln N_max - ln N_min) /
(L - 1)); a point x in [0, 1]^3 lies in the cell floor(x N_l) whose 8 corners are looked up in
the level's table of T = 2^log2_T feature vectors of width F and interpolated trilinearly.
Coarse levels with (N_l + 1)^3 <= T index their table densely (one entry per vertex, no
collision); finer ones hash a vertex as (i * 1 xor j * 2654435761 xor k * 805459861) mod T
(paper eq. 4). The output is the L levels' features concatenated, [N, L * F].

Convention at the upper edge: the cell index is clamped to N_l - 1, so x = 1 lies in the last
cell with weight 1 on its upper corner (vertex N_l) and the table of a dense level needs exactly
(N_l + 1)^3 entries. All levels share one parameter [L, T, F] so a lookup is one gather.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

#: NOTE: the primes of the paper's spatial hash (eq. 4; from Teschner et al. 2003, pi_1 = 1 for
#: cache coherence).
PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridConfig:
    """levels L, log2_T (table size T = 2^log2_T per level), features F per entry, resolutions
    N_min (coarsest) and N_max (finest) over the unit cube."""

    levels: int = 8
    log2_T: int = 15
    features: int = 2
    n_min: int = 16
    n_max: int = 512

    @property
    def table_size(self) -> int:
        return 2 ** self.log2_T

    @property
    def out_dim(self) -> int:
        return self.levels * self.features


def level_resolutions(cfg: HashGridConfig) -> list[int]:
    """N_l = floor(N_min * b^l) for l = 0..L-1 (paper eq. 2-3)."""
    if cfg.levels == 1:
        return [cfg.n_min]
    b = math.exp((math.log(cfg.n_max) - math.log(cfg.n_min)) / (cfg.levels - 1))
    # A hair of slack so that N_min * b^(L-1), which is N_max in exact arithmetic, floors to N_max.
    return [int(math.floor(cfg.n_min * b ** lvl * (1 + 1e-12))) for lvl in range(cfg.levels)]


class HashEncoding(nn.Module):
    """x [N, 3] in [0, 1]^3 -> features [N, L * F] (level-major: level 0's F features first)."""

    def __init__(self, cfg: HashGridConfig, *, init_scale: float = 1e-4, generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        res = level_resolutions(cfg)
        T = cfg.table_size
        #: levels 0..n_dense-1 index densely (resolutions grow, so the dense ones are a prefix)
        self.n_dense = sum((n + 1) ** 3 <= T for n in res)
        # NOTE: the paper initialises the tables uniformly in [-1e-4, 1e-4].
        # Made on the CPU (a CPU generator: the same table on every device); `.to(device)` moves it.
        table = (torch.rand(cfg.levels, T, cfg.features, generator=generator, device="cpu") * 2 - 1) * init_scale
        self.table = nn.Parameter(table)  # [L, T, F]
        self.register_buffer("res", torch.tensor(res, dtype=torch.long, device="cpu"), persistent=False)  # [L]
        res1 = self.res + 1
        strides = torch.stack([torch.ones_like(res1), res1, res1 * res1], -1)  # [L, 3]
        self.register_buffer("strides", strides, persistent=False)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.long, device="cpu"), persistent=False)  # [3]

    def corner_rows(self, cell: torch.Tensor) -> torch.Tensor:
        """Cells cell [N, L, 3] (lower corners) -> table rows [N, L, 8] of their 8 corners, corner
        c = 4 a + 2 b + d at cell + (a, b, d)."""
        nd, T = self.n_dense, self.cfg.table_size
        parts = []
        for sl, mul, dense in ((slice(0, nd), self.strides[:nd], True), (slice(nd, None), self.primes, False)):
            c = cell[:, sl]
            if c.shape[1] == 0:
                continue
            lo, hi = c * mul, (c + 1) * mul  # [N, l, 3]: each axis's term, lower and upper corner
            ax = [torch.stack([lo[..., k], hi[..., k]], -1) for k in range(3)]  # [N, l, 2] each
            a, b, d = ax[0][..., :, None, None], ax[1][..., None, :, None], ax[2][..., None, None, :]
            if dense:  # i + j (N+1) + k (N+1)^2
                parts.append((a + b + d).flatten(-3))
            else:  # hashed: xor of coordinate times prime, mod T (int64: no overflow below 2^31 cells)
                parts.append(((a ^ b ^ d) & (T - 1)).flatten(-3))
        return torch.cat(parts, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        assert x.ndim == 2 and x.shape[1] == 3, x.shape  # [N, 3]
        L, T, F = self.table.shape
        pos = x[:, None, :] * self.res.to(x.dtype)[:, None]  # [N, L, 3]
        cell = torch.minimum(pos.detach().floor().long().clamp_min(0), (self.res - 1)[:, None])  # [N, L, 3]
        frac = pos - cell.to(x.dtype)  # [N, L, 3]; gradients reach x through it
        rows = self.corner_rows(cell) + (torch.arange(L, device=x.device) * T)[:, None]  # [N, L, 8]
        feats = self.table.reshape(L * T, F)[rows]  # [N, L, 8, F]
        ax = [torch.stack([1 - frac[..., k], frac[..., k]], -1) for k in range(3)]  # [N, L, 2] each
        w = (ax[0][..., :, None, None] * ax[1][..., None, :, None] * ax[2][..., None, None, :]).flatten(-3)
        return (feats * w[..., None]).sum(2).reshape(len(x), L * F)
