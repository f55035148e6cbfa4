"""The radiance field of the compact Instant-NGP: hash grid -> tiny density MLP -> (density,
geometry features); geometry features + view direction (real spherical harmonics up to degree 3,
16 coefficients: tiny-cuda-nn's "degree 4") -> tiny colour MLP -> rgb. And the occupancy grid
that lets ray marching skip empty space.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from reference.common.gaussians.project import sh_basis
from reference.common.nerf.encoding import HashEncoding, HashGridConfig
from reference.common.nerf.render import to_unit


@dataclass(frozen=True)
class FieldConfig:
    """grid: the hash encoding; hidden: width of both MLPs; geo_features: features passed from
    the density to the colour MLP; density_bias: added to the density MLP's output before exp, so
    that a fresh field is nearly empty (exp(-4) = 0.018 / m: ~1 optical depth across a 60 m box)."""

    grid: HashGridConfig = field(default_factory=HashGridConfig)
    hidden: int = 64
    geo_features: int = 15
    density_bias: float = -4.0


class _TruncExp(torch.autograd.Function):
    """exp with its gradient's argument clamped (Instant-NGP's density activation: the forward is
    exact, the backward cannot overflow)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-15, 15))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x.clamp(max=30.0))


class NeRFField(nn.Module):
    def __init__(self, cfg: FieldConfig, *, seed: int = 0):
        super().__init__()
        self.cfg = cfg
        g = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)  # the MLPs' default initialisation
        # Made on the CPU (its generators: the same field on every device); `.to(device)` moves it.
        cpu = torch.device("cpu")
        self.encoding = HashEncoding(cfg.grid, generator=g)
        self.density_mlp = nn.Sequential(nn.Linear(cfg.grid.out_dim, cfg.hidden, device=cpu), nn.ReLU(),
                                         nn.Linear(cfg.hidden, 1 + cfg.geo_features, device=cpu))
        self.colour_mlp = nn.Sequential(nn.Linear(cfg.geo_features + 16, cfg.hidden, device=cpu), nn.ReLU(),
                                        nn.Linear(cfg.hidden, cfg.hidden, device=cpu), nn.ReLU(),
                                        nn.Linear(cfg.hidden, 3, device=cpu))

    def density(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points u [N, 3] in the unit cube (contracted) -> sigma [N] (1/m), geometry features [N, G]."""
        h = self.density_mlp(self.encoding(u))
        return trunc_exp(h[:, 0] + self.cfg.density_bias), h[:, 1:]

    def colour(self, geo: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """Geometry features [N, G] and unit directions [N, 3] -> rgb [N, 3] in (0, 1)."""
        return torch.sigmoid(self.colour_mlp(torch.cat([geo, sh_basis(3, dirs)], -1)))


class OccupancyGrid:
    """res^3 cells over the contracted unit cube; a cell is occupied where one sample step in it
    would take more than `alpha` of the light (1 - exp(-sigma * step) > alpha), with sigma a
    running max decayed by `decay` per update (Instant-NGP, sec. 5.4 / its testbed: 0.95, and 1e-2
    opacity over its minimal step). The step is `step_m` (the inner sample spacing, m) stretched
    as the contraction stretches a cell (far-field samples are long), so one threshold serves both.

    mean_clamp: the threshold of the inner cube's cells is min(alpha, their mean opacity), as
    Instant-NGP's testbed (min of its optical-thickness threshold and the grid's mean density) and
    nerfacc's `OccGridEstimator` (clamp(mean occupancy, max=occ_thre)) binarise. The clamp only
    ever lowers the threshold: a field thinner than `alpha` everywhere (a fresh one) keeps its
    denser half instead of losing every cell, which is what lets `alpha` be as high as
    Instant-NGP's. (Its 1e-2 over a step of sqrt(3)/1024 of the grid's cube is a density of
    ~0.024 / m over SynthTown's 244 m cube, 1 - exp(-0.024 * step_m) over our step: ~0.09 at 32
    samples across a 122 m box. With alpha = 0.01 over that step, a density of 0.003 / m, the
    haze of a young field kept every cell occupied after 120-300 steps.) The far field's shell
    keeps the plain threshold (its stretched cells would set the mean)."""

    def __init__(self, res: int, *, step_m: float = 1.0, alpha: float = 0.01,
                 decay: float = 0.95, mean_clamp: bool = False, device: str | torch.device = "cpu"):
        self.res, self.alpha, self.decay, self.mean_clamp = res, alpha, decay, mean_clamp
        self.sigma = torch.zeros(res ** 3, device=device)  # no density seen yet ...
        self.occupied = torch.ones(res ** 3, dtype=torch.bool, device=device)  # ... so nothing skipped
        idx = torch.arange(res, device=device, dtype=torch.float32)
        c = (idx + 0.5) / res * 4 - 2  # contracted centre coordinate per axis
        r = c.abs().clamp(max=2 - 1e-3)
        # d(uncontracted)/d(contracted) along an axis: 1 in the inner cube, 1 / (2 - r)^2 in the
        # shell (the L-inf contraction).
        jac = torch.where(r <= 1, torch.ones_like(r), 1 / (2 - r) ** 2)
        ii, jj, kk = torch.meshgrid(jac, jac, jac, indexing="ij")
        # the largest stretch of the cell's axes: conservative (a far-field step along it)
        self.step_m = step_m * torch.stack([ii, jj, kk], -1).amax(-1).reshape(-1)
        inner = (c.abs() <= 1)
        ii, jj, kk = torch.meshgrid(inner, inner, inner, indexing="ij")
        self.inner = (ii & jj & kk).reshape(-1)  # [res^3] cells of the box (not the far field's shell)

    def index(self, u: torch.Tensor) -> torch.Tensor:
        """Unit-cube points [..., 3] -> flat cell indices [...] (x-major: i * res^2 + j * res + k)."""
        ijk = (u * self.res).long().clamp(0, self.res - 1)
        return (ijk[..., 0] * self.res + ijk[..., 1]) * self.res + ijk[..., 2]

    def query(self, u: torch.Tensor) -> torch.Tensor:
        return self.occupied[self.index(u)]

    def cell_points(self, cells: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """A random point [N, 3] in each of the cells [N] (unit cube)."""
        r = self.res
        ijk = torch.stack([cells // (r * r), (cells // r) % r, cells % r], -1).float()
        # Drawn where the generator lives (the CPU: the same draws on every device), then moved.
        jit = torch.rand(len(cells), 3, generator=generator, device=generator.device).to(cells.device)
        return (ijk + jit) / r

    @torch.no_grad()
    def update(self, density_fn, generator: torch.Generator, *, n_cells: int | None = None, chunk: int = 65536) -> None:
        """Re-evaluate the density at a random point of `n_cells` cells (half uniform, half among
        the occupied; None: every cell) and refresh the occupancy."""
        total = self.res ** 3
        if n_cells is None or n_cells >= total:
            cells = torch.arange(total, device=self.sigma.device)
        else:
            gd = generator.device  # the CPU generator's draws, the same on every device, then moved
            uni = torch.randint(0, total, (n_cells // 2,), generator=generator, device=gd).to(self.sigma.device)
            occ = self.occupied.nonzero()[:, 0]
            pick = torch.randint(0, max(len(occ), 1), (n_cells - n_cells // 2,), generator=generator, device=gd)
            cells = torch.cat([uni, occ[pick.to(occ.device)]]) if len(occ) else uni
        pts = self.cell_points(cells, generator)
        new = torch.cat([density_fn(p) for p in pts.split(chunk)]) if len(pts) else pts[:, 0]
        self.sigma *= self.decay
        self.sigma[cells] = torch.maximum(self.sigma[cells], new.float())
        self.refresh()

    def refresh(self) -> None:
        opacity = -torch.expm1(-self.sigma * self.step_m)
        thr = torch.full_like(opacity, self.alpha)
        if self.mean_clamp and bool(self.inner.any()):
            thr[self.inner] = torch.clamp(opacity[self.inner].mean(), max=self.alpha)
        self.occupied = opacity > thr

    def mark_points(self, u: torch.Tensor, *, dilate: int = 1, sigma_empty: float = 0.0,
                    sigma_full: float = 1e3) -> None:
        """Start from points u [N, 3] (unit cube; an MVS cloud): their cells (grown by `dilate`)
        and every cell of the far-field shell occupied, the rest of the inner cube at `sigma_empty`."""
        r = self.res
        hit = torch.zeros(r ** 3, device=self.sigma.device)
        hit[self.index(u)] = 1
        hit = hit.reshape(1, 1, r, r, r)
        if dilate:
            hit = torch.nn.functional.max_pool3d(hit, 2 * dilate + 1, stride=1, padding=dilate)
        hit = hit.reshape(-1) > 0
        shell = ~self.inner
        self.sigma = torch.where(hit | shell, torch.full_like(self.sigma, sigma_full),
                                 torch.full_like(self.sigma, sigma_empty))
        self.refresh()

    def state_dict(self) -> dict:
        return {"sigma": self.sigma.cpu(), "res": self.res, "alpha": self.alpha, "decay": self.decay,
                "mean_clamp": self.mean_clamp}

    def load(self, sd: dict) -> None:
        self.sigma = sd["sigma"].to(self.sigma.device)
        self.refresh()


def world_density(fld: NeRFField, box, x: torch.Tensor) -> torch.Tensor:
    """sigma [N] (1/m) at world points x [N, 3] (the field seen through the box and contraction)."""
    return fld.density(to_unit(box.normalise(x)))[0]


__all__ = ["FieldConfig", "NeRFField", "OccupancyGrid", "trunc_exp", "world_density"]
