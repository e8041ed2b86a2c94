# SPDX-License-Identifier: Apache-2.0
"""``pugsd.sim.cli`` (``pugsd evaluate``) with the evaluation itself replaced by a stub:
how the arguments map onto ``EvalOptions``, the progress lines and the per-trial JSON lines, and
the arguments refused before anything runs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from pugsd.cli import main
from pugsd.sim import evaluate


def _record(
    obj: str, seed: int, baseline: tuple[bool, bool, bool], pugs: tuple[bool, bool, bool]
) -> dict[str, Any]:
    keys = ("traversal", "closed", "lifted")
    return {
        "object": obj, "recon": "partial", "seed": seed, "mode": "streaming",
        "methods": {"baseline": dict(zip(keys, baseline)), "pugs": dict(zip(keys, pugs))},
    }  # fmt: skip


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> list[evaluate.EvalOptions]:
    """``run_evaluation`` stubbed: it records its options and reports two trials."""
    seen: list[evaluate.EvalOptions] = []

    def run(opts: evaluate.EvalOptions, progress: Any = None) -> dict[str, Any]:
        seen.append(opts)
        if progress is not None:
            progress(_record("mug", 7, (True, True, False), (True, True, True)))
            progress(_record("box", 8, (False, False, False), (True, False, False)))
        return {"wall_time_s": 12.4, "cells": []}

    monkeypatch.setattr(evaluate, "run_evaluation", run)
    monkeypatch.setattr(evaluate, "markdown_table", lambda res, with_paper=True: "TABLE\n")
    return seen


def test_arguments_map_onto_the_options_and_progress_is_reported(
    calls: list[evaluate.EvalOptions], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Comma lists are split and stripped, ``--resolution WxH`` is width then height, repeated
    ``--set`` keep their order; each finished trial is a stderr line ``[i/total] object recon seed
    s mode: method=TCL`` (traversal, closed, lifted as 1/0; total = objects x recons x trials x
    modes = 12) and
    a JSON line in ``<json>.trials.jsonl``; stdout has the table and the wall time."""
    out = tmp_path / "r" / "results.json"
    rc = main([
        "evaluate", "--objects", " mug, box ,", "--recon", "partial,complete", "--methods", "pugs",
        "--trials", "3", "--seed", "5", "--resolution", "160x120", "--frames", "4", "--pose", "lying",
        "--set", "z.b=1", "--set", "a=2", "--json", str(out),
    ])  # fmt: skip
    assert rc == 0
    (opts,) = calls
    assert (opts.objects, opts.recons, opts.methods) == (["mug", "box"], ["partial", "complete"], ["pugs"])
    assert (opts.width, opts.height, opts.trials, opts.seed, opts.n_frames) == (160, 120, 3, 5, 4)
    assert (opts.pose, opts.overrides) == ("lying", ["z.b=1", "a=2"])
    assert opts.modes == ["streaming"] and opts.auc_candidates == 8
    assert opts.object_mesh is None and opts.underwater is False
    io = capsys.readouterr()
    assert io.err.splitlines() == [
        "[1/12] mug partial seed 7 streaming: baseline=110 pugs=111",
        "[2/12] box partial seed 8 streaming: baseline=000 pugs=100",
    ]
    assert io.out == f"TABLE\n\nwall time 12 s\nresults: {out}\n"
    lines = (tmp_path / "r" / "results.trials.jsonl").read_text().splitlines()
    assert [json.loads(x)["seed"] for x in lines] == [7, 8]
    written = json.loads(out.read_text())
    assert written["table_markdown"] == "TABLE\n" and written["wall_time_s"] == 12.4


def test_quiet_runs_print_no_progress(
    calls: list[evaluate.EvalOptions], capsys: pytest.CaptureFixture[str]
) -> None:
    """``--quiet``: no progress lines; with ``--object-mesh`` the total counts one object whatever
    ``--objects`` says (the names are then not checked)."""
    assert main(["evaluate", "--quiet", "--trials", "1"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["evaluate", "--objects", "teapot,kettle", "--object-mesh", "x.stl", "--mass", "0.3",
                 "--recon", "partial", "--trials", "2"]) == 0  # fmt: skip
    assert capsys.readouterr().err.splitlines()[0].startswith("[1/2] ")
    assert calls[-1].object_mesh == "x.stl" and calls[-1].mass_kg == 0.3


def test_a_terminal_gets_a_progress_bar_under_the_trial_lines(
    calls: list[evaluate.EvalOptions], monkeypatch: pytest.MonkeyPatch
) -> None:
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert main(["evaluate", "--objects", "mug", "--recon", "partial", "--trials", "3"]) == 0
    text = term.getvalue()
    assert "[2/3] box partial seed 8 streaming: baseline=000 pugs=100\n" in text
    assert "evaluate:  67%" in text and "2/3 [" in text, text  # with the elapsed time and the ETA


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--recon", "partial,full"], "--recon: unknown full"),
        (["--methods", "pugs,oracle"], "--methods: unknown oracle"),
        (["--methods", " , "], "--methods: empty"),
        (["--pose", "upside_down"], "--pose: unknown upside_down"),
        (["--trials", "0"], "--trials must be >= 1"),
        (["--resolution", "100x100"], "--resolution: one of 160x120, 320x240, 640x480"),
        (["--rescore", "/nonexistent/results.json"], "--rescore: no such file"),
    ],
)
def test_bad_arguments_are_refused_before_anything_runs(
    calls: list[evaluate.EvalOptions], capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    """Each is exit status 1 with ``pugsd evaluate: error: ...`` naming the problem, and the
    evaluation never starts."""
    assert main(["evaluate", "--trials", "1", *args]) == 1
    assert f"pugsd evaluate: error: {message}" in capsys.readouterr().err
    assert calls == []
