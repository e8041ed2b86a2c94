# SPDX-License-Identifier: Apache-2.0
"""tools/bench-svgp-devices (the SVGP half of the bench for GPU hosts without open3d and zenoh)
runs the real pipeline on an exported problem and writes its timings (CPU only here)."""

from __future__ import annotations

import json
import lzma
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np

from pugsd.config import CoreConfig, SvgpConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.pipeline import PugsPipeline
from tests.helpers.scenes import box_mesh, orbit_frames

ROOT = Path(__file__).resolve().parents[2]


def test_measure_runs_the_pipeline_on_an_exported_problem(tmp_path: Path) -> None:
    cam = PinholeCamera(300, 300, 159.5, 119.5, 320, 240)
    meshes = [box_mesh((0.05, 0.08, 0.12), (0, 0, 0.06))]
    depth = orbit_frames(meshes, np.array([0, 0, 0.06]), 0.45, 0.25, np.linspace(-40, 40, 4), cam)
    pipe = PugsPipeline(CoreConfig(svgp=SvgpConfig(num_inducing=16)))
    for d in depth:
        pipe.integrate(d)
    problem = {
        "complete": {
            "overrides": {},
            "depth": depth,
            "cloud_W": pipe.store.mu_W[:50].copy(),
            "paper_sigma2_cpu": np.zeros(50),
            "paper_s_cpu": 0.0,
        }
    }
    path = tmp_path / "problem.pkl.xz"
    with lzma.open(path, "wb") as fh:
        pickle.dump(problem, fh)
    out = tmp_path / "out.json"
    cmd = [sys.executable, str(ROOT / "tools" / "bench-svgp-devices"), "measure", str(path)]
    cmd += ["--no-agreement", "--repeats", "1", "--inducing", "16", "--only", "cpu1"]
    cmd += ["--json", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    row = result["svgp_step"]["M16_cpu_1threads"]
    assert row["store_points"] == len(pipe.store)  # the frames went through the real store
    assert row["model_step_median_ms"] > 0 and row["train_steps_1_median_ms"] > 0
    assert row["fof_default"] == {"query_device": "cpu", "query_workers": 1}
    assert set(row) >= {
        "algorithm1_20k_lines_1_2_default",
        "algorithm1_20k_lines_1_2_cpu_all_threads",
    }
    assert row["algorithm1_20k_lines_1_2_default"]["sigma2_occ_median_ms"] > 0
    assert result["machine"]["gpu"] is None or isinstance(result["machine"]["gpu"], str)


def test_each_streaming_schedule_runs_once() -> None:
    """With a single ``--inducing`` M the (M, 4) run came twice and its row was overwritten."""
    import importlib.machinery
    import importlib.util

    path = str(ROOT / "tools" / "bench-svgp-devices")
    loader = importlib.machinery.SourceFileLoader("bench_svgp_devices", path)
    spec = importlib.util.spec_from_loader(loader.name, loader)
    assert spec is not None
    tool = importlib.util.module_from_spec(spec)
    loader.exec_module(tool)
    assert tool.streaming_schedules((250, 500)) == [(250, 4), (500, 4), (500, 8), (500, 16)]
    assert tool.streaming_schedules((500,)) == [(500, 4), (500, 8), (500, 16)]
