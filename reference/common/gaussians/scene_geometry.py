"""The scene geometry a Gaussian prior offers (`reference.method.SceneGeometry`): its fitted
Gaussians' expected depth from a camera and their means, read by what conditions on the prior
(`reference.common.diffusion.additions`) through this interface, never through the prior's
internals."""

from __future__ import annotations

import numpy as np
import torch

from .render import rasterize


class GaussianGeometry:
    """`SceneGeometry` of a `Method` whose fitted scene (`scene_model(scene)[0]`) is a
    `GaussianModel` and whose config gives `sh_degree` and `render_near_m` (`GaussianSplatting`,
    and test stand-ins)."""

    def _gaussians(self, scene):
        return self.scene_model(scene)[0]

    @torch.no_grad()
    def depth(self, scene, cam) -> np.ndarray:
        """The expected planar depth (m) of the fitted scene seen by `cam`: float64 [H, W], +inf
        where the Gaussians cover less than half the pixel (the sky and the background: a
        direction, as the warp metric reads it)."""
        model = self._gaussians(scene)
        dev = model.means.device
        out = rasterize(model.means, model.quats, model.scales, model.opacities, model.sh,
                        torch.tensor(cam.w2c, dtype=torch.float32, device=dev),
                        torch.tensor(cam.K, dtype=torch.float32, device=dev), cam.width, cam.height,
                        sh_degree=self.config.sh_degree, near=self.config.render_near_m)
        depth = out["depth"].double().cpu().numpy()
        return np.where((out["alpha"].cpu().numpy() > 0.5) & (depth > 0), depth, np.inf)

    def points(self, scene) -> np.ndarray:
        """[M, 3] the fitted Gaussians' means (world, m)."""
        return self._gaussians(scene).means.detach().cpu().numpy()
