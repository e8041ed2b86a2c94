# SPDX-License-Identifier: Apache-2.0
"""tools/setup-env installs the CPU build of torch 2.13.0 (run against stub python3, pip, ldconfig)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# `python3 -m venv DIR` makes DIR/bin/pip (logs its arguments) and DIR/bin/python ("import torch"
# fails unless $TORCH_OK is set); pip fails for a torch pin when $PIP_FAIL_TORCH is set, and for
# one without an extra index (no local wheel) when $PIP_NO_LOCAL_TORCH is set
_PYTHON3 = """#!/usr/bin/env bash
set -e
venv="$3"
mkdir -p "$venv/bin"
cat > "$venv/bin/pip" <<'PIP'
#!/usr/bin/env bash
echo "$*" >> "$PIP_LOG"
if [ -n "${PIP_FAIL_TORCH:-}" ] && [[ "$*" == *torch==* ]]; then exit 1; fi
if [ -n "${PIP_NO_LOCAL_TORCH:-}" ] && [[ "$*" == *torch==* ]] && [[ "$*" != *--extra-index-url* ]]
then exit 1; fi
PIP
cat > "$venv/bin/python" <<'PY'
#!/usr/bin/env bash
[ -n "${TORCH_OK:-}" ]
PY
chmod +x "$venv/bin/pip" "$venv/bin/python"
"""
_LDCONFIG = """#!/usr/bin/env bash
echo "libusb-1.0.so.0 (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libusb-1.0.so.0"
"""


def _run(tmp_path: Path, **env: str) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    stubs = tmp_path / "stubs"
    stubs.mkdir(exist_ok=True)
    for name, text in (("python3", _PYTHON3), ("ldconfig", _LDCONFIG)):
        (stubs / name).write_text(text)
        (stubs / name).chmod(0o755)
    log = tmp_path / "pip.log"
    log.unlink(missing_ok=True)
    full_env = {"PATH": f"{stubs}:{os.environ['PATH']}", "PIP_LOG": str(log), **env}
    proc = subprocess.run(
        ["bash", str(ROOT / "tools" / "setup-env"), str(tmp_path / "venv")],
        cwd=ROOT,
        env=full_env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return proc, log.read_text().splitlines() if log.exists() else []


def test_setup_env_pins_the_cpu_torch(tmp_path: Path) -> None:
    # pip has the +cpu wheel (a local wheel directory, as on the CI machines): no other index
    proc, calls = _run(tmp_path)
    assert proc.returncode == 0, proc.stderr
    torch_calls = [c for c in calls if "torch" in c]
    assert torch_calls == ["install -q torch==2.13.0+cpu"], calls
    assert calls[-1] == "install -q -e .[dev,sim]"
    # no local wheel: PyTorch's CPU index, never PyPI's plain torch==2.13.0 (the CUDA build)
    proc, calls = _run(tmp_path, PIP_NO_LOCAL_TORCH="1")
    assert proc.returncode == 0, proc.stderr
    torch_calls = [c for c in calls if "torch" in c]
    assert len(torch_calls) == 2 and all("torch==2.13.0+cpu" in c.split() for c in torch_calls)
    assert "https://download.pytorch.org/whl/cpu" in torch_calls[1].split()
    proc, calls = _run(tmp_path, PIP_NO_LOCAL_TORCH="1", PUGSD_TORCH_INDEX="file:///srv/wheels")
    assert proc.returncode == 0 and "file:///srv/wheels" in [c for c in calls if "torch" in c][1]


def test_setup_env_replaces_an_earlier_open3d_with_open3d_cpu(tmp_path: Path) -> None:
    """On Linux x86_64 pyproject asks for open3d-cpu (the same module, without CUDA): an open3d
    installed before would share its folder, so it is removed first (the stub pip finds it)."""
    import platform

    proc, calls = _run(tmp_path, TORCH_OK="1")
    assert proc.returncode == 0, proc.stderr
    if (platform.system(), platform.machine()) == ("Linux", "x86_64"):
        want = ["show -q open3d", "uninstall -y -q open3d open3d-cpu", "install -q -e .[dev,sim]"]
        assert calls[-3:] == want, calls


def test_setup_env_keeps_an_installed_torch(tmp_path: Path) -> None:
    proc, calls = _run(tmp_path, TORCH_OK="1")
    assert proc.returncode == 0, proc.stderr
    assert not [c for c in calls if "torch" in c] and calls[-1] == "install -q -e .[dev,sim]"


def test_setup_env_stops_when_the_cpu_torch_cannot_be_had(tmp_path: Path) -> None:
    proc, calls = _run(tmp_path, PIP_FAIL_TORCH="1")
    assert proc.returncode == 1 and "install a torch >= 2.2" in proc.stderr
    assert not any(c.startswith("install -q -e") for c in calls)  # no silent CUDA fallback
