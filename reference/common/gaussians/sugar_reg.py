"""SuGaR's regularisation (Guedon & Lepetit, CVPR 2024) for `reference.common.sugar`.

Two phases after plain 3DGS warm-up:

1. Opacity entropy  -o log o - (1-o) log(1-o): pushes Gaussians to be opaque or gone.
2. Density / SDF alignment (the Skyeyes paper's Eq. sdf-loss): points p are sampled from the
   Gaussians; g* is the neighbour contributing most density at p, n* its normal (the axis of
   its smallest scale: flat Gaussians), s* that smallest scale. With the density
   d(p) = sum_g o_g exp(-q_g(p)/2) over the k nearest Gaussians, the SDF the density implies
   is s* sqrt(-2 log d(p)) and the ideal one is |<p - mu*, n*>|; the loss is their difference
   divided by s*. A normal term 1 - |<grad d / |grad d|, n*>| aligns the density's gradient
   with n*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .model import GaussianModel
from .project import quat_to_rotmat


@dataclass
class SugarWeights:
    """NOTE: weights as in SuGaR's defaults as we read the paper and its training script:
    entropy 0.1, SDF 0.2, normal 0.2, 16 neighbours; the iteration schedule is scaled per preset."""

    entropy_from: int
    sdf_from: int
    entropy_until: int | None = None  # None: to the end
    lambda_entropy: float = 0.1
    lambda_sdf: float = 0.2
    lambda_normal: float = 0.2
    samples: int = 2000
    knn: int = 16
    knn_every: int = 100


class SugarRegularizer:
    def __init__(self, w: SugarWeights, seed: int = 0):
        self.w = w
        self.gen = torch.Generator().manual_seed(seed)
        self._knn: torch.Tensor | None = None
        self._knn_it = -10**9
        self.last: dict[str, float] = {}

    def _neighbours(self, model: GaussianModel, it: int) -> torch.Tensor:
        n = len(model)
        if self._knn is None or self._knn.shape[0] != n or it - self._knn_it >= self.w.knn_every:
            from scipy.spatial import cKDTree

            xyz = model.means.detach().cpu().numpy()
            k = min(self.w.knn, n)
            _, idx = cKDTree(xyz).query(xyz, k=k)
            self._knn = torch.as_tensor(np.asarray(idx).reshape(n, k), device=model.means.device)
            self._knn_it = it
        return self._knn

    def __call__(self, model: GaussianModel, it: int) -> torch.Tensor:
        w = self.w
        loss = model.means.new_zeros(())
        if it >= w.entropy_from and (w.entropy_until is None or it < w.entropy_until):
            o = model.opacities.clamp(1e-6, 1 - 1e-6)
            ent = (-o * torch.log(o) - (1 - o) * torch.log(1 - o)).mean()
            loss = loss + w.lambda_entropy * ent
            self.last["entropy"] = ent.item()
        if it >= w.sdf_from and len(model) > 1:
            sdf, normal = sdf_terms(model, self._neighbours(model, it), w.samples, self.gen)
            loss = loss + w.lambda_sdf * sdf + w.lambda_normal * normal
            self.last.update(sdf=sdf.item(), normal=normal.item())
        return loss


def sdf_terms(model: GaussianModel, knn: torch.Tensor, samples: int, gen: torch.Generator):
    """(SDF alignment loss, normal loss), both scalars, from `samples` points drawn from the
    Gaussians (chosen uniformly). knn: [N, k] neighbour indices (self included)."""
    n = len(model)
    # Drawn where the generator lives (the CPU: the same draws on every device), then moved.
    src = torch.randint(0, n, (samples,), generator=gen, device=gen.device).to(model.means.device)
    means, scales, opac = model.means, model.scales, model.opacities
    R = quat_to_rotmat(model.quats)  # [N, 3, 3]
    with torch.no_grad():  # sample p ~ N(mu, Sigma) of the source Gaussian
        eps = torch.randn(samples, 3, generator=gen, device=gen.device).to(means.device)
        p = means[src] + (R[src] @ (eps * scales[src])[..., None])[..., 0]  # [S, 3]
    nb = knn[src]  # [S, k]
    d = p[:, None, :] - means[nb]  # [S, k, 3]
    Rn = R[nb]  # [S, k, 3, 3]
    sn = scales[nb].clamp_min(1e-8)  # [S, k, 3]
    y = (Rn.transpose(-1, -2) @ d[..., None])[..., 0] / sn  # local coordinates in std units
    g = opac[nb] * torch.exp(-0.5 * (y * y).sum(-1))  # [S, k] density contributions
    dens = g.sum(-1).clamp(1e-6, 1 - 1e-6)
    star = g.detach().argmax(-1)  # g*: the most contributing neighbour
    ar = torch.arange(samples, device=means.device)
    smin, axis = sn[ar, star].min(-1)  # smallest scale and its axis
    n_star = Rn[ar, star, :, axis]  # [S, 3] normal of g*
    ideal = (d[ar, star] * n_star).sum(-1).abs()  # |<p - mu*, n*>|
    implied = smin * torch.sqrt(-2 * torch.log(dens))
    sdf = ((implied - ideal).abs() / smin).mean()
    # grad d(p) = -sum_g o_g e^{-q/2} Sigma_g^-1 (p - mu_g), Sigma^-1 (p - mu) = R (y / s).
    grad = -(g[..., None] * (Rn @ (y / sn)[..., None])[..., 0]).sum(1)  # [S, 3]
    nrm = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    normal = (1 - (nrm * n_star).sum(-1).abs()).mean()
    return sdf, normal
