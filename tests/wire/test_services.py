# SPDX-License-Identifier: Apache-2.0
"""Service types and hashes as ROS 2 computes them, and the rmw_zenoh request/reply framing."""

from __future__ import annotations

import struct

import pytest
from rosbags.typesys import Stores, get_typestore

from pugsd.errors import DecodeError
from pugsd.wire import codec
from pugsd.wire.services import read_request, reply_attachment, response, service_key
from pugsd.wire.types import (
    EXECUTE_GRASP,
    GET_GRASPS,
    TRIGGER,
    _service_hash_store,
    service_type_hash,
    service_types,
    type_hash,
)

#: rmw_zenoh docs/design.md (@99a6a2bd): the add_two_ints service key with DOMAIN_ID=2
ADD_TWO_INTS_KEY = (
    "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
)


def test_service_hashes_match_ros() -> None:
    ts = _service_hash_store()
    ts.register(service_types("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n"))
    assert service_type_hash(ts, "example_interfaces/srv/AddTwoInts") == ADD_TWO_INTS_KEY.rsplit("/", 1)[1]
    assert type_hash(TRIGGER) == "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
    # rosbags' own store reads ServiceEventInfo's char[16] as char, which ROS does not: another hash
    plain = get_typestore(Stores.ROS2_JAZZY)
    plain.register(service_types("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n"))
    assert plain.hash_rihs01("example_interfaces/srv/AddTwoInts") != ADD_TWO_INTS_KEY.rsplit("/", 1)[1]
    # pugsd's own services differ from each other and from their request/response messages
    hashes = {type_hash(t) for t in (GET_GRASPS, EXECUTE_GRASP, TRIGGER)}
    assert len(hashes) == 3 and all(h.startswith("RIHS01_") and len(h) == 71 for h in hashes)


def test_service_key_is_rmw_zenohs() -> None:
    key = service_key("/pugsd/reset", TRIGGER, domain_id=3)
    assert key == "3/pugsd/reset/std_srvs::srv::dds_::Trigger_/" + type_hash(TRIGGER)
    assert service_key("/pugsd/reset", TRIGGER, hash_mode="humble").endswith("/TypeHashNotSupported")


def test_a_srv_needs_one_separator_line() -> None:
    with pytest.raises(ValueError, match="one '---' line"):
        service_types("a/srv/B", "int64 a\n")
    with pytest.raises(ValueError, match="one '---' line"):
        service_types("a/srv/B", "---\n---\n")


def _att(seq: int, gid: bytes = bytes(range(16))) -> bytes:
    return struct.pack("<qqB16s", seq, 123, 16, gid)


def test_requests_are_read_with_their_attachment_and_replies_carry_it_back() -> None:
    # ExecuteGrasp's request by hand: CDR_LE header, int64 grasp_id, float64 width
    payload = b"\x00\x01\x00\x00" + struct.pack("<q", 7) + struct.pack("<d", 0.04)
    req = read_request(EXECUTE_GRASP, payload, _att(5))
    assert (req.request.grasp_id, req.request.width) == (7, 0.04)
    assert (req.sequence_number, req.source_timestamp_ns, req.client_gid) == (5, 123, bytes(range(16)))
    seq, ts, n, gid = struct.unpack("<qqB16s", reply_attachment(req, 999))
    assert (seq, ts, n, gid) == (5, 999, 16, bytes(range(16)))
    # rmw_zenoh's server takes a request numbered 0, refuses a negative one
    assert read_request(TRIGGER, b"\x00\x01\x00\x00\x00", _att(0)).sequence_number == 0
    empty = b"\x00\x01\x00\x00\x00"
    for typename, att, data in (
        (TRIGGER, _att(-1), empty),  # a negative number
        (TRIGGER, None, empty),  # no attachment: not an rmw_zenoh client
        (TRIGGER, _att(1), b""),  # no payload
        (EXECUTE_GRASP, _att(1), b"\x00\x01\x00\x00\x07\x00"),  # truncated
    ):
        with pytest.raises(DecodeError):
            read_request(typename, data, att)


def test_a_response_decodes_with_rosbags() -> None:
    msg = response(TRIGGER, success=True, message="accepted")
    data = codec.serialize(msg, TRIGGER + "_Response")
    plain = get_typestore(Stores.ROS2_JAZZY)
    from rosbags.typesys import get_types_from_msg

    plain.register(get_types_from_msg("bool success\nstring message\n", "check/msg/Trigger_Response"))
    back = plain.deserialize_cdr(data, "check/msg/Trigger_Response")
    assert (back.success, back.message) == (True, "accepted")
