# SPDX-License-Identifier: Apache-2.0
"""Zenoh key expressions for ROS 2 topics: rmw_zenoh style and zenoh-bridge-ros2dds style.

rmw_zenoh (Jazzy+):
``<domain>/<topic without leading/trailing '/'>/<pkg>::msg::dds_::<Name>_/RIHS01_<hex>``.
ros2dds: the topic without its leading '/'.
"""

from __future__ import annotations

from dataclasses import dataclass

from pugsd.errors import ConfigError, DecodeError
from pugsd.wire.types import known_type, type_hash

KEY_STYLES = ("rmw_zenoh", "ros2dds")
HASH_MODES = ("rihs01", "humble")
HUMBLE_HASH = "TypeHashNotSupported"


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_``."""
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise ConfigError(f"not a ROS 2 type name: {typename!r} (expected pkg/msg/Name)")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image``."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        raise DecodeError(f"not a DDS type name: {dds_name!r}")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def strip_topic(topic: str) -> str:
    t = topic.strip("/")
    if not t or "//" in t or any(c in t for c in "*$?#"):
        raise ConfigError(f"invalid topic name {topic!r}")
    return t


def topic_key(
    topic: str,
    typename: str,
    *,
    domain_id: int = 0,
    key_style: str = "rmw_zenoh",
    hash_mode: str = "rihs01",
) -> str:
    """The zenoh key expression a ROS 2 node would use for ``topic`` of type ``typename``."""
    t = strip_topic(topic)
    if key_style == "ros2dds":
        return t
    if key_style != "rmw_zenoh":
        raise ConfigError(f"key_style must be one of {KEY_STYLES}, got {key_style!r}")
    if hash_mode == "rihs01":
        if not known_type(typename):  # e.g. a recording's custom or corrupt schema name
            raise ConfigError(
                f"no RIHS01 type hash for {typename[:100]!r}: not a message type pugsd knows "
                "(use hash_mode 'humble' or key_style 'ros2dds' for it)"
            )
        h = type_hash(typename)
    elif hash_mode == "humble":
        h = HUMBLE_HASH
    else:
        raise ConfigError(f"hash_mode must be one of {HASH_MODES}, got {hash_mode!r}")
    return f"{domain_id}/{t}/{dds_type_name(typename)}/{h}"


def subscription_key(topic: str, *, domain_id: int = 0, key_style: str = "rmw_zenoh") -> str:
    """A key expression matching ``topic`` of any type (rmw_zenoh: ``<d>/<topic>/*/*``)."""
    t = strip_topic(topic)
    if key_style == "ros2dds":
        return t
    if key_style != "rmw_zenoh":
        raise ConfigError(f"key_style must be one of {KEY_STYLES}, got {key_style!r}")
    return f"{domain_id}/{t}/*/*"


@dataclass(frozen=True, slots=True)
class KeyInfo:
    """What an rmw_zenoh data key says: domain, ROS topic (with leading '/'), type and hash."""

    domain_id: int
    topic: str
    typename: str
    type_hash: str


def parse_key(key: str) -> KeyInfo:
    """Split an rmw_zenoh data key; DecodeError if it does not have that form."""
    parts = str(key).split("/")
    if len(parts) < 4:
        raise DecodeError(f"not an rmw_zenoh key: {key!r}")
    try:
        domain = int(parts[0])
    except ValueError:
        raise DecodeError(f"not an rmw_zenoh key (domain {parts[0]!r}): {key!r}") from None
    h = parts[-1]
    if not (h == HUMBLE_HASH or (h.startswith("RIHS01_") and len(h) == 7 + 64)):
        raise DecodeError(f"not an rmw_zenoh key (hash {h!r}): {key!r}")
    return KeyInfo(domain, "/" + "/".join(parts[1:-2]), ros_type_name(parts[-2]), h)
