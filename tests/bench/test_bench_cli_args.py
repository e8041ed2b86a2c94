# SPDX-License-Identifier: Apache-2.0
"""``pugsd bench`` argument handling and the run presets, without running a benchmark: the
measuring (``run_bench``) is replaced by a stub that records what it was asked for."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest

import pugsd.bench.run
import pugsd.bench.targets
from pugsd.bench.cli import _finite
from pugsd.bench.options import BenchOptions
from pugsd.cli import main


class _Stub:
    """Stands in for ``run_bench``: records its arguments, returns a result to print and save."""

    def __init__(self) -> None:
        self.calls: list[dict[str, Any]] = []

    def __call__(self, opts: BenchOptions, overrides: Any, device: str, write: Any, command: str,
                 torch_threads: int | None, progress: Any) -> dict[str, Any]:  # fmt: skip
        self.calls.append({"opts": opts, "overrides": overrides, "device": device,
                           "command": command, "torch_threads": torch_threads})  # fmt: skip
        write("measuring")
        progress(300.0, 600.0)  # half the planned seconds done
        return {"schema": "stub", "nan": float("nan"), "inf": [1.0, float("-inf")],
                "window": (5.0, 30.0), "nested": {"x": float("inf"), "ok": 0.5}}  # fmt: skip


@pytest.fixture
def stub(monkeypatch: pytest.MonkeyPatch) -> _Stub:
    s = _Stub()
    monkeypatch.setattr(pugsd.bench.run, "run_bench", s)
    monkeypatch.setattr(pugsd.bench.targets, "format_table", lambda r: ["TABLE 1", "TABLE 2"])
    monkeypatch.setattr(sys, "argv", ["pugsd", "bench"])
    return s


def test_no_flags_run_the_full_benchmark(stub: _Stub, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench"]) == 0
    (call,) = stub.calls
    assert call["opts"] == BenchOptions.full()
    assert (call["overrides"], call["device"], call["torch_threads"]) == ((), "auto", None)
    assert call["command"] == "pugsd bench"
    io = capsys.readouterr()
    assert io.out == "measuring\n\nTABLE 1\nTABLE 2\n" and io.err == ""  # no bar: not a terminal


def test_a_terminal_gets_a_bar_naming_the_step_with_the_time_taken_and_left(
    stub: _Stub, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import io

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(["bench"]) == 0
    shown = term.getvalue()
    assert "bench: measuring  50%|" in shown and "[00:00<00:" in shown, shown  # elapsed<remaining
    assert capsys.readouterr().out == "measuring\n\nTABLE 1\nTABLE 2\n"


@pytest.mark.parametrize(
    ("flags", "changes"),
    [
        (["--quick"], None),
        (["--no-daemon"], {"use_daemon": False}),
        (["--no-pipeline"], {"use_pipeline": False}),
        (["--quick", "--no-pipeline"], {"use_pipeline": False}),
    ],
)
def test_the_flags_choose_the_preset_and_the_sections(
    stub: _Stub, flags: list[str], changes: dict[str, Any] | None
) -> None:
    assert main(["bench", *flags]) == 0
    base = BenchOptions.quick_preset() if "--quick" in flags else BenchOptions.full()
    assert stub.calls[0]["opts"] == (base if changes is None else base.replace(**changes))


def test_both_halves_skipped_is_refused_before_anything_runs(
    stub: _Stub, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--no-daemon", "--no-pipeline"]) == 2
    assert stub.calls == [] and "leave nothing to measure" in capsys.readouterr().err


def test_overrides_device_and_threads_are_passed_on(stub: _Stub) -> None:
    argv = ["bench", "--set", "svgp.num_inducing=100", "--device", "cpu", "--set", "daemon.k=2",
            "--torch-threads", "3"]  # fmt: skip
    assert main(argv) == 0
    call = stub.calls[0]
    assert call["overrides"] == ["svgp.num_inducing=100", "daemon.k=2"]
    assert call["device"] == "cpu" and call["torch_threads"] == 3
    assert main(["bench", "--device", "cuda", "--torch-threads", "0"]) == 0
    assert (stub.calls[1]["device"], stub.calls[1]["torch_threads"]) == ("cuda", 0)


@pytest.mark.parametrize("bad", [["--device", "gpu"], ["--torch-threads", "two"], ["--bogus"]])
def test_bad_arguments_are_refused_by_the_parser(
    stub: _Stub, bad: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", *bad])
    assert exc.value.code == 2 and stub.calls == []
    capsys.readouterr()


def test_the_recorded_command_is_the_pugsd_command_line(
    stub: _Stub, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The command in the result is what reproduces the run: from ``pugsd bench ...`` as typed,
    and from ``tools/bench ...`` (which has no ``bench`` in its argv) as the same pugsd command."""
    monkeypatch.setattr(sys, "argv", ["/usr/bin/pugsd", "bench", "--quick", "--set", "a b=1"])
    main(["bench", "--quick", "--set", "a b=1"])
    monkeypatch.setattr(sys, "argv", ["tools/bench", "--no-daemon"])
    main(["bench", "--no-daemon"])
    assert [c["command"] for c in stub.calls] == [
        "pugsd bench --quick --set 'a b=1'",
        "pugsd bench --no-daemon",
    ]


