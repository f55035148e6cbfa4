"""`sugar`: SuGaR's surface-aligned Gaussians (Guedon & Lepetit, CVPR 2024), the Skyeyes
paper's stage one, as a row of its own: the part `reference.common.sugar.SuGaRSplatting` (the
Gaussian-splatting pipeline with SuGaR's regularizer and schedule), which Skyeyes conditions on.
"""

from __future__ import annotations

from reference.common.sugar import PRESETS, SuGaRConfig, SuGaRSplatting

__all__ = ["PRESETS", "SuGaR", "SuGaRConfig"]


class SuGaR(SuGaRSplatting):
    name = "sugar"
    kind = "baseline"
    presets = PRESETS

    def components(self) -> list[str]:
        return ["SuGaR: surface-aligned 3D Gaussians fitted on the lane's aerial views", "rendered at the ground cameras",
                "colours mapped as learned on the train split"]
