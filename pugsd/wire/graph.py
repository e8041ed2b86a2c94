# SPDX-License-Identifier: Apache-2.0
"""rmw_zenoh's ROS graph liveliness tokens (what ``ros2 node list`` / ``ros2 topic list`` read).

Every rmw_zenoh entity declares a zenoh liveliness token whose key expression describes it; each
context's graph cache subscribes to ``@ros2_lv/<domain>/**`` and builds the ROS graph from them.
Data flows without them (the data keys of :mod:`pugsd.wire.keys` are separate); they only make
pugsd visible to ROS 2 graph introspection. The format, as read in ros2/rmw_zenoh's rolling
sources (the same code is in ros2-gbp/rmw_zenoh-release at rmw_zenoh_cpp 0.4.0; the Jazzy and
Humble release branches were not read; ROBOTIS-GIT/zenoh_ros2_sdk ``keyexpr.py`` writes the same
format and its interop tests target Jazzy):

``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` @3411fdec149fe0c932f24d4d79ef908eb81d7482
(``enum KeyexprIndex``, ``Entity::Entity``, ``qos_to_keyexpr``, ``mangle_name``)::

    @ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node name>
        [/<topic>/<type>/<type hash>/<qos>]   (publishers, subscriptions, services, clients)

- every ``/`` inside a segment is replaced by ``%`` (``mangle_name``); so the root namespace
  ``/`` and the default enclave ``/`` (rcl's default, ``rcl/src/rcl/init.c``) are written ``%``
  and the topic ``/pugs/grasps`` is ``%pugs%grasps``. An empty segment is never written:
  ``Entity::make`` refuses an empty namespace or node name, and a token with an empty part is
  rejected by the parser;
- ``<zid>``: ``zenoh::Id::to_string()`` (zenoh-cpp) = zenoh-c ``z_id_to_string`` = the Rust
  ``ZenohId`` Display, which is also what zenoh-python's ``str(session.zid())`` returns
  (``ZenohId.__str__`` in zenoh-python ``src/config.rs``): lowercase hex;
- ``<nid>``/``<id>``: decimal numbers from one counter per context that starts at 0
  (``rmw_context_impl_s::Data``: ``next_entity_id_(0)``, ``get_next_entity_id()``); a node's
  token uses its own number twice (``rmw_node_data.cpp``: ``NodeData::make``), a publisher or
  subscription gives its node's number and then its own (``rmw_publisher_data.cpp``,
  ``rmw_subscription_data.cpp``). The graph cache tells nodes apart by ``(zid, nid)``;
- ``<type>``/``<type hash>``: the same strings as in the data key (``TopicInfo`` builds both from
  them): ``pkg::msg::dds_::Name_`` and ``RIHS01_<64 hex>``;
- ``<qos>``: ``R:D:H,depth:DLs,DLns:LSs,LSns:LV,LVs,LVns`` (reliability, durability, history kind
  and depth, deadline, lifespan, liveliness kind and lease, durations as sec,nsec); a field equal
  to rmw_zenoh's default (``rmw_zenoh_cpp/src/detail/qos.cpp`` @7efeee2b: RELIABLE, VOLATILE,
  KEEP_LAST 42, infinite durations, AUTOMATIC) is left empty. Numbers are the ``rmw/types.h``
  enums. The rmw_qos_profile_default (KEEP_LAST 10, RELIABLE, VOLATILE) is ``::,10:,:,:,,``.
  The reader fills an empty field with *its own* default (``keyexpr_to_qos``), and those defaults
  changed between releases (rmw_zenoh_cpp CHANGELOG: "Switch default durability to volatile",
  #521, rolling 0.5.0, backported to the 0.1.x branch in 0.1.2; before, an empty durability read
  TRANSIENT_LOCAL), so pugsd writes every field of its own tokens (``qos_defaults=None``), which
  every release with this format parses alike.

Examples from ros2/rmw_zenoh ``docs/design.md`` @99a6a2bd10b949052f4f12c5854825dc005e95a5 (the
goldens of ``tests/wire/test_graph_tokens.py``)::

    @ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener
    @ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/
        std_msgs::msg::dds_::String_/RIHS01_df668c74...6b1a18/::,7:,:,:,,

rmw_zenoh also derives each entity's GID from the token (XXH3-128 of the key expression,
``Entity::Entity``). Its subscriptions only copy the attachment's GID into
``message_info.publisher_gid`` (``rmw_subscription_data.cpp``) and never compare it with the
graph, so pugsd keeps its random per-publisher GID (:func:`pugsd.wire.attachment.new_gid`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pugsd.errors import DecodeError

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
SLASH_REPLACEMENT = "%"
QOS_DELIMITER = ":"
QOS_COMPONENT_DELIMITER = ","

# rmw/types.h (rmw_qos_*_policy_e; SYSTEM_DEFAULT is 0 in each)
SYSTEM_DEFAULT = 0
RELIABILITY_RELIABLE, RELIABILITY_BEST_EFFORT = 1, 2
DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE = 1, 2
HISTORY_KEEP_LAST, HISTORY_KEEP_ALL = 1, 2
LIVELINESS_AUTOMATIC, LIVELINESS_MANUAL_BY_TOPIC = 1, 3
#: rmw/time.h RMW_DURATION_INFINITE and RMW_DURATION_UNSPECIFIED (sec, nsec)
DURATION_INFINITE = (9223372036, 854775807)
DURATION_UNSPECIFIED = (0, 0)


@dataclass(frozen=True, slots=True)
class QosProfile:
    """The fields of ``rmw_qos_profile_t`` that rmw_zenoh writes into a token."""

    reliability: int = SYSTEM_DEFAULT
    durability: int = SYSTEM_DEFAULT
    history: int = SYSTEM_DEFAULT
    depth: int = 0
    deadline: tuple[int, int] = DURATION_UNSPECIFIED
    lifespan: tuple[int, int] = DURATION_UNSPECIFIED
    liveliness: int = SYSTEM_DEFAULT
    liveliness_lease_duration: tuple[int, int] = DURATION_UNSPECIFIED

    def adapted(self) -> QosProfile:
        """What rmw_zenoh's ``QoS::best_available_qos`` makes of it before writing the token:
        SYSTEM_DEFAULT kinds, depth 0 and unspecified durations become rmw_zenoh's defaults."""
        d = RMW_ZENOH_DEFAULT_QOS
        return QosProfile(
            reliability=self.reliability or d.reliability,
            durability=self.durability or d.durability,
            history=self.history or d.history,
            depth=self.depth or d.depth,
            deadline=d.deadline if self.deadline == DURATION_UNSPECIFIED else self.deadline,
            lifespan=d.lifespan if self.lifespan == DURATION_UNSPECIFIED else self.lifespan,
            liveliness=self.liveliness or d.liveliness,
            liveliness_lease_duration=(
                d.liveliness_lease_duration
                if self.liveliness_lease_duration == DURATION_UNSPECIFIED
                else self.liveliness_lease_duration
            ),
        )


