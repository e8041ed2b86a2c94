# SPDX-License-Identifier: Apache-2.0
"""The daemon's install without the simulation extras (``pugsd[sim]``: trimesh, manifold3d,
MuJoCo, matplotlib): the daemon, its clients and the recording tools import without them, and
each command that renders or simulates says what to install instead of a traceback. The extras
are hidden from a child interpreter (None in sys.modules: an import of them fails as when they
are not installed)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from pugsd.wire.session import free_tcp_port

ROOT = Path(__file__).resolve().parents[1]
HIDE = "import sys; sys.modules.update(dict.fromkeys(('trimesh', 'manifold3d', 'mujoco', 'matplotlib'))); "


def _python(code: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-c", HIDE + code], capture_output=True, text=True, env=env, timeout=240, check=False
    )


def test_the_daemon_clients_and_recording_tools_need_no_simulation_extras() -> None:
    proc = _python(
        "import pugsd.daemon.app, pugsd.daemon.client, pugsd.record.replay, pugsd.record.player, "
        "pugsd.record.recorder, pugsd.pipeline_factory, pugsd.core.pipeline, pugsd.arm.controller; "
        "from pugsd.cli import main; raise SystemExit(main(['version']))"
    )
    assert proc.returncode == 0 and proc.stdout.startswith("pugsd "), proc.stderr[-3000:]


def test_simulation_commands_say_to_install_the_extras(tmp_path: Path) -> None:
    commands = [
        ["evaluate", "--trials", "1"],
        ["offline"],
        ["mcap", "synth", str(tmp_path / "s.mcap")],
        ["demo", "--duration", "1", "--out", str(tmp_path / "demo"), "--listen",
         f"tcp/127.0.0.1:{free_tcp_port()}"],
    ]  # fmt: skip
    proc = _python(
        f"import json; from pugsd.cli import main; print(json.dumps([main(a) for a in {commands!r}]))"
    )
    assert json.loads(proc.stdout) == [1] * len(commands), proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert len(lines) == len(commands) and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    for argv, line in zip(commands, lines):
        assert line.startswith(f"pugsd {argv[0]}: error: this command needs the simulation"), line
        assert line.endswith("pip install 'pugsd[sim]'"), line
