"""`mvs`: the paper's MVS row (Schoenberger et al. 2016): the fused cloud of a lane's aerial
views drawn into each ground camera as surface discs, colours mapped as learned on the train
split; nothing is invented where no disc falls. The part is `reference.common.mvs_cloud.MVSCloud`
(gvg's geometry and the reconstruction methods' learned appearance use the same part); its
config and presets are `reference.common.mvs_start`'s.
"""

from __future__ import annotations

from reference.common.mvs_cloud import MVSCloud, geometry_render
from reference.common.mvs_start import PRESETS, MVSMethodConfig

__all__ = ["MVS", "MVSMethodConfig", "PRESETS", "geometry_render"]


class MVS(MVSCloud):
    name = "mvs"
    kind = "baseline"
    presets = PRESETS

    def components(self) -> list[str]:
        return ["SfM and plane-sweep multi-view stereo on the lane's aerial views",
                "the fused cloud's discs rendered at the ground cameras", "colours mapped as learned on the train split"]
