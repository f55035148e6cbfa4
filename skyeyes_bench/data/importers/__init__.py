"""Importers: CARLA capture folders and MatrixCity / CitySample captures -> canonical layout.

One module per source (`carla`, `matrixcity`) over what they share (`common`: the plan, the
input checks, `write_plan`). The command line is `skyeyes_bench.commands.data`.
"""

from __future__ import annotations

from .carla import CARLA_CAPTURE_FILE, CARLA_DEPTH_FAR_M, CARLA_FORMAT, decode_carla_depth, import_carla, plan_carla
from .common import PlannedFrame, PlannedScene, resample_step, split_lanes, write_plan, yaw_sequence_name
from .matrixcity import MATRIXCITY_DEPTH_INVALID, import_matrixcity, matrixcity_depth_to_metres, plan_matrixcity

__all__ = [
    "CARLA_CAPTURE_FILE", "CARLA_DEPTH_FAR_M", "CARLA_FORMAT", "MATRIXCITY_DEPTH_INVALID", "PlannedFrame",
    "PlannedScene", "decode_carla_depth", "import_carla", "import_matrixcity", "matrixcity_depth_to_metres",
    "plan_carla", "plan_matrixcity", "resample_step", "split_lanes", "write_plan", "yaw_sequence_name",
]
