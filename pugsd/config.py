# SPDX-License-Identifier: Apache-2.0
"""pugsd configuration: one frozen section per stage, loaded strictly from TOML.

``config/pugsd.toml`` is generated from these defaults (``pugsd dump-config``) and a test keeps
the two equal. Each subsystem defines its sections in its own package (the core's in
:mod:`pugsd.core.config`); :class:`PugsdConfig` collects them. The core sections are re-exported
here.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pugsd.arm.config import ArmConfig
from pugsd.configbase import build, to_toml
from pugsd.core.config import (
    CoreConfig,
    CubatureConfig,
    FofConfig,
    FreeSpaceConfig,
    GraspConfig,
    GripperConfig,
    ObservationConfig,
    ReconstructionConfig,
    StereoConfig,
    SvgpConfig,
)
from pugsd.daemon.config import DaemonConfig, QueuesConfig, TopicsConfig
from pugsd.errors import ConfigError
from pugsd.record.config import RecordConfig
from pugsd.wire.config import default_zenoh_config
from pugsd.wire.topics import graph_token_problems, graph_tokens_enabled

__all__ = [
    "USER_KEYS",
    "ZENOH_KEY_DOCS",
    "ArmConfig",
    "CoreConfig",
    "CubatureConfig",
    "DaemonConfig",
    "FofConfig",
    "FreeSpaceConfig",
    "GraspConfig",
    "GripperConfig",
    "ObservationConfig",
    "PugsdConfig",
    "QueuesConfig",
    "ReconstructionConfig",
    "RecordConfig",
    "StereoConfig",
    "SvgpConfig",
    "TopicsConfig",
    "config_warnings",
    "core_of",
    "default_config",
    "dump_config",
    "load_config",
    "load_config_dict",
    "parse_override",
]


@dataclass(frozen=True)
class PugsdConfig:
    """The whole pugsd configuration."""

    stereo: StereoConfig = dataclasses.field(default_factory=StereoConfig)
    observation: ObservationConfig = dataclasses.field(default_factory=ObservationConfig)
    fof: FofConfig = dataclasses.field(default_factory=FofConfig)
    svgp: SvgpConfig = dataclasses.field(default_factory=SvgpConfig)
    cubature: CubatureConfig = dataclasses.field(default_factory=CubatureConfig)
    reconstruction: ReconstructionConfig = dataclasses.field(default_factory=ReconstructionConfig)
    freespace: FreeSpaceConfig = dataclasses.field(default_factory=FreeSpaceConfig)
    grasp: GraspConfig = dataclasses.field(default_factory=GraspConfig)
    daemon: DaemonConfig = dataclasses.field(default_factory=DaemonConfig)
    topics: TopicsConfig = dataclasses.field(default_factory=TopicsConfig)
    queues: QueuesConfig = dataclasses.field(default_factory=QueuesConfig)
    record: RecordConfig = dataclasses.field(default_factory=RecordConfig)
    arm: ArmConfig = dataclasses.field(default_factory=ArmConfig)
    zenoh: dict[str, Any] = dataclasses.field(
        default_factory=default_zenoh_config,
        metadata={"doc": "passed through to zenoh's own configuration (JSON5 keys)"},
    )

    def __post_init__(self) -> None:
        for what in ("listen", "connect"):  # zenoh took a string for one endpoint only at open
            table = self.zenoh.get(what) if isinstance(self.zenoh, dict) else None
            value = table.get("endpoints") if isinstance(table, dict) else None
            if isinstance(value, str):
                one = value.strip().strip("[]").strip().strip("'\"")[:100]  # "[tcp/...]" unquoted too
                raise ConfigError(
                    f"zenoh.{what}.endpoints must be a list, e.g. [\"tcp/127.0.0.1:7447\"] (got the string "
                    f"{value[:100]!r}; on a command line: --set 'zenoh.{what}.endpoints=[\"{one}\"]')"
                )
        # [topics] checks its own names for ros_graph_tokens = "on"; the node name is [daemon]'s
        if self.topics.ros_graph_tokens == "on":
            graph_tokens_enabled(self.topics, self.daemon.node_name)  # ConfigError if refused


def core_of(cfg: PugsdConfig) -> CoreConfig:
    """The core sections of a full config."""
    return CoreConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(CoreConfig)})


def config_warnings(cfg: PugsdConfig) -> list[str]:
    """Settings that are each valid but do not fit together; ``pugsd check-config`` prints them
    and ``pugsd run`` logs them at start (neither refuses: the user may mean it)."""
    out: list[str] = []
    pre_m = cfg.arm.motion.pregrasp_distance_m
    if cfg.arm.enabled and cfg.grasp.approach_check_m < pre_m:
        out.append(
            f"grasp.approach_check_m = {cfg.grasp.approach_check_m:g} m is shorter than "
            f"arm.motion.pregrasp_distance_m = {pre_m:g} m: the arm approaches in a straight line "
            f"from its stand-off, and the first {pre_m - cfg.grasp.approach_check_m:.3g} m of that "
            "line (from the stand-off) are not checked against the cloud"
        )
    image_b, held_b = cfg.daemon.max_image_bytes, cfg.queues.buffered_bytes
    if held_b < 2 * image_b:
        out.append(
            f"queues.buffered_bytes = {held_b} B is less than twice daemon.max_image_bytes = "
            f"{image_b} B: a stereo pair of images that large is dropped for the byte budget"
        )
    t = cfg.topics
    if t.ros_graph_tokens == "auto" and (t.key_style, t.hash_mode) == ("rmw_zenoh", "rihs01"):
        problems = graph_token_problems(t, cfg.daemon.node_name)
        if problems:
            out.append(
                "topics.ros_graph_tokens = 'auto' declares no ROS graph tokens, so ros2 node list "
                "and ros2 topic list will not show pugsd: " + "; ".join(problems)
            )
    return out


def _set_dotted(data: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = data
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise ConfigError(f"{dotted}: {p} is not a table")
    node[parts[-1]] = value


def parse_override(text: str) -> tuple[str, Any]:
    """``section.key=VALUE`` with VALUE in TOML syntax (bare words are taken as strings)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected KEY=VALUE")
    key, raw = text.split("=", 1)
    key, raw = key.strip(), raw.strip()
    if not all(part.strip() for part in key.split(".")):
        raise ConfigError(f"override {text!r}: expected section.key=VALUE")
    try:
        parsed = tomllib.loads(f"v = {raw}")
    except ValueError:  # TOMLDecodeError, or an integer of more than 4300 digits
        return key, raw
    if list(parsed) != ["v"]:  # "3\ngrasp.gamma = 9": the second line was dropped without a word
        raise ConfigError(f"override {text!r}: VALUE must be a single TOML value")
    return key, parsed["v"]


