# SPDX-License-Identifier: Apache-2.0
"""Building a ``PugsPipeline`` with what it must load from disk (the core itself does no I/O).

``grasp.proposer = "torchscript"`` needs the user's network: :func:`load_torchscript` reads it,
:func:`make_pipeline` hands it to the pipeline. Every entry point (daemon, demo, offline run,
replay, bench) builds its pipeline here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pugsd.config import CoreConfig
from pugsd.core.pipeline import PugsPipeline
from pugsd.errors import PugsdError


def model_path_problem(path: str | Path) -> str | None:
    """Why ``grasp.model_path`` cannot be loaded (``proposer = "torchscript"``), None when it names a
    file; ``pugsd check-config`` asks this without loading it (no torch import)."""
    if not str(path).strip():
        return 'grasp.model_path is empty, but grasp.proposer = "torchscript" needs a TorchScript file'
    if not Path(path).is_file():
        return f"grasp.model_path: no TorchScript model at {Path(path)!s}"
    return None


def load_torchscript(path: str | Path) -> Any:
    """The TorchScript module at ``path`` on the CPU, in eval mode; PugsdError naming the file."""
    import torch

    problem = model_path_problem(path)
    if problem:
        raise PugsdError(problem)
    p = Path(path)
    try:
        model = torch.jit.load(str(p), map_location="cpu")
    except (RuntimeError, ValueError, OSError) as exc:
        raise PugsdError(f"grasp.model_path: cannot load {p!s} as TorchScript: {exc}") from None
    model.eval()
    return model


def make_pipeline(core: CoreConfig, seed: int = 0) -> PugsPipeline:
    """``PugsPipeline(core, seed)`` with the grasp network loaded when the config names one."""
    model = load_torchscript(core.grasp.model_path) if core.grasp.proposer == "torchscript" else None
    return PugsPipeline(core, seed, grasp_model=model)
