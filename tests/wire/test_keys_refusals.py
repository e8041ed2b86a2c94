# SPDX-License-Identifier: Apache-2.0
"""Zenoh keys for ROS 2 topics (``pugsd.wire.keys``): goldens written from the ecosystem spec
(section 2.1: ``<domain>/<topic, leading and trailing '/' stripped>/<pkg::msg::dds_::Name_>/<hash>``,
Humble's hash the literal ``TypeHashNotSupported``; zenoh-bridge-ros2dds: the topic without its
leading '/'), and the names and keys that must be refused rather than turned into a key."""

from __future__ import annotations

import pytest

from pugsd.errors import ConfigError, DecodeError
from pugsd.wire.keys import (
    KeyInfo,
    dds_type_name,
    parse_key,
    ros_type_name,
    strip_topic,
    subscription_key,
    topic_key,
)
from pugsd.wire.types import IMAGE, STRING

IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"  # spec 2.1
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_keys_written_from_the_spec() -> None:
    # Humble: the same key with the literal in place of the hash
    assert topic_key("/stereo/left/image_raw", IMAGE, hash_mode="humble") == (
        "0/stereo/left/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"
    )
    # leading and trailing '/' stripped, inner ones kept; the domain first
    assert topic_key("stereo/left/image_raw/", IMAGE, domain_id=42) == (
        f"42/stereo/left/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}"
    )
    assert topic_key("/chatter", STRING) == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    # zenoh-bridge-ros2dds: the topic alone, whatever the type and hash mode
    assert topic_key("/stereo/left/image_raw/", IMAGE, key_style="ros2dds", hash_mode="humble") == (
        "stereo/left/image_raw"
    )
    assert subscription_key("/pugs/grasps/", domain_id=7) == "7/pugs/grasps/*/*"
    assert subscription_key("/pugs/grasps/", key_style="ros2dds") == "pugs/grasps"


def test_a_type_without_a_known_hash_has_a_key_only_where_no_hash_is_written() -> None:
    custom = "my_pkg/msg/Thing"
    with pytest.raises(ConfigError, match="no RIHS01 type hash"):
        topic_key("/thing", custom)
    assert topic_key("/thing", custom, hash_mode="humble") == (
        "0/thing/my_pkg::msg::dds_::Thing_/TypeHashNotSupported"
    )
    assert topic_key("/thing", custom, key_style="ros2dds") == "thing"


@pytest.mark.parametrize("bad", ["sensor_msgs/Image", "a/msg/B/C", "pkg//Name", "/msg/Name", "pkg/msg/"])
def test_a_malformed_ros_type_name_is_refused(bad: str) -> None:
    with pytest.raises(ConfigError, match="not a ROS 2 type name"):
        dds_type_name(bad)


def test_dds_type_names_both_ways() -> None:
    assert dds_type_name("pugs_msgs/msg/GraspArray") == "pugs_msgs::msg::dds_::GraspArray_"
    assert ros_type_name("sensor_msgs::msg::dds_::Image_") == "sensor_msgs/msg/Image"
    for bad in (
        "sensor_msgs::msg::dds::Image_",  # not the dds_ namespace
        "sensor_msgs::msg::dds_::Image",  # no trailing underscore
        "sensor_msgs::msg::dds_::_",  # no name at all
        "sensor_msgs::msg::Image_",  # three parts
    ):
        with pytest.raises(DecodeError):
            ros_type_name(bad)


@pytest.mark.parametrize(
    "bad",
    ["/", "//", "/a//b", "/a/*", "/a/**/b", "/a/$x", "/a/b?", "/a/#b", ""],
)
def test_topics_zenoh_would_read_as_a_pattern_or_an_empty_chunk_are_refused(bad: str) -> None:
    """Zenoh key expressions reserve ``*``, ``$``, ``?`` and ``#`` and have no empty chunks: such a
    topic would subscribe to, or publish on, something other than the one topic named."""
    with pytest.raises(ConfigError, match="invalid topic name"):
        strip_topic(bad)
    with pytest.raises(ConfigError):
        topic_key(bad, IMAGE)
    with pytest.raises(ConfigError):
        subscription_key(bad)


def test_an_unknown_key_style_is_refused_for_subscriptions_too() -> None:
    with pytest.raises(ConfigError, match="key_style"):
        subscription_key("/a", key_style="dds")


def test_parse_key_reads_what_topic_key_writes() -> None:
    k = topic_key("/a/b/c", IMAGE, domain_id=12, hash_mode="humble")
    assert parse_key(k) == KeyInfo(12, "/a/b/c", IMAGE, "TypeHashNotSupported")
    assert parse_key(f"3/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}") == KeyInfo(
        3, "/chatter", STRING, STRING_HASH
    )


@pytest.mark.parametrize(
    "bad",
    [
        # no topic between the domain and the type
        f"0/std_msgs::msg::dds_::String_/{STRING_HASH}",
        # a hash of the right length under another prefix, and RIHS01 one digit short or long
        "0/chatter/std_msgs::msg::dds_::String_/RIHS02_" + STRING_HASH[7:],
        "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH[:-1],
        "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH + "0",
        # the type segment is not a DDS type name
        f"0/chatter/std_msgs/{STRING_HASH}",
        f"0/chatter/std_msgs::msg::dds::String_/{STRING_HASH}",
        # the domain is not a number
        f"d/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}",
        # a zenoh-bridge-ros2dds key
        "chatter",
    ],
)
def test_parse_key_refuses_what_is_not_an_rmw_zenoh_data_key(bad: str) -> None:
    with pytest.raises(DecodeError):
        parse_key(bad)
