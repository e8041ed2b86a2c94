# SPDX-License-Identifier: Apache-2.0
"""The core is pure: importing it loads no zenoh and no I/O package of pugsd, and no pugsd module
of the core imports asyncio.

Each check runs in a fresh interpreter, since this test process has loaded everything already.
torch imports ``unittest.mock``, which imports asyncio, so asyncio is in ``sys.modules`` once
torch is; the import hook below therefore records which module imports asyncio or zenoh, and the
modules that need neither torch nor open3d are also checked for asyncio in ``sys.modules``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

# the pugsd modules outside pugsd.core that the core may load
_ALLOWED_OUTSIDE_CORE = {"pugsd", "pugsd.configbase", "pugsd.errors"}

# core modules that import neither torch nor open3d (both load asyncio themselves)
_LIGHT_CORE_MODULES = (
    "pugsd.core.camera",
    "pugsd.core.config",
    "pugsd.core.cubature",
    "pugsd.core.geometry",
    "pugsd.core.observation",
    "pugsd.core.stereo",
    "pugsd.core.types",
)

_IMPORT_ALL = textwrap.dedent(
    """
    import builtins, importlib, json, pkgutil, sys

    watched = ("asyncio", "zenoh")
    imports = []  # (importer, name) for every import of a watched package by a pugsd module
    _orig = builtins.__import__

    def _hook(name, globals=None, locals=None, fromlist=(), level=0):
        importer = (globals or {}).get("__name__", "")
        if level == 0 and name.split(".")[0] in watched and importer.startswith("pugsd"):
            imports.append((importer, name))
        return _orig(name, globals, locals, fromlist, level)

    builtins.__import__ = _hook
    import pugsd.core

    names = [m.name for m in pkgutil.walk_packages(pugsd.core.__path__, "pugsd.core.")]
    for name in names:
        importlib.import_module(name)
    print(json.dumps({
        "modules": names,
        "imports": imports,
        "zenoh": "zenoh" in sys.modules,
        "pugsd": sorted(m for m in sys.modules if m == "pugsd" or m.startswith("pugsd.")),
    }))
    """
)


def _run(code: str) -> str:
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc.stdout.strip().splitlines()[-1]


def test_importing_every_core_module_loads_no_zenoh_and_no_io_package() -> None:
    out = json.loads(_run(_IMPORT_ALL))
    assert "pugsd.core.pipeline" in out["modules"] and "pugsd.core.grasp.proposer" in out["modules"]
    assert out["imports"] == [], f"core modules import asyncio or zenoh: {out['imports']}"
    assert out["zenoh"] is False
    outside = [m for m in out["pugsd"] if not m.startswith("pugsd.core") and m not in _ALLOWED_OUTSIDE_CORE]
    assert outside == [], f"importing pugsd.core loads {outside}"


def test_core_modules_without_torch_load_no_asyncio() -> None:
    code = "import sys\n" + "".join(f"import {m}\n" for m in _LIGHT_CORE_MODULES)
    code += "print(sorted(m for m in ('asyncio', 'zenoh', 'torch', 'open3d') if m in sys.modules))"
    assert _run(code) == "[]"
