"""The trainable Gaussian set: raw parameters (log scales, logit opacities) and the Adam
bookkeeping densification needs (cloning, splitting, pruning keep the moment estimates)."""

from __future__ import annotations

import math

import numpy as np
import torch

from .project import SH_C0, quat_to_rotmat

PARAMS = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


class GaussianModel:
    """Parameters as leaf tensors in `self.params`; activations as properties."""

    def __init__(self, params: dict[str, torch.Tensor]):
        self.params = {k: params[k].detach().clone().requires_grad_(True) for k in PARAMS}

    @classmethod
    def from_points(cls, xyz: np.ndarray, rgb: np.ndarray, sh_degree: int, *, opacity: float = 0.1,
                    seed: int = 0, max_scale: float = np.inf) -> "GaussianModel":
        """3DGS init: isotropic scales from the mean distance to the 3 nearest neighbours
        (capped at `max_scale` m: sparse clouds otherwise start with giants that cover every tile)."""
        from scipy.spatial import cKDTree

        xyz = np.asarray(xyz, dtype=np.float64)
        n = len(xyz)
        k = min(4, n)
        d, _ = cKDTree(xyz).query(xyz, k=k)
        dist = np.sqrt(np.mean(np.square(d[:, 1:]), axis=1)) if k > 1 else np.ones(n)
        dist = np.clip(dist, 1e-3, max_scale)
        # On the CPU, deliberately: numpy inputs and a CPU generator (the same start on every
        # device); `to(device)` moves the model.
        cpu = torch.device("cpu")
        g = torch.Generator().manual_seed(seed)
        quats = torch.zeros(n, 4, device=cpu)
        quats[:, 0] = 1.0
        quats = quats + 0.01 * torch.randn(n, 4, generator=g, device=cpu)  # break symmetry for SuGaR normals
        nb = (sh_degree + 1) ** 2
        return cls({
            "means": torch.tensor(xyz, dtype=torch.float32, device=cpu),
            "log_scales": torch.log(torch.tensor(dist, dtype=torch.float32, device=cpu))[:, None].repeat(1, 3),
            "quats": quats,
            "logit_opacities": torch.full((n,), math.log(opacity / (1 - opacity)), device=cpu),
            "sh0": rgb_to_sh0(torch.tensor(rgb, dtype=torch.float32, device=cpu))[:, None, :],
            "shN": torch.zeros(n, nb - 1, 3, device=cpu),
        })

    @classmethod
    def from_surfels(cls, surfels: dict[str, torch.Tensor], sh_degree: int, *, opacity: float = 0.1) -> "GaussianModel":
        """Init from oriented discs (`reference.common.geometry.splat.surfels`: means, quats,
        scales, colors), as 3DGS starts from an MVS cloud but with each point's own size and
        orientation instead of its neighbours' distance."""
        n, dev = surfels["means"].shape[0], surfels["means"].device
        nb = (sh_degree + 1) ** 2
        return cls({
            "means": surfels["means"].float(),
            "log_scales": torch.log(surfels["scales"].float().clamp_min(1e-4)),
            "quats": surfels["quats"].float(),
            "logit_opacities": torch.full((n,), math.log(opacity / (1 - opacity)), device=dev),
            "sh0": rgb_to_sh0(surfels["colors"].float())[:, None, :],
            "shN": torch.zeros(n, nb - 1, 3, device=dev),
        })

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    # the activated parameters the rasterizer takes
    means = property(lambda self: self.params["means"])
    scales = property(lambda self: torch.exp(self.params["log_scales"]))
    quats = property(lambda self: self.params["quats"])
    opacities = property(lambda self: torch.sigmoid(self.params["logit_opacities"]))
    sh = property(lambda self: torch.cat([self.params["sh0"], self.params["shN"]], 1))

    def to(self, device: str | torch.device) -> "GaussianModel":
        """The same model with its parameters on `device` (new leaf tensors; make the optimiser after)."""
        return GaussianModel({k: v.detach().to(device) for k, v in self.params.items()})

    def state_dict(self) -> dict:
        return {k: v.detach().clone() for k, v in self.params.items()}

    @classmethod
    def from_state_dict(cls, sd: dict) -> "GaussianModel":
        return cls(sd)

    # ------------------------------------------------------------ structure changes
    def make_optimizer(self, lrs: dict[str, float]) -> torch.optim.Adam:
        groups = [{"params": [self.params[k]], "lr": lrs[k], "name": k} for k in PARAMS]
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    def _replace(self, opt: torch.optim.Adam, fn) -> None:
        """Apply fn(tensor [N, ...]) -> tensor [N', ...] to every parameter and its Adam moments."""
        for group in opt.param_groups:
            old = group["params"][0]
            new = fn(old.detach()).requires_grad_(True)
            state = opt.state.pop(old, None)
            if state:
                state["exp_avg"] = fn(state["exp_avg"])
                state["exp_avg_sq"] = fn(state["exp_avg_sq"])
                opt.state[new] = state
            group["params"][0] = new
            self.params[group["name"]] = new

    def keep(self, opt, mask: torch.Tensor) -> None:
        self._replace(opt, lambda t: t[mask])

    def append(self, opt, new: dict[str, torch.Tensor]) -> None:
        """Append Gaussians (values in raw parameter space); their Adam moments start at 0."""
        for group in opt.param_groups:
            name = group["name"]
            extra = new[name].to(group["params"][0].dtype)
            old = group["params"][0]
            state = opt.state.pop(old, None)
            t = torch.cat([old.detach(), extra]).requires_grad_(True)
            if state:
                z = torch.zeros_like(extra)
                state["exp_avg"] = torch.cat([state["exp_avg"], z])
                state["exp_avg_sq"] = torch.cat([state["exp_avg_sq"], z])
                opt.state[t] = state
            group["params"][0] = t
            self.params[name] = t

    def split_values(self, idx: torch.Tensor, n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """3DGS split: n children sampled from the parent Gaussian, scales / (0.8 n)."""
        p = {k: v.detach()[idx] for k, v in self.params.items()}
        scales = torch.exp(p["log_scales"]).repeat(n, 1)
        R = quat_to_rotmat(p["quats"]).repeat(n, 1, 1)
        # Drawn on the CPU generator's device (the same draws on every device), then moved.
        offs = torch.randn(scales.shape, generator=generator, device=generator.device).to(scales.device) * scales
        out = {k: v.repeat(n, *([1] * (v.ndim - 1))) for k, v in p.items()}
        out["means"] = out["means"] + (R @ offs[..., None])[..., 0]
        # NOTE: 0.8 * N shrink factor from 3DGS densify_and_split.
        out["log_scales"] = torch.log(scales / (0.8 * n))
        return out
