"""Ray marching through the occupancy grid, the training loop, and rendering a camera.

The loop (`train`) is Instant-NGP's, on the CPU in pure torch: random rays of all training views
per step; samples in cells the occupancy grid marks empty are dropped before the field is
evaluated, and colours are evaluated only where a sample's weight exceeds `colour_eps` (its
transmittance cut-off); the grid is refreshed from the density every `occ_every` steps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from reference.common.nerf.encoding import HashGridConfig
from reference.common.nerf.field import FieldConfig, NeRFField, OccupancyGrid
from reference.common.nerf.render import SceneBox, distortion_loss, render_weights, sample_intervals, to_unit


#: Rays stop where the transmittance falls below exp(-T_STOP) = 1e-4 (Instant-NGP's cut-off).
T_STOP = 9.21


@dataclass
class NeRFConfig:
    """The field (hash grid: levels, log2_T, features, n_min, n_max; MLP width `hidden`), ray
    sampling, occupancy grid and schedule.

    Attributes:
        n_inner, n_outer: samples per ray inside the box and in the contracted far field.
        near_m: training rays start this far from their camera (m).
        far_scale: the far field ends at far_scale times the box's largest half side.
        occ_res, occ_every, occ_alpha: occupancy grid cells per axis, update period (steps),
            opacity threshold of an occupied cell.
        occ_warmup: steps during which an update re-evaluates every cell (later: a quarter).
        occ_mean_clamp: the box's cells are occupied above min(occ_alpha, their mean opacity)
            (Instant-NGP's and nerfacc's rule; `field.OccupancyGrid`).
        colour_eps: samples with a smaller weight get no colour evaluation.
        march_block: samples per ray evaluated at once before rays with no light left stop.
        lr, lr_final: Adam rate of the tables and MLPs, decayed exponentially to lr * lr_final.
        distortion: weight of mip-NeRF 360's distortion loss (`render.distortion_loss`, mean over
            the batch's rays; 0: off). It gathers each ray's weight into a short stretch, so the
            thin haze a young field spreads through the whole box gives way to surfaces.
    """

    levels: int = 8
    log2_T: int = 15
    features: int = 2
    n_min: int = 16
    n_max: int = 512
    hidden: int = 64
    iterations: int = 500
    batch_rays: int = 2048
    n_inner: int = 96
    n_outer: int = 32
    near_m: float = 0.5
    far_scale: float = 100.0
    occ_res: int = 64
    occ_every: int = 16
    occ_warmup: int = 128
    occ_alpha: float = 0.01
    occ_mean_clamp: bool = False
    colour_eps: float = 1e-4
    march_block: int = 16
    lr: float = 1e-2
    lr_final: float = 0.1
    distortion: float = 0.0
    chunk: int = 4096

    def field_config(self) -> FieldConfig:
        return FieldConfig(HashGridConfig(self.levels, self.log2_T, self.features, self.n_min, self.n_max),
                           hidden=self.hidden)

    def inner_step(self, box: SceneBox) -> float:
        """The spacing (m) of the inner samples along the box's longest axis."""
        return float(2 * box.half.max() / max(self.n_inner, 1))


@dataclass
class Model:
    """A fitted scene: the field, its occupancy grid, the box, the training background [3] and,
    once baked for the ground renders, the field on a grid over the box (`bake.BakedField`)."""

    field: NeRFField
    grid: OccupancyGrid
    box: SceneBox
    background: torch.Tensor
    baked: object | None = None

    def far(self, cfg: NeRFConfig) -> float:
        """Where the far field's samples end (m)."""
        return float(cfg.far_scale * self.box.half.max())