def load_config_dict(data: Mapping[str, Any], overrides: Sequence[str] = ()) -> PugsdConfig:
    """Build a PugsdConfig from a dict plus ``key=value`` overrides."""
    merged: dict[str, Any] = copy.deepcopy(dict(data))
    for o in overrides:
        k, v = parse_override(o)
        _set_dotted(merged, k, v)
    # the [zenoh] table passes through to zenoh itself, which validates it when the session opens
    return build(PugsdConfig, merged)


def ros_domain_id(env: Mapping[str, str]) -> int | None:
    """``ROS_DOMAIN_ID`` from ``env`` (None when unset or empty, as rcl reads it); ConfigError
    when it is not a whole number."""
    raw = env.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return None
    try:
        value = int(raw, 10)
    except ValueError:
        value = -1
    if not 0 <= value <= 232:
        raise ConfigError(f"ROS_DOMAIN_ID={raw[:50]!r} is not a domain id (a whole number, 0-232)")
    return value


def load_config(
    path: str | Path | None = None, overrides: Sequence[str] = (), env: Mapping[str, str] | None = None
) -> PugsdConfig:
    """Load and validate a TOML file (None: the defaults). The ROS domain is, by precedence: a
    ``topics.domain_id=`` override, then ``ROS_DOMAIN_ID`` in ``env`` (default: the process
    environment) when set, then ``[topics] domain_id`` of the file, then 0."""
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"{p}: no such file") from None
        except OSError as exc:  # a directory, no permission
            raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML: not UTF-8 (byte {exc.start})") from None
        except ValueError as exc:  # TOMLDecodeError, or an integer of more than 4300 digits
            raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    domain = ros_domain_id(os.environ if env is None else env)
    if domain is not None and isinstance(data.setdefault("topics", {}), dict):
        data["topics"]["domain_id"] = domain  # a [topics] that is no table is refused by build()
    return load_config_dict(data, overrides)