#: rmw_zenoh's default QoS (``rmw_zenoh_cpp/src/detail/qos.cpp``, ``QoS::QoS``)
RMW_ZENOH_DEFAULT_QOS = QosProfile(
    reliability=RELIABILITY_RELIABLE,
    durability=DURABILITY_VOLATILE,
    history=HISTORY_KEEP_LAST,
    depth=42,
    deadline=DURATION_INFINITE,
    lifespan=DURATION_INFINITE,
    liveliness=LIVELINESS_AUTOMATIC,
    liveliness_lease_duration=DURATION_INFINITE,
)
#: rmw/qos_profiles.h ``rmw_qos_profile_default`` (rclcpp's ``QoS(10)``)
QOS_PROFILE_DEFAULT = QosProfile(
    reliability=RELIABILITY_RELIABLE,
    durability=DURABILITY_VOLATILE,
    history=HISTORY_KEEP_LAST,
    depth=10,
)


def qos_to_keyexpr(qos: QosProfile, defaults: QosProfile | None = RMW_ZENOH_DEFAULT_QOS) -> str:
    """rmw_zenoh's ``qos_to_keyexpr`` of an (adapted) profile: fields equal to ``defaults``
    (rmw_zenoh's) are left empty; ``:`` between policies, ``,`` inside one. ``defaults=None``
    writes every field, which ``keyexpr_to_qos`` reads the same whatever its own defaults."""
    d = RMW_ZENOH_DEFAULT_QOS if defaults is None else defaults
    c = QOS_COMPONENT_DELIMITER

    def _field(value: int, default: int) -> str:
        return str(value) if defaults is None or value != default else ""

    return QOS_DELIMITER.join(
        (
            _field(qos.reliability, d.reliability),
            _field(qos.durability, d.durability),
            _field(qos.history, d.history) + c + _field(qos.depth, d.depth),
            _field(qos.deadline[0], d.deadline[0]) + c + _field(qos.deadline[1], d.deadline[1]),
            _field(qos.lifespan[0], d.lifespan[0]) + c + _field(qos.lifespan[1], d.lifespan[1]),
            _field(qos.liveliness, d.liveliness)
            + c
            + _field(qos.liveliness_lease_duration[0], d.liveliness_lease_duration[0])
            + c
            + _field(qos.liveliness_lease_duration[1], d.liveliness_lease_duration[1]),
        )
    )


