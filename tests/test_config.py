# SPDX-License-Identifier: Apache-2.0
"""Config: the reference file equals the defaults and shows the keys a deployment sets first;
unknown keys, types and ranges are rejected with the dotted path of the key; every range bound of
the core, daemon, topics, queues and record sections on both sides of its boundary with the exact
message, every choice list, the sections' own cross-key checks, config_warnings, override parsing
and the dump/load round trip.

The bounds and choices are written out here on purpose (not read from the fields' metadata): a
changed limit in the source must fail a test, not move the test along with it."""

from __future__ import annotations

import dataclasses
import datetime
import math
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.config import (
    CoreConfig,
    PugsdConfig,
    config_warnings,
    core_of,
    dump_config,
    load_config,
    load_config_dict,
    parse_override,
)
from pugsd.configbase import to_dict
from pugsd.daemon.config import DaemonConfig, TopicsConfig
from pugsd.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_reference_file_equals_defaults() -> None:
    ref = tomllib.loads((ROOT / "config" / "pugsd.toml").read_text())
    assert ref == to_dict(PugsdConfig())
    assert load_config(ROOT / "config" / "pugsd.toml") == PugsdConfig()
    assert (ROOT / "config" / "pugsd.toml").read_text() == dump_config()


def test_every_key_is_documented() -> None:
    text = dump_config()
    lines = text.splitlines()
    keys = [i for i, line in enumerate(lines) if " = " in line and not line.startswith("#")]
    assert len(keys) == len(_dotted_keys(to_dict(PugsdConfig())))
    for i in keys:
        start = i
        while start > 0 and lines[start - 1].startswith("# ") and not _TABLE_HEADING.match(lines[start - 1]):
            start -= 1
        doc = " ".join(ln[2:] for ln in lines[start:i])
        assert len(doc) > 3 and not doc.startswith("["), lines[i]  # a meaning, not only a unit


_TABLE_HEADING = re.compile(r"# \[[a-z_.]+\]( |$)")  # "# [stereo] Stereo matching ..."


def _dotted_keys(d: dict, prefix: str = "") -> list[str]:
    out: list[str] = []
    for k, v in d.items():
        out += _dotted_keys(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]
    return out


def test_the_keys_a_deployment_sets_come_before_the_advanced_part() -> None:
    lines = dump_config().splitlines()
    order = [ln.split(" = ")[0] for ln in lines if " = " in ln and not ln.startswith("#")]
    assert sorted(order) == sorted(_dotted_keys(to_dict(PugsdConfig())))  # each key once
    advanced = next(i for i, ln in enumerate(lines) if ln.startswith("# Advanced"))
    n_user = sum(1 for ln in lines[:advanced] if " = " in ln and not ln.startswith("#"))
    user = {
        "topics.left_image", "topics.pose", "topics.domain_id", "zenoh.listen.endpoints",
        "zenoh.connect.endpoints", "daemon.T_B_C_xyz_m", "daemon.T_B_C_quat_xyzw", "svgp.device",
        "fof.query_device", "grasp.gripper.max_width_m", "grasp.gamma", "record.enabled",
        "record.directory",
    }  # fmt: skip
    assert user <= set(order[:n_user])
    assert {"stereo.downsample", "svgp.kernel", "daemon.ingress_limit", "queues.depth"} <= set(order[n_user:])


def test_a_file_of_section_tables_loads_like_the_dotted_reference() -> None:
    dotted = load_config_dict(tomllib.loads("grasp.gamma = 3.0\ngrasp.gripper.depth_m = 0.1\n"))
    tables = load_config_dict(tomllib.loads("[grasp]\ngamma = 3.0\n[grasp.gripper]\ndepth_m = 0.1\n"))
    assert dotted == tables and tables.grasp.gamma == 3.0 and tables.grasp.gripper.depth_m == 0.1