def default_config() -> PugsdConfig:
    return PugsdConfig()


#: The keys a deployment sets, shown first by ``dump_config`` (and so in config/pugsd.toml), by
#: topic; an entry names a key or a whole table. Every other key is internal tuning and follows
#: in the advanced part.
USER_KEYS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("ROS 2 topics: names, domain and key style of the wire format", ("topics",)),
    (
        "zenoh session: where pugsd listens and connects (loopback only unless "
        "daemon.allow_non_loopback), and the keys of its own API",
        (
            "zenoh.mode",
            "zenoh.listen.endpoints",
            "zenoh.connect.endpoints",
            "daemon.allow_non_loopback",
            "daemon.prefix",
            "daemon.node_name",
        ),
    ),
    (
        "Camera mount and pose input",
        (
            "daemon.T_B_C_xyz_m",
            "daemon.T_B_C_quat_xyzw",
            "daemon.pose_std_translation_m",
            "daemon.pose_std_rotation_rad",
            "daemon.world_frame",
        ),
    ),
    ("Compute device", ("svgp.device", "fof.query_device")),
    (
        "Gripper and grasp selection",
        (
            "grasp.gripper",
            "grasp.proposer",
            "grasp.model_path",
            "grasp.uncertainty",
            "grasp.gamma",
            "grasp.top_k",
            "daemon.grasp_rate_hz",
            "daemon.publish_cloud",
        ),
    ),
    (
        "Recording",
        (
            "record.enabled",
            "record.directory",
            "record.name_prefix",
            "record.keys",
            "record.rotate_size_bytes",
            "record.rotate_duration_s",
            "record.max_total_bytes",
        ),
    ),
    ("Logging", ("daemon.log_level", "daemon.log_json")),
    (
        "Arm (no arm command is sent unless arm.enabled)",
        (
            "arm.enabled",
            "arm.transport",
            "arm.serial.port",
            "arm.udp.host",
            "arm.udp.port",
            "arm.can.channel",
            "arm.kinematics.T_B_W",
            "arm.kinematics.T_B_W_xyz",
            "arm.kinematics.T_B_W_rpy_deg",
            "arm.safety.workspace_min_m",
            "arm.safety.workspace_max_m",
        ),
    ),
)


#: The keys of the [zenoh] table that dump_config documents (zenoh documents every other one).
ZENOH_KEY_DOCS: dict[str, str] = {
    "zenoh.mode": "zenoh session mode: peer, client or router",
    "zenoh.listen.endpoints": "zenoh endpoints this session listens on, e.g. tcp/127.0.0.1:7447",
    "zenoh.connect.endpoints": "zenoh endpoints (routers or peers) this session connects to",
    "zenoh.scouting.multicast.enabled": "multicast scouting: discover peers on the LAN",
    "zenoh.scouting.gossip.enabled": "gossip scouting: learn of peers from connected peers",
}


def dump_config(cfg: PugsdConfig | None = None) -> str:
    """The documented TOML text of ``cfg`` (default: the defaults): the keys a deployment sets
    first (:data:`USER_KEYS`), then the internal tuning keys."""
    header = (
        "pugsd configuration reference: every key with its meaning and unit.\n"
        "Generated by `pugsd dump-config`; a test keeps it equal to the defaults in code.\n"
        "Unknown keys, wrong types and out-of-range values are errors (`pugsd check-config FILE`).\n"
        "\n"
        "Each line is `section.key = value`, the form `--set section.key=VALUE` takes; a file may\n"
        "as well group keys under [section] headers. A file needs only the keys it changes. The\n"
        "keys a deployment sets come first; the advanced part below them holds internal tuning."
    )
    return to_toml(
        cfg if cfg is not None else PugsdConfig(),
        header,
        first=USER_KEYS,
        rest_title="Advanced: internal tuning. The defaults suit a deployment; change them with care",
        free_docs=ZENOH_KEY_DOCS,
    )
