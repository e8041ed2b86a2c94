# SPDX-License-Identifier: Apache-2.0
"""Config: the reference file equals the defaults; unknown keys, types and ranges are rejected."""

from __future__ import annotations

import dataclasses
import datetime
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from pugsd.cli import main
from pugsd.config import PugsdConfig, dump_config, load_config, load_config_dict, parse_override
from pugsd.configbase import to_dict
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