def render_rays(model: Model, o: torch.Tensor, d: torch.Tensor, cfg: NeRFConfig, *, near: float,
                generator: torch.Generator | None = None, far_field: bool = True) -> dict:
    """rgb [R, 3] over black, opacity acc [R], depth [R] (expected t, m) and sample counts of rays
    from o [R, 3] along unit d [R, 3]; differentiable in the field's parameters. far_field=False:
    the rays end where they leave the box."""
    t = sample_intervals(o, d, model.box, n_inner=cfg.n_inner, n_outer=cfg.n_outer if far_field else 0, near=near,
                         far=model.far(cfg), generator=generator)
    mids, deltas = (t[:, 1:] + t[:, :-1]) / 2, t[:, 1:] - t[:, :-1]  # [R, S]
    u = to_unit(model.box.normalise(o[:, None] + d[:, None] * mids[..., None]))  # [R, S, 3]
    keep = model.grid.query(u) & (deltas > 0)
    # Early ray termination in blocks of samples (Instant-NGP stops a ray at transmittance 1e-4):
    # a block's samples are evaluated only on rays whose light is not yet used up.
    sigmas = torch.zeros(mids.shape, dtype=o.dtype, device=o.device)
    tau = torch.zeros(len(o), dtype=o.dtype, device=o.device)
    rays_k, smps_k, geos = [], [], []
    for s0 in range(0, mids.shape[1], cfg.march_block):
        blk = keep[:, s0:s0 + cfg.march_block] & (tau < T_STOP)[:, None]
        ray, smp = blk.nonzero(as_tuple=True)
        smp = smp + s0
        if len(ray):
            sig, geo = model.field.density(u[ray, smp])
            sigmas = sigmas.index_put((ray, smp), sig)
            rays_k.append(ray)
            smps_k.append(smp)
            geos.append(geo)
            tau = tau + (sigmas[:, s0:s0 + cfg.march_block] * deltas[:, s0:s0 + cfg.march_block]).detach().sum(1)
    if not rays_k:  # nothing to evaluate: every ray is empty
        return {"rgb": torch.zeros(len(o), 3, device=o.device), "acc": torch.zeros(len(o), device=o.device),
                "depth": torch.zeros(len(o), device=o.device), "weights": torch.zeros(mids.shape, device=o.device),
                "samples": 0, "coloured": 0}
    ray, smp, geo_k = torch.cat(rays_k), torch.cat(smps_k), torch.cat(geos)
    weights, _ = render_weights(sigmas, deltas)
    w_k = weights[ray, smp]
    live = w_k.detach() > cfg.colour_eps
    cols = model.field.colour(geo_k[live], d[ray[live]])
    rgb = torch.zeros(len(o), 3, dtype=cols.dtype, device=o.device).index_add(0, ray[live], w_k[live, None] * cols)
    return {"rgb": rgb, "acc": weights.sum(1), "depth": (weights * mids).sum(1), "weights": weights,
            "samples": int(len(ray)), "coloured": int(live.sum())}


