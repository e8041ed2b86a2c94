# SPDX-License-Identifier: Apache-2.0
"""Synthetic world (procedural objects, scenes, stereo rendering) and the physics evaluation.

Importing ``pugsd.sim`` does not import MuJoCo or open3d; the physics trial
(:mod:`pugsd.sim.physics`) and the evaluation (:mod:`pugsd.sim.evaluate`) load them when used.
"""

from __future__ import annotations

import importlib
from typing import Any

from pugsd.sim.objects import (
    BUILTIN_OBJECTS,
    ObjectSpec,
    get_object,
    load_object_mesh,
)
from pugsd.sim.render import Underwater, default_rig
from pugsd.sim.sequence import (
    POSES,
    TRAJECTORIES,
    SyntheticSequence,
    camera_path,
    make_sequence,
    object_pose,
    se3_exp,
)

_LAZY = {
    "GraspTrial": "pugsd.sim.physics",
    "TrialConfig": "pugsd.sim.physics",
    "TrialResult": "pugsd.sim.physics",
    "grasp_pose": "pugsd.sim.physics",
    "run_trial": "pugsd.sim.physics",
    "EvalOptions": "pugsd.sim.evaluate",
    "run_evaluation": "pugsd.sim.evaluate",
}


def __getattr__(name: str) -> Any:
    """Physics and evaluation names load MuJoCo (and the pipeline) only when first used."""
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pugsd.sim' has no attribute {name!r}")


__all__ = [
    "BUILTIN_OBJECTS",
    "POSES",
    "TRAJECTORIES",
    "EvalOptions",
    "GraspTrial",
    "ObjectSpec",
    "SyntheticSequence",
    "TrialConfig",
    "TrialResult",
    "Underwater",
    "camera_path",
    "default_rig",
    "get_object",
    "grasp_pose",
    "load_object_mesh",
    "make_sequence",
    "object_pose",
    "run_evaluation",
    "run_trial",
    "se3_exp",
]