def keyexpr_to_qos(text: str) -> QosProfile:
    """rmw_zenoh's ``keyexpr_to_qos``: empty fields are rmw_zenoh's defaults (DecodeError if the
    string does not have 6 policies with 2, 2, 2 and 3 components)."""
    parts = text.split(QOS_DELIMITER)
    if len(parts) != 6:
        raise DecodeError(f"not an rmw_zenoh QoS string: {text!r}")
    comps = [p.split(QOS_COMPONENT_DELIMITER) for p in parts[2:]]
    if [len(c) for c in comps] != [2, 2, 2, 3] or "," in parts[0] + parts[1]:
        raise DecodeError(f"not an rmw_zenoh QoS string: {text!r}")
    d = RMW_ZENOH_DEFAULT_QOS

    def num(s: str, default: int) -> int:
        if s == "":
            return default
        if not s.isdigit():
            raise DecodeError(f"not an rmw_zenoh QoS string: {text!r}")
        return int(s)

    (hk, depth), (dls, dlns), (lss, lsns), (lv, lvs, lvns) = comps
    return QosProfile(
        reliability=num(parts[0], d.reliability),
        durability=num(parts[1], d.durability),
        history=num(hk, d.history),
        depth=num(depth, d.depth),
        deadline=(num(dls, d.deadline[0]), num(dlns, d.deadline[1])),
        lifespan=(num(lss, d.lifespan[0]), num(lsns, d.lifespan[1])),
        liveliness=num(lv, d.liveliness),
        liveliness_lease_duration=(
            num(lvs, d.liveliness_lease_duration[0]),
            num(lvns, d.liveliness_lease_duration[1]),
        ),
    )


def mangle_name(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle_name(name: str) -> str:
    return name.replace(SLASH_REPLACEMENT, "/")


_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,254}$")
_FULL_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def node_name_problem(name: str) -> str | None:
    """Why ``name`` is not a ROS 2 node name (rmw's ``rmw_validate_node_name``: letters, digits
    and ``_``, not starting with a digit, at most 255 characters), or None."""
    if _NODE_NAME.match(name):
        return None
    return f"{name!r} is not a ROS 2 node name (letters, digits and '_', not starting with a digit)"