def test_the_json_is_strict_and_holds_the_table(
    stub: _Stub, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "new" / "dir" / "bench.json"
    assert main(["bench", "--json", str(path)]) == 0
    text = path.read_text()
    r = json.loads(text)  # strict: no NaN or Infinity tokens
    assert "NaN" not in text and "Infinity" not in text
    assert r == {"schema": "stub", "nan": None, "inf": [1.0, None], "window": [5.0, 30.0],
                 "nested": {"x": None, "ok": 0.5}, "table": ["TABLE 1", "TABLE 2"]}  # fmt: skip
    assert [p.name for p in path.parent.iterdir()] == ["bench.json"]  # no temporary left behind
    assert capsys.readouterr().out.endswith(f"TABLE 2\nwrote {path}\n")
    # an existing file is replaced
    assert main(["bench", "--json", str(path)]) == 0
    assert json.loads(path.read_text())["schema"] == "stub"


def test_finite_replaces_every_non_finite_float() -> None:
    obj = {"a": [math.nan, (math.inf, 2)], "b": {"c": -math.inf, "d": 1e308}, "e": "nan", "f": 3}
    assert _finite(obj) == {"a": [None, [None, 2]], "b": {"c": None, "d": 1e308}, "e": "nan", "f": 3}


def test_the_full_preset_is_the_documented_method() -> None:
    """docs/performance.md: the mug's complete and partial trajectories, 30 stereo pairs each,
    640x480 at 10 Hz; throughput at 30, 25, 20, 15, 10, 5, 2.5, 1.25 Hz, highest first, each for
    max(10 s, 30 frames); a 30 simulated-minute replay spread over 240 s, RSS compared between
    minutes 5 and 30; the diagnostics: a second paper fit with seed 1, +100 / +400 idle steps, the
    streaming run at the paper's M (full run only), the converged reference, one SVGP step at 1
    and 2 torch threads."""
    f = BenchOptions.full()
    assert (f.quick, f.object_name, f.trajectories) == (False, "mug", ("complete", "partial"))
    assert (f.n_frames, f.width, f.height, f.rate_hz) == (30, 640, 480, 10.0)
    assert f.throughput_rates_hz == (30.0, 25.0, 20.0, 15.0, 10.0, 5.0, 2.5, 1.25)
    assert (f.throughput_trial_s, f.throughput_min_frames) == (10.0, 30)
    assert (f.replay_sim_min, f.replay_window_min, f.replay_wall_s) == (30.0, (5.0, 30.0), 240.0)
    assert f.use_daemon and f.use_pipeline
    assert f.paper_epochs is None  # the config's svgp.paper_epochs (the paper's 100)
    assert (f.paper_reference_seed, f.refine_steps, f.thread_sweep) == (1, (100, 400), (1, 2))
    assert f.streaming_at_paper_m and f.optimal_q


def test_the_quick_preset_is_a_smaller_run_of_the_same_sections() -> None:
    q, f = BenchOptions.quick_preset(), BenchOptions.full()
    assert q.quick is True and q != f
    assert q.use_daemon and q.use_pipeline and q.trajectories == f.trajectories
    assert q.n_frames < f.n_frames and q.paper_epochs is not None and q.paper_epochs < 100
    assert q.replay_sim_min < f.replay_sim_min
    w0, w1 = q.replay_window_min
    assert 0 < w0 < w1 <= q.replay_sim_min  # the RSS window lies inside the shorter replay
    assert 10.0 in q.throughput_rates_hz  # so that the quick throughput row can be judged
    # replace: a new object with just those fields changed
    r = q.replace(n_frames=2, use_daemon=False)
    assert (r.n_frames, r.use_daemon, q.n_frames, q.use_daemon) == (2, False, 6, True)
    assert r.replace(n_frames=6, use_daemon=True) == q
