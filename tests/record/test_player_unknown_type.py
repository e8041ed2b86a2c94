# SPDX-License-Identifier: Apache-2.0
"""Playing a recording whose message type pugsd does not know (a custom type, or a schema name a
corrupt summary altered) with keys rebuilt from topic and type: a ConfigError naming the type,
not a KeyError traceback from the type store (`pugsd play` printed one)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pugsd.errors import ConfigError
from pugsd.record.mcapio import iter_recording, new_writer
from pugsd.record.player import Player, PlayOptions, output_key
from pugsd.wire.keys import HUMBLE_HASH, topic_key
from pugsd.wire.types import IMAGE


class _Pub:
    matching_status = True

    def __init__(self, key: str, sent: list[str]) -> None:
        self.key, self.sent = key, sent

    def put(self, payload: bytes, **_: Any) -> None:
        self.sent.append(self.key)

    def undeclare(self) -> None:
        pass


class _Session:
    """Records the keys put on; no zenoh."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    def declare_publisher(self, key: str, **_: Any) -> _Pub:
        return _Pub(key, self.sent)


def _recording(path: Path, typename: str) -> Path:
    with path.open("wb") as f:
        w = new_writer(f, 1 << 16, "none")
        sid = w.register_schema(typename, "ros2msg", b"int32 x\n")
        cid = w.register_channel("/foo", "cdr", sid)  # no zenoh_key metadata: keys are rebuilt
        w.add_message(cid, log_time=1, data=b"\x00\x01\x00\x00\x07\x00\x00\x00", publish_time=1)
        w.finish()
    return path


@pytest.mark.parametrize("typename", ["my_msgs/msg/Foo", "sensor_msgs/msg/I}age", "s\x00nsor_msgs/msg/Image"])
def test_an_unknown_type_is_a_config_error_when_its_key_is_rebuilt(tmp_path: Path, typename: str) -> None:
    f = _recording(tmp_path / "custom.mcap", typename)
    (msg,) = iter_recording([f])
    with pytest.raises(ConfigError, match="no RIHS01 type hash"):
        output_key(msg, PlayOptions())
    session = _Session()
    with pytest.raises(ConfigError, match="no RIHS01 type hash"):
        Player(session, [f], PlayOptions(rate=0.0)).run()
    # the Humble key needs no hash: played
    if typename == "my_msgs/msg/Foo":
        assert Player(session, [f], PlayOptions(rate=0.0, hash_mode="humble")).run() == 1
        assert session.sent == [f"0/foo/my_msgs::msg::dds_::Foo_/{HUMBLE_HASH}"]


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(st.text(max_size=40), st.sampled_from(["rihs01", "humble"]), st.sampled_from(["rmw_zenoh", "ros2dds"]))
def test_topic_key_of_any_type_name_is_a_key_or_a_config_error(typename: str, mode: str, style: str) -> None:
    try:
        key = topic_key("/foo", typename, key_style=style, hash_mode=mode)
    except ConfigError:
        return
    assert isinstance(key, str)


def test_a_known_type_still_gets_its_hash() -> None:
    assert topic_key("/img", IMAGE).startswith("0/img/sensor_msgs::msg::dds_::Image_/RIHS01_")
