# SPDX-License-Identifier: Apache-2.0
"""Key expressions (rmw_zenoh / ros2dds) and the 33-byte rmw_zenoh attachment."""

from __future__ import annotations

import pytest
from zenoh.ext import Int64, z_serialize

from pugsd.daemon.config import TopicsConfig
from pugsd.errors import ConfigError, DecodeError
from pugsd.wire.attachment import decode_attachment, encode_attachment
from pugsd.wire.keys import dds_type_name, parse_key, subscription_key, topic_key
from pugsd.wire.topics import key_for, subscribe_key_for
from pugsd.wire.types import GRASP_ARRAY, IMAGE, type_hash

SPEC_IMAGE_KEY = (
    "0/stereo/left/image_raw/sensor_msgs::msg::dds_::Image_/"
    "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
)


def test_image_key_matches_spec_example() -> None:
    assert topic_key("/stereo/left/image_raw", IMAGE) == SPEC_IMAGE_KEY
    assert key_for(TopicsConfig(), "left_image") == SPEC_IMAGE_KEY


def test_key_variants() -> None:
    assert topic_key("/a/b/", IMAGE, domain_id=7).startswith(
        "7/a/b/sensor_msgs::msg::dds_::Image_/"
    )
    assert topic_key("/a/b", IMAGE, hash_mode="humble").endswith("/TypeHashNotSupported")
    assert (
        topic_key("/stereo/left/image_raw", IMAGE, key_style="ros2dds") == "stereo/left/image_raw"
    )
    assert subscription_key("/camera_pose", domain_id=3) == "3/camera_pose/*/*"
    assert subscribe_key_for(TopicsConfig(key_style="ros2dds"), "pose") == "camera_pose"
    assert dds_type_name(GRASP_ARRAY) == "pugs_msgs::msg::dds_::GraspArray_"
    gk = topic_key("/pugs/grasps", GRASP_ARRAY)
    assert gk.endswith(type_hash(GRASP_ARRAY)) and len(type_hash(GRASP_ARRAY)) == 71
    with pytest.raises(ConfigError):
        topic_key("/a", IMAGE, key_style="dds")
    with pytest.raises(ConfigError):
        topic_key("/a", IMAGE, hash_mode="iron")
    with pytest.raises(ConfigError):
        topic_key("/", IMAGE)
    with pytest.raises(ConfigError):
        topic_key("/a/*", IMAGE)


def test_parse_key() -> None:
    info = parse_key(SPEC_IMAGE_KEY)
    assert (info.domain_id, info.topic, info.typename) == (0, "/stereo/left/image_raw", IMAGE)
    assert info.type_hash.startswith("RIHS01_d31d")
    img = "sensor_msgs::msg::dds_::Image_"
    bad_keys = ("stereo/left", f"x/a/{img}/TypeHashNotSupported",
                "0/a/Image/TypeHashNotSupported", f"0/a/{img}/RIHS01_12")  # fmt: skip
    for bad in bad_keys:
        with pytest.raises(DecodeError):
            parse_key(bad)


def test_attachment_layout_matches_zenoh_ext() -> None:
    gid = bytes(range(16))
    att = encode_attachment(1, 1_700_000_000_000_000_123, gid)
    assert len(att) == 33
    ref = z_serialize((Int64(1), Int64(1_700_000_000_000_000_123), gid)).to_bytes()
    assert att == ref
    assert att[:8] == (1).to_bytes(8, "little") and att[16] == 0x10 and att[17:] == gid
    a = decode_attachment(att)
    assert (a.sequence_number, a.source_timestamp_ns, a.gid) == (1, 1_700_000_000_000_000_123, gid)
    with pytest.raises(DecodeError):
        decode_attachment(att[:-1])
    with pytest.raises(DecodeError):
        decode_attachment(att[:16] + b"\x0f" + att[17:])
    with pytest.raises(DecodeError):
        decode_attachment(None)
    with pytest.raises(ValueError):
        encode_attachment(1, 2, b"short")


def test_sequence_tracker_counts_gaps_late_and_untracked_per_publisher() -> None:
    from pugsd.wire.attachment import SequenceTracker

    a, b = b"A" * 16, b"B" * 16
    t = SequenceTracker()
    # the first message of a publisher is its baseline, whatever its number (we may join late)
    assert t.observe("img", encode_attachment(7, 0, a)) == 0
    assert t.observe("img", encode_attachment(8, 0, a)) == 0
    assert t.observe("img", encode_attachment(11, 0, a)) == 2  # 9 and 10 missing
    # another publisher on the same input is tracked on its own
    assert t.observe("img", encode_attachment(1, 0, b)) == 0
    assert t.observe("img", encode_attachment(3, 0, b)) == 1
    assert t.observe("img", encode_attachment(10, 0, a)) == 0  # late: not a gap, not a reset
    assert t.observe("img", encode_attachment(12, 0, a)) == 0
    assert t.observe("img", None) == 0
    assert t.observe("img", b"\x00" * 12) == 0
    assert t.observe("pose", encode_attachment(5, 0, a)) == 0  # same GID, other input
    snap = t.snapshot()
    assert snap == {
        "lost": {"img": 3},
        "late": {"img": 1},
        "restarts": {},
        "untracked": {"img": 2},
        "before_first": {"img": 6, "pose": 4},  # 1-6 of A, 1-4 of A on pose; B began at 1
        "publishers": {"img": 2, "pose": 1},
    }


def test_sequence_tracker_forgets_the_least_recent_publisher() -> None:
    from pugsd.wire.attachment import SequenceTracker

    t = SequenceTracker(max_publishers=2)
    g = [bytes([i]) * 16 for i in range(3)]
    t.observe("x", encode_attachment(1, 0, g[0]))
    t.observe("x", encode_attachment(1, 0, g[1]))
    t.observe("x", encode_attachment(1, 0, g[2]))  # forgets g[0]
    assert t.snapshot()["publishers"] == {"x": 2}
    assert t.observe("x", encode_attachment(50, 0, g[0])) == 0  # back: a new baseline
    assert t.observe("x", encode_attachment(5, 0, g[1])) == 0  # g[1] forgotten in turn
    assert t.snapshot()["lost"] == {}
    assert t.snapshot()["before_first"] == {"x": 49 + 4}  # a returning publisher counts again


def test_sequence_tracker_resyncs_when_a_publisher_restarts_with_the_same_gid() -> None:
    from pugsd.wire.attachment import SequenceTracker

    g = b"G" * 16
    t = SequenceTracker()
    for seq in range(1, 101):
        assert t.observe("img", encode_attachment(seq, 0, g)) == 0
    # the publisher restarts under the same GID (fixed zenoh id): numbering begins at 1 again
    for seq in range(1, 51):
        assert t.observe("img", encode_attachment(seq, 0, g)) == 0
    assert t.observe("img", encode_attachment(53, 0, g)) == 2  # gaps are seen again at once
    snap = t.snapshot()
    assert snap["restarts"] == {"img": 1} and snap["late"] == {} and snap["lost"] == {"img": 2}
    assert snap["before_first"] == {}  # a restart begins at 1 again: nothing before it
    assert t.observe("img", encode_attachment(53, 0, g)) == 0  # a repeat is still late
    assert t.snapshot()["late"] == {"img": 1}