@pytest.mark.parametrize(
    "data,message",
    [
        ({"fof": {"k_neighbors": 3}}, "fof.k_neighbors: unknown key"),
        ({"nope": {}}, "nope: unknown key"),
        ({"fof": {"k_neighbours": "ten"}}, "fof.k_neighbours: expected an integer"),
        ({"fof": {"k_neighbours": 0}}, "fof.k_neighbours: 0 is below the minimum 1"),
        (
            {"grasp": {"gripper": {"max_width_m": -1}}},
            "grasp.gripper.max_width_m: -1.0 must be greater",
        ),
        ({"cubature": {"variance_form": "B"}}, "cubature.variance_form: 'B' is not one of"),
        ({"stereo": {"block_size": 4}}, "block_size: must be odd"),
        ({"svgp": {"ngd_lr": True}}, "svgp.ngd_lr: expected a number"),
        ({"observation": {"regulariser_m": 0}}, "observation.regulariser_m: 0.0 must be greater"),
        ({"fof": 3}, "fof: expected a table, got int"),
        ({"arm": {"kinematics": {"joint_signs": 1.0}}}, "arm.kinematics.joint_signs: expected an array"),
        (
            {"arm": {"kinematics": {"joint_signs": [1.0, "x"]}}},
            "arm.kinematics.joint_signs[1]: expected a number, got str",
        ),
        ({"zenoh": []}, "zenoh: expected a table, got list"),
        ({"svgp": {"device": 1}}, "svgp.device: expected a string, got int"),
        ({"daemon": {"log_json": "yes"}}, "daemon.log_json: expected true or false, got str"),
        # checks across keys name the dotted path too (they said "daemon: T_B_C_quat_xyzw: ...")
        ({"stereo": {"block_size": 4}}, "stereo.block_size: must be odd"),
        (
            {"daemon": {"T_B_C_quat_xyzw": [0.0, 0.0, 0.0, 2.0]}},
            "daemon.T_B_C_quat_xyzw: [0.0, 0.0, 0.0, 2.0] is not a unit quaternion",
        ),
        ({"daemon": {"T_B_C_xyz_m": [0.1, 0.0]}}, "daemon.T_B_C_xyz_m: expected 3 finite values"),
        # an unknown key near a known one suggests it
        (
            {"daemon": {"T_B_C_xyz": [0.1, 0.0, 0.2]}},
            "daemon.T_B_C_xyz: unknown key; did you mean T_B_C_xyz_m?",
        ),
    ],
)
def test_bad_values_name_the_dotted_path(data: dict, message: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(ConfigError) as exc:
        load_config_dict(data)
    assert message in str(exc.value)


def test_int_widens_to_float_and_overrides() -> None:
    cfg = load_config_dict({"grasp": {"gamma": 2}}, ["fof.k_neighbours=7", "svgp.kernel=matern52"])
    assert cfg.grasp.gamma == 2.0 and isinstance(cfg.grasp.gamma, float)
    assert cfg.fof.k_neighbours == 7
    assert cfg.svgp.kernel == "matern52"


def test_default_zenoh_config_is_loopback_only() -> None:
    z = PugsdConfig().zenoh
    assert z["scouting"]["multicast"]["enabled"] is False
    assert z["scouting"]["gossip"]["enabled"] is False
    eps = z["listen"]["endpoints"] + z["connect"]["endpoints"]
    assert eps and all(e.startswith("tcp/127.0.0.1:") for e in eps)


def test_cli_check_config_exit_codes(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("[grasp]\ngamma = 3.0\n")
    bad = tmp_path / "bad.toml"
    bad.write_text("[grasp]\ngama = 3.0\n")
    run = [sys.executable, "-m", "pugsd", "check-config"]
    ok = subprocess.run([*run, str(good)], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    ko = subprocess.run([*run, str(bad)], capture_output=True, text=True, timeout=60)
    assert ko.returncode == 1
    assert "grasp.gama: unknown key" in ko.stderr
    v = subprocess.run([sys.executable, "-m", "pugsd", "version"], capture_output=True, text=True, timeout=60)
    assert v.returncode == 0 and v.stdout.startswith("pugsd ")


def test_partial_zenoh_table_keeps_safe_defaults() -> None:
    cfg = load_config_dict({}, ["zenoh.listen.endpoints=['tcp/127.0.0.1:17999']"])
    assert cfg.zenoh["listen"]["endpoints"] == ["tcp/127.0.0.1:17999"]
    assert cfg.zenoh["scouting"]["multicast"]["enabled"] is False
    assert cfg.zenoh["scouting"]["gossip"]["enabled"] is False
    cfg = load_config_dict({"zenoh": {"mode": "client"}})
    assert cfg.zenoh["mode"] == "client" and cfg.zenoh["scouting"]["gossip"]["enabled"] is False


@pytest.mark.parametrize(
    "override",
    [
        "daemon.pose_max_gap_s=inf",  # int(inf * 1e9) broke the daemon's start after check-config
        "daemon.status_rate_hz=inf",  # a period of 0 s: a busy loop
        "daemon.stall_timeout_s=nan",
        "arm.kinematics.T_B_W_xyz=[nan, 0.0, 0.0]",  # no range check on these: nan went through
        "arm.safety.workspace_min_m=[-inf, -1.0, -1.0]",
    ],
)
def test_non_finite_numbers_are_rejected(override: str) -> None:
    with pytest.raises(ConfigError, match="expected a finite number"):
        load_config_dict({}, [override])


def test_pose_max_gap_is_bounded() -> None:
    """A finite but huge gap overflowed the daemon's conversion to integer nanoseconds."""
    with pytest.raises(ConfigError, match=r"daemon.pose_max_gap_s: 1e\+300 is above the maximum"):
        load_config_dict({}, ["daemon.pose_max_gap_s=1e300"])
    assert load_config_dict({}, ["daemon.pose_max_gap_s=3600"]).daemon.pose_max_gap_s == 3600.0


def test_zenoh_table_must_be_json() -> None:
    """A TOML date in the zenoh table was a TypeError traceback, not a config error."""
    with pytest.raises(ConfigError, match="zenoh: not representable as JSON"):
        load_config_dict({"zenoh": {"when": datetime.date(1979, 5, 27)}})


def test_override_parsing_edge_cases() -> None:
    assert parse_override("daemon.log_level = debug") == ("daemon.log_level", "debug")
    assert parse_override("daemon.prefix=pugs/robot1") == ("daemon.prefix", "pugs/robot1")
    assert parse_override("daemon.prefix=a=b") == ("daemon.prefix", "a=b")
    assert parse_override("zenoh.connect.endpoints=['tcp/127.0.0.1:1']") == (
        "zenoh.connect.endpoints",
        ["tcp/127.0.0.1:1"],
    )
    assert load_config_dict({}, ["daemon.log_level = debug"]).daemon.log_level == "debug"
    for bad in ("=3", "daemon..prefix=x", "daemon.=x", "noequals"):
        with pytest.raises(ConfigError, match="override"):
            parse_override(bad)


@pytest.mark.parametrize(
    "text,message",
    [
        # zenoh rejects the typo when `pugsd run` opens its session: check-config (the unit's
        # ExecStartPre) said ok, and the service restarted in a loop
        ("[zenoh.scouting.multicast]\nenabeld = false\n", "unknown field `enabeld`"),
        ('[zenoh.connect]\nendpoints = ["tcp/192.168.1.10:7447"]\n', "allow_non_loopback = true"),
        ('[zenoh]\nmode = "server"\n', "invalid [zenoh] config"),
    ],
)
def test_check_config_validates_the_zenoh_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    f = tmp_path / "z.toml"
    f.write_text(text)
    assert main(["check-config", str(f)]) == 1
    assert message in capsys.readouterr().err
    lan = tmp_path / "lan.toml"
    lan.write_text(
        '[daemon]\nallow_non_loopback = true\n[zenoh.connect]\nendpoints = ["tcp/192.168.1.10:7447"]\n'
    )
    assert main(["check-config", str(lan)]) == 0


@pytest.mark.parametrize(
    "text,message",
    [
        ("[zenoh.adminspace]\nenabled = true\n[zenoh.adminspace.permissions]\nwrite = true\n",
         "adminspace.permissions.write must be false"),
        ("[zenoh.plugins_loading]\nenabled = true\n", "plugins_loading.enabled must be false"),
        ('[zenoh.plugins_loading]\nenabled = true\n[zenoh.plugins.rest]\nhttp_port = "0.0.0.0:8000"\n',
         "plugins_loading.enabled must be false"),
        ('[zenoh.plugins.rest]\nhttp_port = "0.0.0.0:8000"\n', "plugins (rest) must not be configured"),
    ],
)  # fmt: skip
def test_check_config_refuses_zenoh_adminspace_write_and_plugins_on_loopback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    """What could open the daemon's session beyond 127.0.0.1 (write access to its config through
    the admin space, a REST plugin on every interface) is refused like a LAN endpoint, and
    allowed with allow_non_loopback like one."""
    f = tmp_path / "z.toml"
    f.write_text(text)
    assert main(["check-config", str(f)]) == 1
    err = capsys.readouterr().err
    assert message in err and "unless [daemon] allow_non_loopback = true" in err, err
    f.write_text("[daemon]\nallow_non_loopback = true\n" + text)
    assert main(["check-config", str(f)]) == 0
    # read-only access to the admin space over loopback stays allowed
    f.write_text("[zenoh.adminspace]\nenabled = true\n")
    assert main(["check-config", str(f)]) == 0


@pytest.mark.parametrize(
    "override",
    [
        "daemon.prefix=''",  # zenoh refused "/grasps/latest" only when the daemon declared it
        "daemon.prefix='pugs/'",
        "daemon.prefix='pugs/*'",
        "daemon.node_name=''",
        "daemon.node_name='arm*1'",
        "topics.pose=''",
        "topics.left_image='/stereo//left'",
        "topics.grasps='/pugs/grasps?x'",
    ],
)
def test_keys_that_zenoh_would_refuse_are_config_errors(override: str) -> None:
    with pytest.raises(ConfigError, match="is not a usable zenoh key"):
        load_config_dict({}, [override])


@pytest.mark.parametrize("key", ["a//b", "/pugs/**", "a/**/**", "pugs/grasps?x", ""])
def test_record_keys_zenoh_would_refuse_are_config_errors(key: str, tmp_path: Path) -> None:
    """They were refused only when the recorder subscribed: the daemon then ran unrecorded."""
    with pytest.raises(ConfigError, match=r"record\.keys: .* is not a zenoh key expression \(Invalid Key"):
        load_config_dict({"record": {"keys": ["*/pugs/**", key]}})
    f = tmp_path / "r.toml"
    f.write_text(f"[record]\nkeys = [{key!r}]\n".replace("'", '"'))
    assert main(["check-config", str(f)]) == 1
    wildcards = ["*/pugs/**", "0/stereo/*/image_raw/**", "**"]
    assert load_config_dict({"record": {"keys": wildcards}}).record.keys == tuple(wildcards)


@pytest.mark.parametrize(
    ("override", "given"),
    [
        ("zenoh.listen.endpoints=tcp/127.0.0.1:21447", "tcp/127.0.0.1:21447"),  # the brackets forgotten
        ("zenoh.connect.endpoints=[tcp/127.0.0.1:21447]", "[tcp/127.0.0.1:21447]"),  # the quotes forgotten
    ],
)
def test_an_endpoint_string_instead_of_a_list_says_so(override: str, given: str) -> None:
    """It was refused as "no listen or connect endpoint" / "must be given explicitly (... unless
    allow_non_loopback)", which pointed at the safety switch instead of the missing brackets."""
    what = override.split(".")[1]
    with pytest.raises(ConfigError) as err:
        load_config_dict({}, [override])
    assert str(err.value) == (
        f'zenoh.{what}.endpoints must be a list, e.g. ["tcp/127.0.0.1:7447"] (got the string {given!r}; '
        f"on a command line: --set 'zenoh.{what}.endpoints=[\"tcp/127.0.0.1:21447\"]')"
    )
    listed = load_config_dict({}, [f'zenoh.{what}.endpoints=["tcp/127.0.0.1:21447"]'])
    assert listed.zenoh[what]["endpoints"] == ["tcp/127.0.0.1:21447"]


def test_check_config_warns_of_a_recording_directory_it_cannot_use(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon then serves without recording; check-config said ok without a word."""
    import os

    ref = str(ROOT / "config" / "pugsd.toml")
    (tmp_path / "afile").write_text("x")
    under_a_file = tmp_path / "afile" / "rec"
    assert main(["check-config", ref, "--set", "record.enabled=true",
                 "--set", f'record.directory="{under_a_file}"']) == 0  # fmt: skip
    assert capsys.readouterr().err == (
        f"{ref}: warning: record.directory = {str(under_a_file)!r}: {str(tmp_path / 'afile')!r} is not a "
        "directory; the daemon will run without recording\n"
    )
    new = tmp_path / "new" / "rec"  # created by the recorder: fine

    def enabled_at(path: Path) -> list[str]:
        return ["--set", "record.enabled=true", "--set", f'record.directory="{path}"']

    assert main(["check-config", ref, *enabled_at(new)]) == 0
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(os, "access", lambda path, mode: False)  # as a user without write access
    assert main(["check-config", ref, *enabled_at(new)]) == 0
    assert capsys.readouterr().err == (
        f"{ref}: warning: record.directory = {str(new)!r}: this user cannot create it "
        f"({str(tmp_path)!r} is not writable); the daemon will run without recording\n"
    )
    assert main(["check-config", ref, "--set", f'record.directory="{new}"']) == 0  # not enabled: no word
    assert capsys.readouterr().err == ""


def test_usable_keys_are_accepted() -> None:
    cfg = load_config_dict(
        {}, ["daemon.prefix=robot1/pugs", "daemon.node_name=bow", "topics.pose=/nav/pose/"]
    )
    assert (cfg.daemon.prefix, cfg.daemon.node_name, cfg.topics.pose) == ("robot1/pugs", "bow", "/nav/pose/")


def test_the_global_log_level_overrides_the_daemons_for_run() -> None:
    from pugsd.cli import build_parser
    from pugsd.config import load_config_dict
    from pugsd.daemon.cli import run_log_level

    cfg = load_config_dict({"daemon": {"log_level": "info"}})
    assert run_log_level(build_parser().parse_args(["run"]), cfg) == "info"
    assert run_log_level(build_parser().parse_args(["--log-level", "debug", "run"]), cfg) == "debug"
    with pytest.raises(SystemExit):  # a typo is an argument error, not a silent WARNING
        build_parser().parse_args(["--log-level", "verbose", "run"])


def test_the_global_log_level_applies_to_demo(monkeypatch: pytest.MonkeyPatch) -> None:
    """``pugsd --log-level info demo`` shows the daemon's info lines (it was reset to warning)."""
    import logging

    import pugsd.daemon.demo
    from pugsd.cli import main

    levels: list[int] = []
    monkeypatch.setattr(pugsd.daemon.demo, "run_demo", lambda **kw: levels.append(logging.getLogger().level))
    root = logging.getLogger()
    saved = (root.level, list(root.handlers))
    try:
        assert main(["--log-level", "info", "demo"]) == 0
        assert main(["demo"]) == 0
    finally:
        root.handlers[:] = saved[1]
        root.setLevel(saved[0])
    assert levels == [logging.INFO, logging.WARNING]


def test_check_config_warns_when_the_approach_check_is_shorter_than_the_arms_stand_off(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The proposer checks the straight approach grasp.approach_check_m back; the arm starts it
    arm.motion.pregrasp_distance_m back. Both valid alone, so a warning, not a refusal."""
    f = tmp_path / "arm.toml"
    f.write_text("[arm]\nenabled = true\n[grasp]\napproach_check_m = 0.12\n")
    assert main(["check-config", str(f)]) == 0
    err = capsys.readouterr().err
    assert "warning: grasp.approach_check_m = 0.12 m is shorter than" in err
    assert "arm.motion.pregrasp_distance_m = 0.2 m" in err and "first 0.08 m" in err
    for text in (
        "[arm]\nenabled = true\n",  # the defaults agree (0.2 m, 0.2 m)
        "[grasp]\napproach_check_m = 0.12\n",  # no arm: nothing approaches
        "[arm]\nenabled = true\n[arm.motion]\npregrasp_distance_m = 0.1\n[grasp]\napproach_check_m = 0.12\n",
    ):
        f.write_text(text)
        assert main(["check-config", str(f)]) == 0
        assert "warning" not in capsys.readouterr().err, text


def test_config_sections_declare_only_types_the_loader_checks() -> None:
    """Every field of every section is a section, ``tuple[X, ...]``, dict, float, int, bool or str,
    and opt() refuses mutable defaults (a shared list would leak between configs)."""
    import dataclasses
    import typing

    from pugsd.config import PugsdConfig
    from pugsd.configbase import opt

    def walk(cls: type) -> None:
        for name, tp in typing.get_type_hints(cls).items():
            if dataclasses.is_dataclass(tp):
                walk(tp)  # type: ignore[arg-type]
                continue
            origin = typing.get_origin(tp)
            if origin is tuple:
                assert typing.get_args(tp)[1] is Ellipsis, (cls, name, tp)
            else:
                assert tp in (dict, float, int, bool, str) or origin is dict, (cls, name, tp)

    walk(PugsdConfig)
    with pytest.raises(TypeError, match="default_factory"):
        opt([1.0], "a list")


@pytest.mark.parametrize("override", ["daemon.grasp_rate_hz=1" + "0" * 400, "grasp.gamma=-1" + "0" * 400])
def test_an_integer_too_large_for_a_float_key_is_a_config_error(
    override: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """TOML integers are unbounded in tomllib: one too large for a float was an OverflowError
    traceback from check-config, dump-config and run, not a one-line error."""
    key = override.split("=")[0]
    with pytest.raises(ConfigError, match=f"{key}: expected a finite number"):
        load_config_dict({}, [override])
    assert main(["dump-config", "--set", override]) == 1
    assert f"pugsd dump-config: error: {key}: expected a finite number" in capsys.readouterr().err
    # beyond Python's 4300-digit limit tomllib refuses the number: a bare word, then a type error
    with pytest.raises(ConfigError, match=r"daemon\.markers_top_k: expected an integer, got str"):
        load_config_dict({}, ["daemon.markers_top_k=" + "1" * 5000])


def test_an_unreadable_config_file_is_a_config_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A directory or a file that is not UTF-8 (a typo in the unit's path, a binary file) was an
    IsADirectoryError or UnicodeDecodeError traceback, not a one-line error."""
    binary = tmp_path / "pugsd.toml"
    binary.write_bytes(b"\xff\xfe[daemon]\n")
    huge = tmp_path / "huge.toml"
    huge.write_text("[daemon]\nmarkers_top_k = " + "1" * 5000 + "\n")
    for path, message in ((tmp_path, "cannot read"), (binary, "not valid TOML"), (huge, "not valid TOML")):
        with pytest.raises(ConfigError, match=message):
            load_config(path)
        assert main(["check-config", str(path)]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"pugsd check-config: error: {path}: ") and err.count("\n") == 1, err


def test_offline_set_wins_over_the_sequences_own_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    """``pugsd offline --trajectory noisy_partial --set stereo.sigma_d2_m2=0.001``: the user's
    ``--set`` wins over the sequence's ``core_overrides``, as in ``pugsd evaluate``."""
    import types

    import pugsd.pipeline_factory
    import pugsd.sim
    from pugsd.cli import main

    seen: list[float] = []

    class Stop(Exception):
        pass

    def fake_pipeline(core: PugsdConfig, seed: int = 0) -> None:
        seen.append(core.stereo.sigma_d2_m2)
        raise Stop

    seq = types.SimpleNamespace(core_overrides={"stereo.sigma_d2_m2": 0.01})
    monkeypatch.setattr(pugsd.sim, "make_sequence", lambda *a, **kw: seq)
    monkeypatch.setattr(pugsd.pipeline_factory, "make_pipeline", fake_pipeline)
    for argv in (["offline"], ["offline", "--set", "stereo.sigma_d2_m2=0.002"]):
        with pytest.raises(Stop):
            main(argv)
    assert seen == [0.01, 0.002]


@pytest.mark.parametrize(
    ("overrides", "keys"),
    [
        (["svgp.device=cuda"], ["svgp.device"]),
        (["fof.query_device=cuda"], ["fof.query_device"]),
        (["svgp.device=cuda", "fof.query_device=cuda"], ["svgp.device", "fof.query_device"]),
    ],
)
def test_check_config_refuses_cuda_settings_on_a_machine_without_cuda(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], overrides: list[str], keys: list[str]
) -> None:
    """`pugsd run` refuses these when it builds the model; check-config (the unit's ExecStartPre)
    used to print ok for them."""
    import torch

    from pugsd.core.fof import FofStore
    from pugsd.core.predictive import OccupancySVGP

    ref = str(ROOT / "config" / "pugsd.toml")
    args = [a for o in overrides for a in ("--set", o)]
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = load_config(ref, overrides)
    builders = {"svgp.device": lambda: OccupancySVGP(cfg.svgp), "fof.query_device": lambda: FofStore(cfg.fof)}
    for key in keys:  # what `pugsd run` meets when it builds the model
        with pytest.raises(ConfigError, match="no CUDA device"):
            builders[key]()
    assert main(["check-config", ref, *args]) == 1
    err = capsys.readouterr().err
    for key in keys:
        assert f"{key} = cuda, but torch sees no CUDA device" in err
    assert err.count("no CUDA device") == len(keys)
    assert main(["check-config", ref, "--set", "svgp.device=auto"]) == 0
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert main(["check-config", ref, *args]) == 0


@pytest.mark.parametrize(
    "key",
    ["num_disparities", "min_disparity", "speckle_window_size", "speckle_range", "disp12_max_diff"],
)
def test_the_sgbm_settings_are_bounded_where_opencv_still_takes_them(key: str) -> None:
    """OpenCV's SGBM parameters are C ints: stereo.speckle_range = 2^40 passed check-config and
    every frame then failed with ValueError("integer won't fit into a C int")."""
    from pugsd.core.camera import PinholeCamera, StereoRig
    from pugsd.core.stereo import StereoDepth

    field = {f.name: f for f in dataclasses.fields(PugsdConfig().stereo)}[key]
    top = field.metadata["le"]
    cfg = load_config_dict({"stereo": {key: top}})
    rig = StereoRig(PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480), 0.1)
    StereoDepth(cfg.stereo)._matcher(1, rig)  # the largest accepted value reaches OpenCV
    with pytest.raises(ConfigError, match=rf"stereo\.{key}: .* is above the maximum"):
        load_config_dict({"stereo": {key: top + 1}})
    with pytest.raises(ConfigError, match=rf"stereo\.{key}"):
        load_config_dict({"stereo": {key: 1 << 40}})


@pytest.mark.parametrize("path", ["", "/nonexistent/grasp-net.pt"])
def test_check_config_refuses_a_missing_torchscript_model(
    path: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`pugsd run` refuses it when it builds the pipeline; check-config used to print ok for it."""
    ref = str(ROOT / "config" / "pugsd.toml")
    sets = ["--set", 'grasp.proposer="torchscript"', "--set", f'grasp.model_path="{path}"']
    assert main(["check-config", ref, *sets]) == 1
    err = capsys.readouterr().err
    assert ("grasp.model_path is empty" if not path else f"no TorchScript model at {path}") in err


@pytest.mark.parametrize("text", ["grasp.top_k=3\ngrasp.gamma=9", "grasp.top_k=3\n[daemon]\nprefix='x'"])
def test_a_value_with_a_second_toml_statement_is_refused(text: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_override(text)
    assert str(exc.value) == f"override {text!r}: VALUE must be a single TOML value"


def test_a_single_value_with_a_comment_still_loads() -> None:
    assert parse_override("grasp.top_k=3 # three") == ("grasp.top_k", 3)


@pytest.mark.parametrize("key", ["fof.k_neighbours", "svgp.seed", "queues.stereo"])
@pytest.mark.parametrize("value", [True, False])
def test_a_boolean_is_not_an_integer(key: str, value: bool) -> None:
    """Python's bool is an int: ``k_neighbours = true`` would load as 1 without the check."""
    section, name = key.split(".")
    with pytest.raises(ConfigError, match=rf"{section}\.{name}: expected an integer, got bool"):
        load_config_dict({section: {name: value}})


def test_the_depth_band_must_not_be_empty() -> None:
    with pytest.raises(ConfigError, match=r"stereo\.max_depth_m: must exceed min_depth_m"):
        load_config_dict({"stereo": {"min_depth_m": 1.0, "max_depth_m": 1.0}})
    cfg = load_config_dict({"stereo": {"min_depth_m": 1.0, "max_depth_m": 1.001}})
    assert cfg.stereo.max_depth_m == 1.001


@pytest.mark.parametrize("m", [1, 7])
def test_num_inducing_is_zero_or_at_least_eight(m: int) -> None:
    with pytest.raises(ConfigError, match=rf"svgp\.num_inducing: 0 \(auto\) or at least 8, got {m}"):
        load_config_dict({"svgp": {"num_inducing": m}})
    assert load_config_dict({"svgp": {"num_inducing": 8}}).svgp.num_inducing == 8
    assert load_config_dict({"svgp": {"num_inducing": 0}}).svgp.num_inducing == 0


# (dotted key, kind, bound): kind ge/le are inclusive, gt/lt exclusive
BOUNDS: list[tuple[str, str, float]] = [
    ("stereo.downsample", "ge", 1),
    ("stereo.downsample", "le", 16),
    ("stereo.num_disparities", "ge", 0),
    ("stereo.num_disparities", "le", 65520),
    ("stereo.min_disparity", "ge", 0),
    ("stereo.min_disparity", "le", 65535),
    ("stereo.block_size", "ge", 1),
    ("stereo.block_size", "le", 31),
    ("stereo.uniqueness_ratio", "ge", 0),
    ("stereo.uniqueness_ratio", "le", 100),
    ("stereo.speckle_window_size", "ge", 0),
    ("stereo.speckle_window_size", "le", 2147483647),
    ("stereo.speckle_range", "ge", 0),
    ("stereo.speckle_range", "le", 65535),
    ("stereo.disp12_max_diff", "ge", -1),
    ("stereo.disp12_max_diff", "le", 65535),
    ("stereo.min_depth_m", "gt", 0.0),
    ("stereo.max_depth_m", "gt", 0.0),
    ("stereo.sigma_d2_m2", "gt", 0.0),
    ("stereo.sigma_disp_px", "gt", 0.0),
    ("observation.regulariser_m", "gt", 0.0),
    ("observation.max_points_per_frame", "ge", 0),
    ("observation.max_points_per_frame", "le", 10000000),
    ("fof.k_neighbours", "ge", 1),
    ("fof.k_neighbours", "le", 64),
    ("fof.voxel_size_m", "gt", 0.0),
    ("fof.max_voxels", "ge", 100),
    ("fof.max_voxels", "le", 20000000),
    ("fof.query_workers", "ge", -1),
    ("fof.query_workers", "le", 1024),
    ("svgp.num_inducing", "ge", 0),
    ("svgp.num_inducing", "le", 5000),
    ("svgp.paper_num_inducing", "ge", 8),
    ("svgp.paper_num_inducing", "le", 5000),
    ("svgp.seed", "ge", 0),
    ("svgp.paper_lr", "gt", 0.0),
    ("svgp.paper_epochs", "ge", 1),
    ("svgp.batch_size", "ge", 16),
    ("svgp.batch_size", "le", 1000000),
    ("svgp.lengthscale_init_m", "gt", 0.0),
    ("svgp.noise_init", "gt", 0.0),
    ("svgp.ngd_lr", "gt", 0.0),
    ("svgp.ngd_lr", "le", 1.0),
    ("svgp.adam_lr", "gt", 0.0),
    ("svgp.inducing_lr", "ge", 0.0),
    ("svgp.steps_per_update", "ge", 1),
    ("svgp.replay_fraction", "ge", 0.0),
    ("svgp.replay_fraction", "le", 1.0),
    ("svgp.ready_min_steps", "ge", 0),
    ("svgp.ready_max_moved_fraction", "ge", 0.0),
    ("svgp.ready_max_moved_fraction", "le", 1.0),
    ("svgp.ready_move_window", "ge", 1),
    ("svgp.ready_move_window", "le", 100000),
    ("svgp.ready_elbo_slope", "gt", 0.0),
    ("svgp.ready_elbo_window", "ge", 1),
    ("svgp.ready_elbo_window", "le", 100000),
    ("svgp.spread_factor", "gt", 0.0),
    ("svgp.coverage_lengthscales", "gt", 0.0),
    ("svgp.predict_chunk", "ge", 256),
    ("svgp.predict_chunk", "le", 10000000),
    ("svgp.predict_chunk_cuda", "ge", 256),
    ("svgp.predict_chunk_cuda", "le", 10000000),
    ("cubature.alpha", "gt", 0.0),
    ("cubature.beta", "ge", 0.0),
    ("cubature.kappa", "ge", -2.9),
    ("cubature.max_query_points", "ge", 100),
    ("cubature.max_query_points", "le", 1000000),
    ("reconstruction.tsdf_voxel_m", "gt", 0.0),
    ("reconstruction.sdf_trunc_voxels", "gt", 0.0),
    ("reconstruction.block_count", "ge", 100),
    ("reconstruction.block_count", "le", 400000),
    ("reconstruction.sample_points", "ge", 100),
    ("reconstruction.sample_points", "le", 10000000),
    ("reconstruction.outlier_nb_neighbors", "ge", 1),
    ("reconstruction.outlier_nb_neighbors", "le", 1000),
    ("reconstruction.outlier_std_ratio", "gt", 0.0),
    ("freespace.voxel_m", "gt", 0.0),
    ("freespace.voxel_m", "le", 1.0),
    ("freespace.margin_m", "ge", 0.0),
    ("freespace.margin_m", "le", 1.0),
    ("freespace.extent_m", "gt", 0.0),
    ("freespace.extent_m", "le", 5.0),
    ("freespace.background_range_m", "ge", 0.0),
    ("freespace.background_range_m", "le", 100.0),
    ("freespace.max_blocks", "ge", 1),
    ("freespace.max_blocks", "le", 10_000_000),
    ("grasp.gamma", "ge", 0.0),
    ("grasp.gamma", "le", 1e12),
    ("grasp.unknown_weight", "ge", 0.0),
    ("grasp.unknown_weight", "le", 1e6),
    ("grasp.unknown_decay_m", "gt", 0.0),
    ("grasp.unknown_decay_m", "le", 10.0),
    ("grasp.swept_step_m", "gt", 0.0),
    ("grasp.swept_step_m", "le", 0.5),
    ("grasp.threads", "ge", 1),
    ("grasp.threads", "le", 64),
    ("grasp.single_contact_max_contacts", "ge", 1),
    ("grasp.single_contact_max_contacts", "le", 100_000),
    ("grasp.single_contact_face_deg", "gt", 0.0),
    ("grasp.single_contact_face_deg", "lt", 90.0),
    ("grasp.single_contact_voxel_m", "ge", 0.0),
    ("grasp.single_contact_voxel_m", "le", 0.05),
    ("grasp.single_contact_approaches", "ge", 1),
    ("grasp.single_contact_approaches", "le", 64),
    ("grasp.single_contact_rolls", "ge", 1),
    ("grasp.single_contact_rolls", "le", 64),
    ("grasp.top_k", "ge", 1),
    ("grasp.top_k", "le", 10000),
    ("grasp.thin_distance_m", "ge", 0.0),
    ("grasp.normal_radius_m", "gt", 0.0),
    ("grasp.friction_cone_deg", "gt", 0.0),
    ("grasp.friction_cone_deg", "lt", 90.0),
    ("grasp.num_orientations", "ge", 1),
    ("grasp.num_orientations", "le", 360),
    ("grasp.max_contacts", "ge", 10),
    ("grasp.max_contacts", "le", 1000000),
    ("grasp.min_support", "ge", 1),
    ("grasp.partner_radius_m", "gt", 0.0),
    ("grasp.clearance_m", "ge", 0.0),
    ("grasp.approach_check_m", "ge", 0.0),
    ("grasp.gripper.max_width_m", "gt", 0.0),
    ("grasp.gripper.min_width_m", "ge", 0.0),
    ("grasp.gripper.depth_m", "gt", 0.0),
    ("grasp.gripper.finger_length_m", "gt", 0.0),
    ("grasp.gripper.finger_width_m", "gt", 0.0),
    ("grasp.gripper.finger_thickness_m", "gt", 0.0),
    ("grasp.gripper.palm_depth_m", "gt", 0.0),
    ("grasp.gripper.palm_width_m", "gt", 0.0),
    ("daemon.grasp_rate_hz", "gt", 0.0),
    ("daemon.pause_publish_s", "ge", 0.0),
    ("daemon.status_rate_hz", "gt", 0.0),
    ("daemon.pose_wait_s", "ge", 0.0),
    ("daemon.side_image_wait_s", "ge", 0.0),
    ("daemon.shutdown_timeout_s", "gt", 0.0),
    ("daemon.torch_threads", "ge", 0),
    ("daemon.torch_threads", "le", 1024),
    ("daemon.blas_threads", "ge", 0),
    ("daemon.blas_threads", "le", 1024),
    ("daemon.malloc_arena_max", "ge", 0),
    ("daemon.max_frame_rate_hz", "ge", 0.0),
    ("daemon.train_steps_per_frame", "ge", 0),
    ("daemon.idle_train_steps", "ge", 0),
    ("daemon.min_train_interval_s", "gt", 0.0),
    ("daemon.idle_train_s", "ge", 0.0),
    ("daemon.idle_rate_decay_steps", "ge", 0),
    ("daemon.pose_max_gap_s", "gt", 0.0),
    ("daemon.pose_max_gap_s", "le", 3600.0),
    ("daemon.pose_publisher_hold_s", "ge", 0.0),
    ("daemon.pose_std_translation_m", "ge", 0.0),
    ("daemon.pose_std_rotation_rad", "ge", 0.0),
    ("daemon.markers_top_k", "ge", 0),
    ("daemon.markers_top_k", "le", 10000),
    ("daemon.cloud_interval_s", "ge", 0.0),
    ("daemon.stall_timeout_s", "gt", 0.0),
    ("daemon.input_stale_s", "ge", 0.0),
    ("daemon.max_consecutive_failures", "ge", 1),
    ("daemon.ingress_limit", "ge", 1),
    ("daemon.ingress_limit", "le", 65536),
    ("daemon.ingress_max_bytes", "ge", 1048576),
    ("daemon.ingress_max_bytes", "le", 17179869184),
    ("daemon.max_image_bytes", "ge", 4096),
    ("daemon.max_image_bytes", "le", 1073741824),
    ("daemon.max_pose_std_translation_m", "gt", 0.0),
    ("daemon.max_pose_std_translation_m", "le", 1000000.0),
    ("daemon.max_pose_std_rotation_rad", "gt", 0.0),
    ("daemon.max_pose_std_rotation_rad", "le", 1000.0),
    ("topics.domain_id", "ge", 0),
    ("topics.domain_id", "le", 232),
    ("queues.stereo", "ge", 1),
    ("queues.stereo", "le", 64),
    ("queues.depth", "ge", 1),
    ("queues.depth", "le", 64),
    ("queues.commands", "ge", 1),
    ("queues.commands", "le", 1024),
    ("queues.record", "ge", 1),
    ("queues.record", "le", 1048576),
    ("queues.pose_wait", "ge", 1),
    ("queues.pose_wait", "le", 1024),
    ("queues.unpaired", "ge", 1),
    ("queues.unpaired", "le", 1024),
    ("queues.poses", "ge", 2),
    ("queues.poses", "le", 1048576),
    ("queues.side_images", "ge", 1),
    ("queues.side_images", "le", 1024),
    ("queues.buffered_bytes", "ge", 1048576),
    ("queues.buffered_bytes", "le", 17179869184),
    ("record.chunk_size_bytes", "ge", 4096),
    ("record.chunk_size_bytes", "le", 1073741824),
    ("record.flush_interval_s", "gt", 0.0),
    ("record.rotate_size_bytes", "ge", 1048576),
    ("record.rotate_duration_s", "gt", 0.0),
    ("record.max_total_bytes", "ge", 0),
    ("record.queue_max_bytes", "ge", 1048576),
    ("record.queue_max_bytes", "le", 17179869184),
]

CHOICES: dict[str, tuple[str, ...]] = {
    "stereo.mode": ("sgbm", "sgbm_3way", "hh"),
    "stereo.noise_mode": ("fixed", "disparity"),
    "observation.covariance_form": ("rotated", "paper_literal"),
    "fof.target_scale": ("max", "p99"),
    "fof.fused_mean": ("query", "information"),
    "fof.query_device": ("auto", "cpu", "cuda"),
    "svgp.kernel": ("rbf", "matern52"),
    "svgp.variance": ("latent", "observed"),
    "svgp.device": ("cpu", "cuda", "auto"),
    "svgp.dtype": ("float32", "float64"),
    "svgp.inducing_policy": ("spread", "coverage"),
    "svgp.output_units": ("density", "normalised"),
    "cubature.variance_form": ("total", "paper_literal"),
    "grasp.proposer": ("single_contact", "antipodal", "torchscript"),
    "grasp.uncertainty": ("swept", "contact"),
    "daemon.log_level": ("debug", "info", "warning", "error"),
    "topics.key_style": ("rmw_zenoh", "ros2dds"),
    "topics.hash_mode": ("rihs01", "humble"),
    "topics.ros_graph_tokens": ("auto", "on", "off"),
    "topics.pose_type": ("PoseWithCovarianceStamped", "PoseStamped", "Odometry"),
    "record.compression": ("zstd", "lz4", "none"),
}

SECTIONS = ("stereo", "observation", "fof", "svgp", "cubature", "reconstruction", "freespace", "grasp",
            "daemon", "topics", "queues", "record")  # fmt: skip

# keys whose accepted edge needs a companion setting to pass the section's cross-key check:
# max_depth_m must exceed min_depth_m > 0, so its smallest accepted value is two steps above 0
CONTEXT: dict[str, dict[str, Any]] = {
    "stereo.max_depth_m": {"min_depth_m": 5e-324},
}
ACCEPT_ABOVE: dict[str, float] = {"stereo.max_depth_m": 1e-323}


def _nested(dotted: str, value: Any) -> dict[str, Any]:
    *head, last = dotted.split(".")
    data: dict[str, Any] = {last: value}
    for part in reversed(head):
        data = {part: data}
    return data


def _load(dotted: str, value: Any) -> Any:
    data = _nested(dotted, value)
    if dotted in CONTEXT:
        section = dotted.split(".")[0]
        data[section].update(CONTEXT[dotted])
    cfg = load_config_dict(data)
    obj: Any = cfg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def _error(data: dict[str, Any], overrides: tuple[str, ...] = ()) -> str:
    with pytest.raises(ConfigError) as exc:
        load_config_dict(data, list(overrides))
    return str(exc.value)


def _walk_meta(obj: Any, path: str, out: dict[str, dict[str, Any]]) -> None:
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            _walk_meta(v, f"{path}.{f.name}", out)
        else:
            out[f"{path}.{f.name}"] = dict(f.metadata)


def _all_meta() -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    cfg = PugsdConfig()
    for s in SECTIONS:
        _walk_meta(getattr(cfg, s), s, out)
    return out


def test_the_tables_here_list_every_bound_and_choice_of_these_sections() -> None:
    """A bound or choice added, dropped or renamed in the source shows up here first."""
    meta = _all_meta()
    kinds = ("ge", "gt", "le", "lt")
    declared = {(k, kind) for k, m in meta.items() for kind in kinds if m.get(kind) is not None}
    assert declared == {(k, kind) for k, kind, _ in BOUNDS}
    assert {k for k, m in meta.items() if m.get("choices") is not None} == set(CHOICES)


@pytest.mark.parametrize(("key", "kind", "bound"), BOUNDS, ids=[f"{k}-{kind}" for k, kind, _ in BOUNDS])
def test_each_bound_on_both_sides_with_its_exact_message(key: str, kind: str, bound: float) -> None:
    down: float
    up: float
    if isinstance(bound, int):
        down, up = bound - 1, bound + 1
    else:  # the neighbouring floats
        down, up = math.nextafter(bound, -math.inf), math.nextafter(bound, math.inf)
    if kind == "ge":
        assert _load(key, bound) == bound
        assert _error(_nested(key, down)) == f"{key}: {down} is below the minimum {bound}"
    elif kind == "le":
        assert _load(key, bound) == bound
        assert _error(_nested(key, up)) == f"{key}: {up} is above the maximum {bound}"
    elif kind == "gt":
        up = ACCEPT_ABOVE.get(key, up)
        assert _load(key, up) == up
        assert _error(_nested(key, bound)) == f"{key}: {bound} must be greater than {bound}"
    else:  # lt
        assert _load(key, down) == down
        assert _error(_nested(key, bound)) == f"{key}: {bound} must be less than {bound}"


@pytest.mark.parametrize("key", sorted(CHOICES))
def test_each_choice_loads_and_anything_else_is_refused_with_the_list(key: str) -> None:
    for choice in CHOICES[key]:
        assert _load(key, choice) == choice
    assert _error(_nested(key, "bogus")) == f"{key}: 'bogus' is not one of {list(CHOICES[key])}"


# the sections' own checks across keys


def test_block_size_must_be_odd() -> None:
    assert _error({"stereo": {"block_size": 4}}) == "stereo.block_size: must be odd, got 4"
    assert _error({"stereo": {"block_size": 30}}) == "stereo.block_size: must be odd, got 30"
    assert load_config_dict({"stereo": {"block_size": 3}}).stereo.block_size == 3


@pytest.mark.parametrize("n", [8, 24, 65512 + 4])
def test_num_disparities_must_be_a_multiple_of_16(n: int) -> None:
    assert _error({"stereo": {"num_disparities": n}}) == (
        "stereo.num_disparities: must be 0 (auto) or a multiple of 16"
    )


@pytest.mark.parametrize("n", [0, 16, 32, 65520])
def test_a_multiple_of_16_disparities_loads(n: int) -> None:
    assert load_config_dict({"stereo": {"num_disparities": n}}).stereo.num_disparities == n


def test_the_depth_band_check_is_strict_and_its_message_exact() -> None:
    assert _error({"stereo": {"min_depth_m": 2.0, "max_depth_m": 1.0}}) == (
        "stereo.max_depth_m: must exceed min_depth_m"
    )
    assert _error({"stereo": {"max_depth_m": 0.2}}) == "stereo.max_depth_m: must exceed min_depth_m"
    assert load_config_dict({"stereo": {"max_depth_m": math.nextafter(0.2, 1.0)}}).stereo.max_depth_m > 0.2


# [daemon] and [topics]


_KEY_MESSAGE = "is not a usable zenoh key (non-empty '/'-separated chunks, no '*', '$', '?' or '#')"


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("daemon.prefix", "pugs$x"),
        ("daemon.prefix", "pugs#x"),
        ("daemon.prefix", "/pugs"),  # the prefix is not stripped: a leading '/' is an empty chunk
        ("daemon.node_name", "a/"),
        ("daemon.node_name", "a?b"),
        ("topics.status", "/pugs/$status"),
        ("topics.cloud", "/pugs/cl#oud"),
        ("topics.depth", "/"),  # stripped to nothing
        ("topics.mask", "//"),
    ],
)
def test_a_key_with_a_reserved_character_or_empty_chunk_is_refused_exactly(key: str, value: str) -> None:
    assert _error(_nested(key, value)) == f"{key}: {value!r} {_KEY_MESSAGE}"


def test_topics_but_not_the_prefix_have_their_outer_slashes_stripped() -> None:
    cfg = load_config_dict({"topics": {"status": "//pugs/status//", "mask": "mask"}})
    assert (cfg.topics.status, cfg.topics.mask) == ("//pugs/status//", "mask")
    # the choice-valued keys of [topics] are no topics: their values are not checked as keys
    assert load_config_dict({"topics": {"pose_type": "Odometry"}}).topics.pose_type == "Odometry"


def test_a_section_built_directly_runs_the_same_key_checks() -> None:
    with pytest.raises(ConfigError, match=r"^prefix: 'a\*' is not a usable zenoh key"):
        DaemonConfig(prefix="a*")
    with pytest.raises(ConfigError, match=r"^grasps: '/x//y' is not a usable zenoh key"):
        TopicsConfig(grasps="/x//y")


@pytest.mark.parametrize(
    ("xyz", "message"),
    [
        ((math.nan, 0.0, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [nan, 0.0, 0.0]"),
        ((0.0, math.inf, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [0.0, inf, 0.0]"),
        ((0.0, 0.0, 0.0, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [0.0, 0.0, 0.0, 0.0]"),
    ],
)
def test_the_mount_translation_must_be_three_finite_values(xyz: tuple[float, ...], message: str) -> None:
    """Built directly (the loader refuses nan first): the section's own check still holds."""
    with pytest.raises(ConfigError) as exc:
        DaemonConfig(T_B_C_xyz_m=xyz)
    assert str(exc.value) == message


@pytest.mark.parametrize(
    ("q", "message"),
    [
        ((0.0, 0.0, math.nan, 1.0), "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, nan, 1.0]"),
        ((0.0, 0.0, 1.0), "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, 1.0]"),
        (
            (0.0, 0.0, 0.0, 0.0, 1.0),
            "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, 0.0, 0.0, 1.0]",
        ),
    ],
)
def test_the_mount_rotation_must_be_four_finite_values(q: tuple[float, ...], message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        DaemonConfig(T_B_C_quat_xyzw=q)
    assert str(exc.value) == message


@pytest.mark.parametrize("w", [1.0011, 0.9989])
def test_a_quaternion_off_unit_norm_by_more_than_1e_3_is_refused(w: float) -> None:
    assert _error({"daemon": {"T_B_C_quat_xyzw": [0.0, 0.0, 0.0, w]}}) == (
        f"daemon.T_B_C_quat_xyzw: [0.0, 0.0, 0.0, {w}] is not a unit quaternion (norm {w:.6g}); "
        "the order is x y z w"
    )


@pytest.mark.parametrize("w", [1.0009, 0.9991])
def test_a_quaternion_within_1e_3_of_unit_norm_loads_as_given(w: float) -> None:
    cfg = load_config_dict({"daemon": {"T_B_C_quat_xyzw": [0.0, 0.0, 0.0, w]}})
    assert cfg.daemon.T_B_C_quat_xyzw == (0.0, 0.0, 0.0, w)  # not normalised


def test_the_mount_matrix_is_none_only_for_the_identity() -> None:
    assert DaemonConfig().T_B_C is None
    T = DaemonConfig(T_B_C_xyz_m=(0.1, -0.2, 0.3)).T_B_C
    assert T is not None
    np.testing.assert_array_equal(T, [[1, 0, 0, 0.1], [0, 1, 0, -0.2], [0, 0, 1, 0.3], [0, 0, 0, 1]])
    s = math.sqrt(0.5)
    T = DaemonConfig(T_B_C_quat_xyzw=(0.0, 0.0, s, s)).T_B_C  # 90 deg about z, no translation
    assert T is not None
    np.testing.assert_allclose(T, [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-15)


def test_graph_tokens_on_refuses_a_topic_ros_would_not_take_in_the_topics_section() -> None:
    assert _error({"topics": {"ros_graph_tokens": "on", "status": "/pugs/st%tus"}}) == (
        "topics: ros_graph_tokens = 'on', but topics.status: '/pugs/st%tus' is not a fully qualified "
        "ROS 2 topic name ('/'-separated tokens of letters, digits and '_', none starting with a digit)"
    )
    assert _error({"topics": {"ros_graph_tokens": "on", "key_style": "ros2dds"}}) == (
        "topics: ros_graph_tokens = 'on', but key_style is 'ros2dds' (graph tokens are rmw_zenoh's)"
    )
    # off and auto accept the same names
    for mode in ("off", "auto"):
        assert load_config_dict({"topics": {"ros_graph_tokens": mode, "status": "/pugs/st%tus"}})


# config_warnings


def _approach_warning(check: float, pre: float) -> str:
    return (
        f"grasp.approach_check_m = {check:g} m is shorter than arm.motion.pregrasp_distance_m = {pre:g} m: "
        "the arm approaches in a straight line from its stand-off, and the first "
        f"{pre - check:.3g} m of that line (from the stand-off) are not checked against the cloud"
    )


_NODE_WARNING = (
    "topics.ros_graph_tokens = 'auto' declares no ROS graph tokens, so ros2 node list and ros2 topic "
    "list will not show pugsd: daemon.node_name: 'pugs-1' is not a ROS 2 node name (letters, digits "
    "and '_', not starting with a digit)"
)


def test_config_warnings_exact_text_and_order() -> None:
    cfg = load_config_dict(
        {"arm": {"enabled": True}, "grasp": {"approach_check_m": 0.05}, "daemon": {"node_name": "pugs-1"}}
    )
    assert config_warnings(cfg) == [_approach_warning(0.05, 0.2), _NODE_WARNING]
    assert config_warnings(PugsdConfig()) == []


def test_the_approach_warning_rounds_the_unchecked_length_to_three_digits() -> None:
    arm = {"enabled": True, "motion": {"pregrasp_distance_m": 0.3}}
    cfg = load_config_dict({"arm": arm, "grasp": {"approach_check_m": 0.1234}})
    (w,) = config_warnings(cfg)
    assert w == _approach_warning(0.1234, 0.3)
    assert "0.1234 m is shorter than" in w and "= 0.3 m:" in w and "the first 0.177 m" in w


def test_the_approach_warning_needs_a_strictly_shorter_check() -> None:
    base = {"arm": {"enabled": True, "motion": {"pregrasp_distance_m": 0.15}}}
    assert config_warnings(load_config_dict({**base, "grasp": {"approach_check_m": 0.15}})) == []
    assert len(config_warnings(load_config_dict({**base, "grasp": {"approach_check_m": 0.149}}))) == 1


@pytest.mark.parametrize(
    "topics",
    [
        {"ros_graph_tokens": "off"},
        {"key_style": "ros2dds"},  # tokens describe rmw_zenoh only: nothing is missed
        {"hash_mode": "humble"},
    ],
)
def test_no_graph_token_warning_where_tokens_are_not_expected(topics: dict[str, str]) -> None:
    cfg = load_config_dict({"topics": topics, "daemon": {"node_name": "pugs-1"}})
    assert config_warnings(cfg) == []


def test_a_topic_ros_refuses_is_warned_of_in_auto_mode() -> None:
    (w,) = config_warnings(load_config_dict({"topics": {"grasps": "/pugs/2grasps"}}))
    assert w.startswith("topics.ros_graph_tokens = 'auto' declares no ROS graph tokens, so ros2 node list")
    assert w.endswith(
        ": topics.grasps: '/pugs/2grasps' is not a fully qualified ROS 2 topic name "
        "('/'-separated tokens of letters, digits and '_', none starting with a digit)"
    )


def test_several_graph_token_problems_are_joined_with_semicolons() -> None:
    cfg = load_config_dict({"daemon": {"node_name": "pugs-1"}, "topics": {"grasps": "/pugs/2grasps"}})
    (w,) = config_warnings(cfg)
    assert "'pugs-1' is not a ROS 2 node name (letters, digits and '_', not starting with a digit); " \
        "topics.grasps: '/pugs/2grasps' is not" in w  # fmt: skip


# overrides


@pytest.mark.parametrize(
    ("text", "parsed"),
    [
        ("fof.k_neighbours=7", ("fof.k_neighbours", 7)),
        ("grasp.gamma=2.5", ("grasp.gamma", 2.5)),
        ("grasp.gamma=-1e-3", ("grasp.gamma", -1e-3)),
        ("daemon.log_json=true", ("daemon.log_json", True)),
        ("daemon.log_json = false ", ("daemon.log_json", False)),
        ("record.keys=['a/b', \"c\"]", ("record.keys", ["a/b", "c"])),
        (
            "zenoh.scouting={multicast = {enabled = false}}",
            ("zenoh.scouting", {"multicast": {"enabled": False}}),
        ),
        ("daemon.prefix='quoted'", ("daemon.prefix", "quoted")),
        ('daemon.prefix="true"', ("daemon.prefix", "true")),  # a quoted word stays a string
        ("daemon.prefix=two words", ("daemon.prefix", "two words")),  # not TOML: the raw text
        ("daemon.prefix=", ("daemon.prefix", "")),
        ("  grasp.top_k  =  3  ", ("grasp.top_k", 3)),
        ("fof=3", ("fof", 3)),  # one part is a key too (the loader then refuses the value)
    ],
)
def test_override_values_are_toml_or_the_bare_text(text: str, parsed: tuple[str, Any]) -> None:
    assert parse_override(text) == parsed


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("noequals", "override 'noequals': expected KEY=VALUE"),
        ("=3", "override '=3': expected section.key=VALUE"),
        ("daemon. .prefix=x", "override 'daemon. .prefix=x': expected section.key=VALUE"),
        (".prefix=x", "override '.prefix=x': expected section.key=VALUE"),
        ("daemon.prefix.=x", "override 'daemon.prefix.=x': expected section.key=VALUE"),
    ],
)
def test_a_malformed_override_is_refused_exactly(text: str, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_override(text)
    assert str(exc.value) == message


def test_an_override_into_a_value_that_is_no_table_names_both() -> None:
    assert _error({"fof": {"k_neighbours": 3}}, ("fof.k_neighbours.x=1",)) == (
        "fof.k_neighbours.x: k_neighbours is not a table"
    )
    assert _error({"fof": 3}, ("fof.k_neighbours=1",)) == "fof.k_neighbours: fof is not a table"
    # not set before: an empty table is made, and the loader refuses it by type
    assert _error({}, ("fof.k_neighbours.x=1",)) == "fof.k_neighbours: expected an integer, got dict"
    assert _error({}, ("fof=3",)) == "fof: expected a table, got int"


def test_overrides_apply_in_order_over_the_data_and_leave_it_unchanged() -> None:
    data = {"grasp": {"gamma": 1.0, "gripper": {"max_width_m": 0.2}}, "fof": {"k_neighbours": 5}}
    cfg = load_config_dict(data, ["grasp.gamma=2", "grasp.gripper.max_width_m=0.3", "grasp.gamma=3"])
    assert (cfg.grasp.gamma, cfg.grasp.gripper.max_width_m, cfg.fof.k_neighbours) == (3.0, 0.3, 5)
    assert data == {"grasp": {"gamma": 1.0, "gripper": {"max_width_m": 0.2}}, "fof": {"k_neighbours": 5}}


# files and the dump/load round trip


def test_load_config_file_errors_are_exact(tmp_path: Path) -> None:
    missing = tmp_path / "missing.toml"
    with pytest.raises(ConfigError) as exc:
        load_config(missing)
    assert str(exc.value) == f"{missing}: no such file"
    with pytest.raises(ConfigError) as exc:
        load_config(tmp_path)
    assert str(exc.value) == f"{tmp_path}: cannot read: Is a directory"
    binary = tmp_path / "b.toml"
    binary.write_bytes(b"[daemon]\n\xff\n")
    with pytest.raises(ConfigError) as exc:
        load_config(binary)
    assert str(exc.value) == f"{binary}: not valid TOML: not UTF-8 (byte 9)"
    bad = tmp_path / "bad.toml"
    bad.write_text("[daemon\n")
    with pytest.raises(ConfigError) as exc:
        load_config(str(bad))
    assert str(exc.value).startswith(f"{bad}: not valid TOML: ")


def test_load_config_reads_the_file_and_applies_overrides_over_it(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[grasp]\ngamma = 2.0\ntop_k = 4\n")
    cfg = load_config(f, ["grasp.top_k=6"])
    assert (cfg.grasp.gamma, cfg.grasp.top_k) == (2.0, 6)
    assert load_config(None, ["grasp.top_k=6"]).grasp.top_k == 6
    assert load_config() == PugsdConfig()


def test_a_non_default_config_round_trips_through_dump_and_load() -> None:
    overrides = [
        "stereo.block_size=7",
        "stereo.mode=hh",
        "observation.rotation_term=false",
        "svgp.ngd_lr=0.25",
        "cubature.kappa=-1.5",
        "grasp.gripper.palm_width_m=0.07",
        "grasp.model_path='/tmp/model \"x\".pt'",
        "daemon.T_B_C_xyz_m=[0.1, -0.2, 0.3]",
        "daemon.prefix=robot1/pugs",
        "record.keys=['a/b', 'c/**']",
        "topics.domain_id=42",
        "queues.poses=3",
        "zenoh.connect.endpoints=['tcp/127.0.0.1:7448']",
    ]
    cfg = load_config_dict({}, overrides)
    text = dump_config(cfg)
    assert text != dump_config()
    again = load_config_dict(tomllib.loads(text))
    assert again == cfg
    assert again.grasp.model_path == '/tmp/model "x".pt' and again.record.keys == ("a/b", "c/**")
    assert dump_config(again) == text


def test_core_of_takes_exactly_the_core_sections() -> None:
    cfg = load_config_dict({}, ["grasp.gamma=2", "fof.k_neighbours=3", "daemon.grasp_rate_hz=4"])
    core = core_of(cfg)
    assert isinstance(core, CoreConfig)
    assert core.grasp is cfg.grasp and core.fof is cfg.fof and core.stereo is cfg.stereo
    assert [f.name for f in dataclasses.fields(CoreConfig)] == [
        "stereo", "observation", "fof", "svgp", "cubature", "reconstruction", "freespace", "grasp"
    ]  # fmt: skip


def test_a_byte_budget_below_a_pair_of_the_largest_images_is_warned_of() -> None:
    image = {"max_image_bytes": 1 << 20}
    at = load_config_dict({"daemon": image, "queues": {"buffered_bytes": 2 << 20}})
    assert config_warnings(at) == []
    below = load_config_dict({"daemon": image, "queues": {"buffered_bytes": (2 << 20) - 1}})
    assert config_warnings(below) == [
        "queues.buffered_bytes = 2097151 B is less than twice daemon.max_image_bytes = 1048576 B: a "
        "stereo pair of images that large is dropped for the byte budget"
    ]
