# SPDX-License-Identifier: Apache-2.0
"""ROS 2 services the rmw_zenoh way: a queryable on the service's key, CDR request and reply, the
rmw_zenoh attachment on both.

As read in ros2/rmw_zenoh (``rmw_zenoh_cpp/src/detail/rmw_service_data.cpp`` and
``rmw_client_data.cpp``, rolling):

- the key is a topic key (:func:`pugsd.wire.keys.topic_key`) of the service name and the
  *service* type, ``<domain>/<name>/<pkg>::srv::dds_::<Name>_/RIHS01_<hash of the service>``
  (e.g. ``2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6b...`` in
  rmw_zenoh's ``docs/design.md``); the server declares its queryable ``complete``;
- a client sends a get on that key (target ALL_COMPLETE, no consolidation) whose payload is the
  request's CDR (``<Name>_Request``) and whose attachment carries the client's sequence number,
  its send time and its GID (:mod:`pugsd.wire.attachment`);
- the server replies on its key with the response's CDR (``<Name>_Response``) and an attachment
  of the *request's* sequence number and client GID with the reply's send time: the client
  matches the reply to its request by that sequence number. An error reply is only logged by the
  client (the call then waits for its timeout), so a refusal is a response (``success = false``);
- the server announces itself with an ``SS`` liveliness token
  (:func:`pugsd.wire.topics.ros_graph_tokens`); ``ros2 service call`` waits for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pugsd.errors import DecodeError
from pugsd.wire.attachment import decode_attachment, encode_attachment, now_ns
from pugsd.wire.codec import deserialize, serialize
from pugsd.wire.keys import topic_key
from pugsd.wire.types import msg_class


def service_key(name: str, typename: str, *, domain_id: int = 0, hash_mode: str = "rihs01") -> str:
    """The rmw_zenoh key of service ``name`` (fully qualified, ``/pugsd/reset``) of ``typename``
    (``std_srvs/srv/Trigger``)."""
    return topic_key(name, typename, domain_id=domain_id, key_style="rmw_zenoh", hash_mode=hash_mode)


@dataclass(frozen=True, slots=True)
class ServiceRequest:
    """A decoded request: the message and what its reply must carry back."""

    request: Any  # the rosbags ``<Name>_Request`` object
    sequence_number: int
    source_timestamp_ns: int
    client_gid: bytes


def read_request(typename: str, payload: bytes | None, attachment: bytes | None) -> ServiceRequest:
    """Decode a request of service ``typename``; DecodeError without a valid rmw_zenoh attachment
    (rmw_zenoh numbers a client's requests from 1 and its server refuses one below 0) or with a
    payload that is not the request's CDR."""
    att = decode_attachment(attachment, min_sequence=0)
    if not payload:
        raise DecodeError(f"{typename}: empty request (rmw_zenoh sends the request's CDR)")
    req = deserialize(payload, typename + "_Request")
    return ServiceRequest(req, att.sequence_number, att.source_timestamp_ns, att.gid)


def response(typename: str, **fields: Any) -> Any:
    """A ``<Name>_Response`` object of service ``typename``."""
    return msg_class(typename + "_Response")(**fields)


def encode_response(typename: str, msg: Any) -> bytes:
    return serialize(msg, typename + "_Response")


def reply_attachment(req: ServiceRequest, source_timestamp_ns: int | None = None) -> bytes:
    """The attachment of the reply to ``req``: its sequence number and client GID, sent now."""
    ts = now_ns() if source_timestamp_ns is None else int(source_timestamp_ns)
    return encode_attachment(req.sequence_number, ts, req.client_gid)


def reply(query: Any, key: str, typename: str, req: ServiceRequest, msg: Any) -> None:
    """Answer ``query`` (a zenoh Query) with response ``msg`` on ``key``, as rmw_zenoh does."""
    query.reply(key, encode_response(typename, msg), attachment=reply_attachment(req))