@torch.no_grad()
def render_camera(model: Model, cam, cfg: NeRFConfig, *, near: float, far_field: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(rgb [H, W, 3] over black, opacity [H, W]) of a `skyeyes_bench.cameras.Camera`."""
    dev = model.background.device
    o, d = cam.rays()
    o = torch.tensor(o, dtype=torch.float32, device=dev)
    d = torch.tensor(d, dtype=torch.float32, device=dev)
    rgbs, accs = [], []
    for oc, dc in zip(o.split(cfg.chunk), d.split(cfg.chunk)):
        out = render_rays(model, oc, dc, cfg, near=near, far_field=far_field)
        rgbs.append(out["rgb"])
        accs.append(out["acc"])
    rgb = torch.cat(rgbs).reshape(cam.height, cam.width, 3).clamp(0, 1)
    return rgb.cpu().numpy(), torch.cat(accs).reshape(cam.height, cam.width).clamp(0, 1).cpu().numpy()


def camera_rays(cams: list, images: list[np.ndarray], device) -> tuple[torch.Tensor, ...]:
    """Origins, unit directions and colours [N, 3] of every pixel of the views."""
    os_, ds, cs = [], [], []
    for cam, img in zip(cams, images):
        o, d = cam.rays()
        os_.append(o)
        ds.append(d)
        cs.append(img.reshape(-1, 3))
    return tuple(torch.tensor(np.concatenate(a), dtype=torch.float32, device=device) for a in (os_, ds, cs))


def pretrain_density(model: Model, points: torch.Tensor, cfg: NeRFConfig, *, steps: int, batch: int = 4096,
                     seed: int = 0, step_m: float = 0.5) -> float:
    """Start the density from a fused cloud, points [P, 3] (world): cells the grid marks occupied
    (`OccupancyGrid.mark_points`) are pulled towards an opaque layer at the points (opacity over
    `step_m` -> 1), the grid's empty inner cells towards empty (-> 0); binary cross-entropy on
    opacity, written with optical depths so it stays finite. Returns the last loss."""
    gen = torch.Generator().manual_seed(seed + 1)
    dev = points.device
    opt = torch.optim.Adam(model.field.parameters(), lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    empty = (~model.grid.occupied).nonzero()[:, 0]
    loss = torch.zeros((), device=dev)
    gd = gen.device  # draws on the CPU generator (the same on every device), then moved
    for _ in range(steps):
        pos = points[torch.randint(0, len(points), (batch,), generator=gen, device=gd).to(dev)]
        pos = pos + (torch.rand(batch, 3, generator=gen, device=gd).to(dev) - 0.5) * step_m
        sig_pos = model.field.density(to_unit(model.box.normalise(pos)))[0]
        loss = -torch.log(-torch.expm1(-(sig_pos * step_m).clamp_min(1e-6))).mean()
        if len(empty):
            cells = empty[torch.randint(0, len(empty), (batch,), generator=gen, device=gd).to(dev)]
            sig_neg = model.field.density(model.grid.cell_points(cells, gen))[0]
            loss = loss + (sig_neg * step_m).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return float(loss.detach())


def train(model: Model, rays: tuple[torch.Tensor, torch.Tensor, torch.Tensor], cfg: NeRFConfig, *, seed: int = 0,
          full_warmup: bool = True, progress: bool = True,
          callback: Callable[[int, float, Model], None] | None = None, callback_every: int = 100) -> dict:
    """Optimise `model` in place on rays (origins, unit directions, colours; [N, 3] each).
    full_warmup: the first `occ_warmup` steps re-evaluate every grid cell (off after an MVS start,
    which would otherwise be overwritten by the fresh field). Returns the fit's statistics."""
    from tqdm import tqdm

    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    o_all, d_all, c_all = rays
    fld, grid = model.field, model.grid
    table = [fld.encoding.table]
    mlps = [p for n, p in fld.named_parameters() if not n.startswith("encoding.")]
    # NOTE: Instant-NGP's optimiser: Adam, beta2 0.99, eps 1e-15, a small L2 on the MLPs only.
    opt = torch.optim.Adam([{"params": table, "weight_decay": 0.0}, {"params": mlps, "weight_decay": 1e-6}],
                           lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    density_fn = lambda p: fld.density(p)[0]  # noqa: E731
    losses, samples, t_train, cpu_train = [], [], 0.0, 0.0
    bar = tqdm(range(1, cfg.iterations + 1), desc="fit", disable=None if progress else True, leave=False)
    for it in bar:
        t0, c0 = time.perf_counter(), time.process_time()
        # 1. The learning rate's exponential decay.
        for g in opt.param_groups:
            g["lr"] = cfg.lr * cfg.lr_final ** ((it - 1) / max(cfg.iterations - 1, 1))
        # 2. Occupancy: every cell while warming up, later a quarter (half of them occupied ones).
        if it == 1 and full_warmup or it % cfg.occ_every == 0:
            warm = full_warmup and it <= cfg.occ_warmup
            grid.update(density_fn, gen, n_cells=None if warm else grid.res ** 3 // 4)
        # 3. A batch of random rays of all views, rendered over the training background.
        idx = torch.randint(0, len(o_all), (cfg.batch_rays,), generator=gen, device=gen.device).to(o_all.device)
        out = render_rays(model, o_all[idx], d_all[idx], cfg, near=cfg.near_m, generator=gen)
        rgb = out["rgb"] + (1 - out["acc"])[:, None] * model.background
        loss = torch.nn.functional.mse_loss(rgb, c_all[idx])
        if cfg.distortion > 0:
            loss = loss + cfg.distortion * distortion_loss(out["weights"]).mean()
        # 4. Step.
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        t_train += time.perf_counter() - t0
        cpu_train += time.process_time() - c0
        losses.append(float(loss.detach()))
        samples.append(out["samples"])
        if it % 25 == 0:
            bar.set_postfix(loss=f"{np.mean(losses[-25:]):.4f}", occ=f"{float(grid.occupied.float().mean()):.2f}")
        if callback is not None and (it % callback_every == 0 or it == cfg.iterations):
            callback(it, t_train, model)
    # train_cpu_seconds: this process's CPU time (one thread: the seconds it would take on a free core)
    return {"iterations": cfg.iterations, "train_seconds": t_train, "train_cpu_seconds": cpu_train,
            "final_loss": float(np.mean(losses[-25:])),
            "loss_every_25": [float(np.mean(losses[i:i + 25])) for i in range(0, len(losses), 25)],
            "samples_per_ray": float(np.mean(samples)) / cfg.batch_rays,
            "occupied_fraction": float(grid.occupied.float().mean()),
            "train_rays_per_s": cfg.iterations * cfg.batch_rays / max(t_train, 1e-9)}