def topic_name_problem(topic: str) -> str | None:
    """Why ``topic`` is not a fully qualified ROS 2 topic name (rmw's
    ``rmw_validate_full_topic_name``: ``/``-separated tokens of letters, digits and ``_``, none
    starting with a digit), or None. A ``%`` could not be told from a mangled ``/``."""
    if _FULL_TOPIC.match(topic):
        return None
    return (
        f"{topic!r} is not a fully qualified ROS 2 topic name ('/'-separated tokens of letters, "
        "digits and '_', none starting with a digit)"
    )


def _join(parts: list[str]) -> str:
    for p in parts:
        if not p:
            raise ValueError(f"empty segment in a graph token: {parts!r}")
        if "/" in p:
            raise ValueError(f"unmangled '/' in a graph token segment: {p!r}")
    return "/".join(parts)


def node_token(
    domain_id: int,
    zid: str,
    node_id: int,
    node_name: str,
    *,
    namespace: str = "/",
    enclave: str = "/",
) -> str:
    """The ``NN`` token of a node (its own number as both ``nid`` and ``id``)."""
    return _join(
        [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(node_id), NODE,
         mangle_name(enclave), mangle_name(namespace), mangle_name(node_name)]
    )  # fmt: skip


def endpoint_token(
    kind: str,
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    node_name: str,
    topic: str,
    dds_type: str,
    type_hash: str,
    qos: QosProfile,
    *,
    namespace: str = "/",
    enclave: str = "/",
    qos_defaults: QosProfile | None = RMW_ZENOH_DEFAULT_QOS,
) -> str:
    """The token of a publisher (``MP``), subscription (``MS``), service (``SS``) or client
    (``SC``); ``topic`` fully qualified (``/pugs/grasps``), ``dds_type`` as in the data key
    (``pugs_msgs::msg::dds_::GraspArray_``), ``qos`` written as given (see
    :meth:`QosProfile.adapted`), its fields equal to ``qos_defaults`` left empty (None: none)."""
    if kind not in (PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT):
        raise ValueError(f"not an endpoint kind: {kind!r}")
    return _join(
        [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(entity_id), kind,
         mangle_name(enclave), mangle_name(namespace), mangle_name(node_name),
         mangle_name(topic), mangle_name(dds_type), mangle_name(type_hash), qos_to_keyexpr(qos, qos_defaults)]
    )  # fmt: skip


@dataclass(frozen=True, slots=True)
class GraphToken:
    """A parsed graph token (names demangled, as rmw_zenoh's ``Entity::make(keyexpr)`` does)."""

    domain_id: int
    zid: str
    nid: str
    id: str
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: QosProfile | None = None


def parse_token(key: str) -> GraphToken:
    """Parse a graph token as rmw_zenoh's graph cache does (``Entity::make(keyexpr)``), a little
    stricter: exactly 9 segments for a node, 13 for an endpoint; DecodeError otherwise."""
    parts = str(key).split("/")
    if len(parts) < 9 or any(not p for p in parts) or parts[0] != ADMIN_SPACE:
        raise DecodeError(f"not an rmw_zenoh graph token: {key!r}")
    if parts[5] not in ENTITY_KINDS or not parts[1].isdigit():
        raise DecodeError(f"not an rmw_zenoh graph token: {key!r}")
    if len(parts) != (9 if parts[5] == NODE else 13):
        raise DecodeError(f"wrong number of segments for a {parts[5]} token: {key!r}")
    endpoint = len(parts) == 13
    return GraphToken(
        domain_id=int(parts[1]),
        zid=parts[2],
        nid=parts[3],
        id=parts[4],
        kind=parts[5],
        enclave=demangle_name(parts[6]),
        namespace=demangle_name(parts[7]),
        node_name=demangle_name(parts[8]),
        topic=demangle_name(parts[9]) if endpoint else None,
        dds_type=demangle_name(parts[10]) if endpoint else None,
        type_hash=demangle_name(parts[11]) if endpoint else None,
        qos=keyexpr_to_qos(parts[12]) if endpoint else None,
    )
