# SPDX-License-Identifier: Apache-2.0
"""``pugsd`` command line (pugsd/cli.py, pugsd/config_cli.py and pugsd/offline_cli.py): exit codes,
the subcommands, the global log level, ``check-config``'s ok line, ``dump-config --config``,
``offline`` (its defaults, the streaming and paper modes, its grasp table), with the model and the
synthetic scene replaced by stubs."""

from __future__ import annotations

import argparse
import contextlib
import logging
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import pugsd.cli
from pugsd.cli import build_parser, main
from pugsd.core.types import ScoredGrasps
from pugsd.errors import ConfigError
from pugsd.offline_cli import format_grasps


def _grasps(n: int) -> ScoredGrasps:
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, 3] = (0.1 * (i + 1), 0.02 * i, 0.5)
    return ScoredGrasps(
        pose_W=poses,
        contact_W=poses[:, :3, 3].copy(),
        width_m=np.full(n, 0.04),
        baseline_confidence=np.linspace(0.9, 0.5, n),
        sigma2_occ=np.full(n, 2.5e-5),
        pugs_confidence=np.linspace(12.0, 3.0, n),
        grasp_id=np.arange(10, 10 + n, dtype=np.int64),
    )


def _stub(monkeypatch: pytest.MonkeyPatch, name: str, func: Any) -> None:
    """Replace a subcommand of pugsd.cli (``build_parser`` looks the name up when main runs)."""
    monkeypatch.setattr(pugsd.cli, name, func)


def test_the_subcommands_a_user_types_are_all_registered() -> None:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    core = ("version", "check-config", "dump-config", "offline")
    for cmd in (*core, "run", "demo", "status", "grasps", "reset"):
        assert cmd in sub.choices, cmd


def test_no_subcommand_is_an_argument_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
    assert "the following arguments are required: COMMAND" in capsys.readouterr().err


def test_ctrl_c_in_a_command_exits_130(monkeypatch: pytest.MonkeyPatch) -> None:
    def interrupted(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    _stub(monkeypatch, "_version", interrupted)
    assert main(["version"]) == 130


def test_ctrl_c_while_the_commands_are_imported_exits_130_without_a_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The subcommand modules import open3d, torch and scipy (seconds): a Ctrl-C then gave a
    KeyboardInterrupt traceback, before main's own handler."""

    def importing() -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr("pugsd.cli.build_parser", importing)
    assert main(["version"]) == 130
    assert capsys.readouterr().err == "pugsd: interrupted\n"


def test_ctrl_c_swallowed_by_an_import_guard_still_stops_the_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A library's catch-all import guard swallowed the KeyboardInterrupt raised inside it, and
    the command ran on (a `pugsd run` interrupted 0.3 s after its start went on to serve)."""
    import signal

    real = build_parser
    ran: list[str] = []

    def importing_with_a_guard() -> argparse.ArgumentParser:
        with contextlib.suppress(BaseException):  # an import guard that swallows everything ...
            signal.raise_signal(signal.SIGINT)  # ... and the Ctrl-C during that import
        return real()

    monkeypatch.setattr("pugsd.cli.build_parser", importing_with_a_guard)
    _stub(monkeypatch, "_version", lambda args: ran.append("version") or 0)
    assert main(["version"]) == 130 and ran == []
    assert capsys.readouterr().err == "pugsd: interrupted\n"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back


@pytest.mark.parametrize(("rc", "want"), [(None, 0), (0, 0), (3, 3)])
def test_the_commands_return_code_is_the_exit_code(
    monkeypatch: pytest.MonkeyPatch, rc: int | None, want: int
) -> None:
    _stub(monkeypatch, "_version", lambda args: rc)
    assert main(["version"]) == want


def test_an_error_is_one_line_naming_the_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def bad(args: argparse.Namespace) -> int:
        raise ConfigError("x.y: nope")

    _stub(monkeypatch, "_version", bad)
    assert main(["version"]) == 1
    assert capsys.readouterr().err == "pugsd version: error: x.y: nope\n"


@pytest.fixture
def bare_root() -> Iterator[logging.Logger]:
    """The root logger, its handlers and level put back after the test (which removes the
    handlers itself: pytest adds its own between a fixture's set-up and the test)."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        yield root
    finally:
        for h in root.handlers:
            h.close()
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])


@pytest.mark.parametrize(
    ("argv", "level"), [([], logging.WARNING), (["--log-level", "error"], logging.ERROR)]
)
def test_the_global_log_level_defaults_to_warning(
    bare_root: logging.Logger, capsys: pytest.CaptureFixture[str], argv: list[str], level: int
) -> None:
    bare_root.handlers[:] = []  # so that main's basicConfig takes effect
    bare_root.setLevel(logging.NOTSET)
    assert main([*argv, "version"]) == 0
    assert bare_root.level == level


