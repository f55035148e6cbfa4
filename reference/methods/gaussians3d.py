"""`gaussians3d`: vanilla 3D Gaussian splatting (Kerbl et al. 2023) fitted on a lane's aerial
views, rendered from its ground cameras.

The Gaussian-splatting pipeline (`reference.common.splatting`) without a regularizer: the MVS
start (`reference.common.mvs_start`), 3DGS training on the aerial views, ground renders through
the appearance learned on the train split (`reference.common.appearance`). Its presets are the
pipeline's 3DGS schedule per size (`splatting.PRESETS`), which `sugar` extends.
"""

from __future__ import annotations

from reference.common.splatting import PRESETS as SPLATTING_PRESETS
from reference.common.splatting import GaussianSplatting

PRESETS = SPLATTING_PRESETS


class Gaussians3D(GaussianSplatting):
    name = "gaussians3d"
    kind = "baseline"

    def components(self) -> list[str]:
        return ["3D Gaussian splatting fitted on the lane's aerial views", "rendered at the ground cameras", "colours mapped as learned on the train split"]
    presets = PRESETS
