"""Capturing the paper's data: `carla_plan` (the protocol's lanes and every camera transform of a
CARLA town, a pure function of the map's waypoints) and `carla_live` (drives a CARLA server in
synchronous mode to render the plan). The command line is `skyeyes-bench data capture-carla`
(`skyeyes_bench.commands.data`); the result is a capture folder that `data import-carla` reads.
"""

from __future__ import annotations

from .carla_plan import (WAYPOINTS_FILE, WAYPOINTS_FORMAT, Lane, PlanConfig, Waypoint, plan_capture, read_waypoints,
                         select_lanes, waypoints_document)

__all__ = ["WAYPOINTS_FILE", "WAYPOINTS_FORMAT", "Lane", "PlanConfig", "Waypoint", "plan_capture", "read_waypoints",
           "select_lanes", "waypoints_document"]
