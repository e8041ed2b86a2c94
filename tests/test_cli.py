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


def test_format_grasps_lines() -> None:
    text = format_grasps(_grasps(2), n=5)  # fewer grasps than asked for
    assert text.splitlines() == [
        "grasp 1: PUGS confidence 12 (baseline 0.900, sigma^2_occ 2.5e-05), contact (+0.100, +0.000, "
        "+0.500) m in world, approach (+0.00, +0.00, +1.00), width 4.0 cm, id 10",
        "grasp 2: PUGS confidence 3 (baseline 0.500, sigma^2_occ 2.5e-05), contact (+0.200, +0.020, "
        "+0.500) m in world, approach (+0.00, +0.00, +1.00), width 4.0 cm, id 11",
    ]
    assert len(format_grasps(_grasps(8)).splitlines()) == 8
    assert len(format_grasps(_grasps(12)).splitlines()) == 10  # the default top 10


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


def test_dash_dash_version_prints_the_version(capsys: pytest.CaptureFixture[str]) -> None:
    from pugsd import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out == f"pugsd {__version__}\n"


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["stauts"], "invalid choice: 'stauts' (choose from"),
        (["mcap", "inf", "x.mcap"], "invalid choice: 'inf' (choose from"),
        (["demo", "--durration", "3"], "pugsd demo: error: unrecognized arguments: --durration 3"),
        (["grasps", "--top=3", "--jsn"], "pugsd grasps: error: unrecognized arguments: --jsn"),
    ],
)
def test_a_misspelled_command_or_option_gets_a_suggestion(
    capsys: pytest.CaptureFixture[str], argv: list[str], said: str
) -> None:
    want = {"stauts": "'status'", "inf": "'info'", "--durration": "'--duration'", "--jsn": "'--json'"}
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and said in err, err
    typo = next(a for a in argv if a.lstrip("-").split("=")[0] in {k.lstrip("-") for k in want})
    assert err.rstrip().endswith(f"; did you mean {want[typo]}?"), err


def test_a_word_close_to_nothing_gets_no_suggestion(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["demo", "--zzzzzz"])
    err = capsys.readouterr().err
    assert "unrecognized arguments: --zzzzzz" in err and "did you mean" not in err


def _leaf_parsers() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    def walk(p: argparse.ArgumentParser, path: str) -> Iterator[tuple[str, argparse.ArgumentParser]]:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            yield path, p
        for a in subs:
            for name, q in a.choices.items():
                yield from walk(q, f"{path} {name}")

    yield from walk(build_parser(), "pugsd")


def test_every_command_has_an_example_and_every_option_its_help_and_default() -> None:
    for path, p in _leaf_parsers():
        required = [g for g in p._mutually_exclusive_groups if g.required]
        required_groups = {id(a) for g in required for a in g._group_actions}
        assert p.epilog and f"\n  {path}" in "\n" + p.epilog.split("example", 1)[1], path
        help_text = p.format_help()
        for a in p._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            assert a.help, f"{path} {a.dest}: no help"
            flag = isinstance(a, (argparse._StoreTrueAction, argparse._AppendAction))
            if a.option_strings and not flag and id(a) not in required_groups:
                # the default is shown by the formatter, or the help says what no value means
                assert a.default is not None or "default" in a.help, f"{path} {a.dest}: no default"
                if a.default is not None and "default" not in a.help:
                    assert f"(default: {a.default})" in " ".join(help_text.split()), (path, a.dest)


def test_the_top_level_help_opens_with_what_pugsd_does(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    first = out.split("\n\n")[1]
    assert first.startswith("pugsd finds grasps on an object") and "``" not in first
    assert "exit codes: 0 ok; 1 failure; 2 usage error;" in out


def test_a_closed_stdout_ends_a_command_quietly(tmp_path: Path) -> None:
    """`pugsd mcap info x.mcap | head`: the reader goes away; the command printed a
    BrokenPipeError traceback (twice: once more at the interpreter's exit)."""
    import os
    import subprocess
    import sys

    r, w = os.pipe()
    os.close(r)  # nobody will read
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run(
        [sys.executable, "-m", "pugsd", "dump-config"], stdout=w, stderr=subprocess.PIPE, env=env,
        timeout=120, check=False,
    )  # fmt: skip
    os.close(w)
    assert proc.returncode == 141 and proc.stderr == b"", proc.stderr.decode()


def test_a_simulation_command_without_the_sim_extras_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def needs_mujoco(args: argparse.Namespace) -> int:
        import mujoco_is_not_installed  # noqa: F401  (stands for a missing extra below)

        return 0

    def needs_sim(args: argparse.Namespace) -> int:
        raise ModuleNotFoundError("No module named 'trimesh'", name="trimesh")

    _stub(monkeypatch, "_version", needs_sim)
    assert main(["version"]) == 1
    assert capsys.readouterr().err == (
        "pugsd version: error: this command needs the simulation (no module named 'trimesh'): "
        "pip install 'pugsd[sim]'\n"
    )
    _stub(monkeypatch, "_version", needs_mujoco)  # any other missing module is a bug: raised
    with pytest.raises(ModuleNotFoundError):
        main(["version"])
