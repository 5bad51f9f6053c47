"""Fast gating of reports against tracks (paper 2): the grid-hash gate, clusters, bearing-only
gating, constant-velocity projections and the cost model that picks M_D.

Calibration lives in :mod:`tracker.gating.calibrate` (imported on demand: it is a benchmark).
"""

from tracker.gating.bearing import gate_bearings, track_bearings
from tracker.gating.clusters import Clusters, cluster_tracks, gate_clusters, pseudotracks
from tracker.gating.costmodel import DEFAULT_CONSTANTS, Choice, CostConstants
from tracker.gating.gate import (
    Gater,
    gate,
    gate_checked,
    gate_threshold,
    gate_unchecked,
    plan_choice,
)
from tracker.gating.reach import ReachBound, project, project_states
from tracker.gating.scene import Scene

__all__ = [
    "DEFAULT_CONSTANTS",
    "Choice",
    "Clusters",
    "CostConstants",
    "Gater",
    "ReachBound",
    "Scene",
    "cluster_tracks",
    "gate",
    "gate_bearings",
    "gate_checked",
    "gate_unchecked",
    "gate_clusters",
    "gate_threshold",
    "plan_choice",
    "project",
    "project_states",
    "pseudotracks",
    "track_bearings",
]
