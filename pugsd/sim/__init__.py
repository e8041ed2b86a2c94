# SPDX-License-Identifier: Apache-2.0
"""Synthetic world (procedural objects, scenes, stereo rendering) and the physics evaluation:
the simulation extras (``pip install 'pugsd[sim]'``: trimesh, manifold3d, MuJoCo, matplotlib).

Importing ``pugsd.sim`` imports none of them, so that the daemon's install (without the extras)
can register the commands: each name below loads its module when first used.
"""

from __future__ import annotations

import importlib
from typing import Any

_MODULE_NAMES = {
    "pugsd.sim.objects": ("BUILTIN_OBJECTS", "ObjectSpec", "get_object", "load_object_mesh"),
    "pugsd.sim.render": ("Underwater", "default_rig"),
    "pugsd.sim.sequence": (
        "POSES", "TRAJECTORIES", "SyntheticSequence", "camera_path", "make_sequence", "object_pose",
        "se3_exp",
    ),
    "pugsd.sim.physics": ("GraspTrial", "TrialConfig", "TrialResult", "grasp_pose", "run_trial"),
    "pugsd.sim.evaluate": ("EvalOptions", "run_evaluation"),
}  # fmt: skip
_LAZY = {name: module for module, names in _MODULE_NAMES.items() for name in names}


def __getattr__(name: str) -> Any:
    """A name's module (and with it trimesh, MuJoCo or the pipeline) loads when first used."""
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