def test_check_config_prints_ok(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "good.toml"
    f.write_text("[grasp]\ngamma = 3.0\n")
    assert main(["check-config", str(f)]) == 0
    out = capsys.readouterr()
    assert out.out == f"{f}: ok\n" and out.err == ""


def test_dump_config_shows_the_given_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[grasp]\ngamma = 3.5\n")
    assert main(["dump-config", "--config", str(f)]) == 0
    assert "\ngrasp.gamma = 3.5\n" in capsys.readouterr().out
    assert main(["dump-config"]) == 0
    assert "\ngrasp.gamma = 3.5\n" not in capsys.readouterr().out


def test_format_grasps_table() -> None:
    text = format_grasps(_grasps(2), n=5)  # fewer grasps than asked for
    assert text.splitlines() == [
        "rank     id      x_m      y_m      z_m  width_m  baseline  sigma2_occ       pugs",
        "   1     10    0.100    0.000    0.500    0.040     0.900     2.5e-05         12",
        "   2     11    0.200    0.020    0.500    0.040     0.500     2.5e-05          3",
    ]
    assert len(format_grasps(_grasps(8)).splitlines()) == 1 + 8
    assert len(format_grasps(_grasps(12)).splitlines()) == 1 + 10  # the default top 10


def test_offline_defaults() -> None:
    a = build_parser().parse_args(["offline"])
    scene = (a.object, a.trajectory, a.frames, a.width, a.height, a.seed)
    assert scene == ("mug", "partial", None, 640, 480, 0)
    assert (a.mode, a.epochs, a.final_steps, a.top) == ("streaming", None, 60, 5)


class _FakePipe:
    def __init__(self) -> None:
        self.calls: list[tuple[str, Any]] = []

    def add_stereo(self, frame: Any) -> None:
        self.calls.append(("add", frame))

    def train_steps(self, n: int | None = None) -> None:
        self.calls.append(("train", n))

    def fit_paper(self, epochs: int | None) -> None:
        self.calls.append(("fit_paper", epochs))

    def stats(self) -> dict[str, int]:
        return {"voxels": 77}

    def compute(self) -> Any:
        return types.SimpleNamespace(
            grasps=_grasps(3),
            baseline_grasps=_grasps(1),
            cloud_W=np.zeros((5, 3)),
            candidates=types.SimpleNamespace(valid=np.array([True, False, True, True])),
        )


@pytest.fixture
def offline_pipe(monkeypatch: pytest.MonkeyPatch) -> _FakePipe:
    import pugsd.pipeline_factory
    import pugsd.sim

    pipe = _FakePipe()
    seq = types.SimpleNamespace(
        object_name="mug", trajectory="partial", frames=["f0", "f1", "f2"], core_overrides={}
    )
    monkeypatch.setattr(pugsd.sim, "make_sequence", lambda *a, **kw: seq)
    monkeypatch.setattr(pugsd.pipeline_factory, "make_pipeline", lambda core, seed=0: pipe)
    return pipe


def test_offline_streaming_trains_after_every_frame_then_the_final_steps(
    offline_pipe: _FakePipe, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["offline", "--final-steps", "9", "--top", "2"]) == 0
    assert offline_pipe.calls == [
        ("add", "f0"), ("train", None), ("add", "f1"), ("train", None), ("add", "f2"), ("train", None),
        ("train", 9),
    ]  # fmt: skip
    out = capsys.readouterr().out
    assert out.startswith(
        "pugsd offline: mug, partial, 3 frames 640x480, mode streaming: 77 Gaussians, "
        "5 query points, 3 candidates, "
    )
    pugs, base = out.split("Top grasps by the proposer's own confidence (baseline):\n")
    assert "Top grasps by PUGS confidence (Eq. 13):\n" in pugs
    assert pugs.rstrip("\n").endswith(format_grasps(_grasps(3), 2).rstrip("\n"))  # --top 2 of 3
    assert base == format_grasps(_grasps(1), 2)


def test_offline_paper_mode_fits_in_one_batch(
    offline_pipe: _FakePipe, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["offline", "--mode", "paper", "--epochs", "4"]) == 0
    assert offline_pipe.calls == [("add", "f0"), ("add", "f1"), ("add", "f2"), ("fit_paper", 4)]
    assert "mode paper: 77 Gaussians" in capsys.readouterr().out
