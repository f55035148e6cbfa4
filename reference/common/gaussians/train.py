"""Fit Gaussians to posed images: L1 + 0.2 D-SSIM, Adam with 3DGS's per-parameter rates,
densification (clone / split by view-space positional gradient), pruning, opacity reset.

The loop is `train`; the SuGaR regulariser plugs in as `regularizer(model, it) -> loss`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from .model import GaussianModel
from .render import rasterize
from .ssim import ssim

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """3DGS training schedule (iteration counts scaled down for CPU presets).

    NOTE: learning rates, thresholds and the L1/D-SSIM weight follow 3DGS
    (Kerbl et al. 2023, arguments/__init__.py): position 1.6e-4 -> 1.6e-6 (x scene extent),
    SH DC 2.5e-3 (rest /20), opacity 0.05, scaling 5e-3, rotation 1e-3; densify grad 2e-4,
    percent_dense 0.01, prune opacity 0.005, lambda_dssim 0.2.
    """

    iterations: int = 1000
    sh_degree: int = 1
    sh_increase_every: int = 500
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lambda_dssim: float = 0.2
    densify_from: int = 100
    densify_until: int = 700
    densify_every: int = 100
    densify_grad: float = 2e-4
    percent_dense: float = 0.01
    opacity_reset_every: int = 3000
    prune_opacity: float = 0.005
    max_screen_px: float = 0.0  # prune Gaussians larger than this on screen (0: off)
    max_gaussians: int = 50_000
    init_opacity: float = 0.1


@dataclass
class View:
    """One training image. image [H, W, 3] float32, viewmat [4, 4] w2c, K [3, 3], mask [H, W]."""

    image: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    mask: torch.Tensor | None = None
    name: str = ""

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @property
    def height(self) -> int:
        return self.image.shape[0]


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10 * math.log10(1.0 / mse) if mse > 0 else math.inf


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None, lambda_dssim: float):
    """(1 - l) L1 + l (1 - SSIM); pixels outside `mask` [H, W] take the ground truth (no loss)."""
    if mask is not None:
        pred = torch.where(mask[..., None], pred, gt)
    l1 = (pred - gt).abs().mean()
    return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(pred, gt))


def render_view(model: GaussianModel, view: View, sh_degree: int, background: torch.Tensor) -> dict:
    return rasterize(model.means, model.quats, model.scales, model.opacities, model.sh, view.viewmat, view.K,
                     view.width, view.height, background=background, sh_degree=sh_degree)


def train(model: GaussianModel, views: list[View], cfg: TrainConfig, *, extent: float,
          box: torch.Tensor | None = None, background: torch.Tensor | None = None, seed: int = 0,
          regularizer: Callable[[GaussianModel, int], torch.Tensor] | None = None,
          callback: Callable[[int, float, GaussianModel], None] | None = None,
          progress: bool = True) -> dict:
    """Optimise `model` in place on `views`. Returns stats (loss history, counts, seconds).

    Args:
        extent: scene radius (m); scales the position learning rate and the clone/split size.
        box: [2, 3] region (min, max); Gaussians that leave it are pruned.
        regularizer: extra loss term (SuGaR), called every iteration after the photometric loss.
        callback: called as callback(iteration, train_seconds, model) every `densify_every` its.
    """
    from tqdm import tqdm

    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    dev = model.means.device  # everything runs where the model's parameters live
    bg = background.to(dev) if background is not None else torch.zeros(3, device=dev)
    if box is not None:
        box = box.to(dev)
    lrs = {"means": cfg.lr_means * extent, "log_scales": cfg.lr_scales, "quats": cfg.lr_quats,
           "logit_opacities": cfg.lr_opacity, "sh0": cfg.lr_sh0, "shN": cfg.lr_shN}
    opt = model.make_optimizer(lrs)
    grad_acc = torch.zeros(len(model), device=dev)
    grad_cnt = torch.zeros(len(model), device=dev)
    order: list[int] = []
    losses = []
    t_train = 0.0
    bar = tqdm(range(1, cfg.iterations + 1), desc="fit", disable=None if progress else True, file=None, leave=False)
    for it in bar:
        t0 = time.perf_counter()
        # 1. Schedules: exponential position rate decay, SH degree warm-up.
        frac = (it - 1) / max(cfg.iterations - 1, 1)
        opt.param_groups[0]["lr"] = extent * math.exp((1 - frac) * math.log(cfg.lr_means) + frac * math.log(cfg.lr_means_final))
        degree = min(cfg.sh_degree, (it - 1) // max(cfg.sh_increase_every, 1))
        # 2. Render one view (shuffled epochs) and take the photometric loss.
        if not order:
            order = list(rng.permutation(len(views)))
        view = views[order.pop()]
        out = render_view(model, view, degree, bg)
        loss = photometric_loss(out["rgb"], view.image, view.mask, cfg.lambda_dssim)
        if regularizer is not None:
            loss = loss + regularizer(model, it)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        # 3. Densification statistics: view-space positional gradient in NDC units (as 3DGS).
        vis = out["visible"]
        if out["means2d"].grad is not None and it < cfg.densify_until:
            ndc = torch.tensor([view.width / 2, view.height / 2], device=dev)
            g = out["means2d"].grad.detach().reshape(-1, 2) * ndc  # reshape: gsplat's means2d is [1, N, 2]
            grad_acc[vis] += g[vis].norm(dim=-1)
            grad_cnt[vis] += 1
        opt.step()
        # 4. Densify and prune, reset opacities.
        with torch.no_grad():
            if cfg.densify_from <= it < cfg.densify_until and it % cfg.densify_every == 0:
                _densify(model, opt, grad_acc / grad_cnt.clamp_min(1), cfg, extent, box, gen)
                grad_acc = torch.zeros(len(model), device=dev)
                grad_cnt = torch.zeros(len(model), device=dev)
            if cfg.opacity_reset_every and it % cfg.opacity_reset_every == 0 and it < cfg.densify_until:
                lo = torch.logit(torch.tensor(0.01, device=dev))
                model.params["logit_opacities"].clamp_(max=lo)
                for group in opt.param_groups:
                    if group["name"] == "logit_opacities":
                        st = opt.state.get(group["params"][0])
                        if st:
                            st["exp_avg"].zero_()
                            st["exp_avg_sq"].zero_()
        t_train += time.perf_counter() - t0
        losses.append(loss.item())
        if it % 20 == 0:
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}", n=len(model))
        if callback is not None and (it % cfg.densify_every == 0 or it == cfg.iterations):
            callback(it, t_train, model)
    return {"iterations": cfg.iterations, "final_loss": float(np.mean(losses[-20:])) if losses else None,
            "gaussians": len(model), "train_seconds": t_train, "losses": losses[:: max(1, len(losses) // 100)]}


def _densify(model: GaussianModel, opt, grads: torch.Tensor, cfg: TrainConfig, extent: float,
             box: torch.Tensor | None, gen: torch.Generator) -> None:
    """3DGS densify_and_prune: clone small, split large high-gradient Gaussians; prune."""
    n0 = len(model)
    max_scale = model.scales.max(-1).values
    hot = grads >= cfg.densify_grad
    room = cfg.max_gaussians - n0
    if room > 0 and hot.any():
        # Strongest gradients first when the budget is short.
        idx = torch.nonzero(hot).squeeze(1)
        idx = idx[torch.argsort(grads[idx], descending=True)][: max(room // 2, 0)]
        small = max_scale[idx] <= cfg.percent_dense * extent
        clone, split = idx[small], idx[~small]
        new_split = model.split_values(split, 2, gen)
        new_clone = {k: v.detach()[clone] for k, v in model.params.items()}
        new = {k: torch.cat([new_clone[k], new_split[k]]) for k in new_clone}
        model.append(opt, new)
        drop = torch.zeros(len(model), dtype=torch.bool, device=model.means.device)
        drop[split] = True  # split parents are replaced by their children
    else:
        drop = torch.zeros(len(model), dtype=torch.bool, device=model.means.device)
    drop |= model.opacities < cfg.prune_opacity
    if box is not None:
        m = model.means
        drop |= ~((m >= box[0]) & (m <= box[1])).all(-1)
    drop |= model.scales.max(-1).values > 0.5 * extent  # world-space giants (3DGS: 0.1 x extent)
    drop |= ~torch.isfinite(model.means).all(-1)
    if drop.all():
        drop[:1] = False  # never prune to nothing
    model.keep(opt, ~drop)
    log.debug("densify: %d -> %d Gaussians", n0, len(model))


def config_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)
