# SPDX-License-Identifier: Apache-2.0
"""The ROS 2 (Jazzy) type store with pugsd's own ``pugs_msgs`` types and the services pugsd
serves registered.

Type names are ROS 2 style (``sensor_msgs/msg/Image``, ``std_srvs/srv/Trigger``). :func:`msgdef`
gives the ``ros2msg`` schema text used in MCAP files and :func:`type_hash` the RIHS01 hash used in
rmw_zenoh keys.

A service ``pkg/srv/Name`` is registered as rosidl generates it: ``Name_Request`` and
``Name_Response`` (the two halves of the ``.srv``), ``Name_Event`` (``service_msgs/ServiceEventInfo
info``, ``Name_Request[<=1] request``, ``Name_Response[<=1] response``) and ``Name`` itself
(``request_message``, ``response_message``, ``event_message``), whose RIHS01 hash is the one in
the service's rmw_zenoh key and liveliness token.
"""

from __future__ import annotations

import functools
from importlib import resources
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

#: message types of pugsd's own package (``pugsd/msg/*.msg``)
PUGS_MSGS = ("pugs_msgs/msg/Grasp", "pugs_msgs/msg/GraspArray")

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POINT_FIELD = "sensor_msgs/msg/PointField"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
STRING = "std_msgs/msg/String"
GRASP = "pugs_msgs/msg/Grasp"
GRASP_ARRAY = "pugs_msgs/msg/GraspArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

TRIGGER = "std_srvs/srv/Trigger"
GET_GRASPS = "pugs_msgs/srv/GetGrasps"
EXECUTE_GRASP = "pugs_msgs/srv/ExecuteGrasp"
#: service types of pugsd's own package (``pugsd/srv/*.srv``)
PUGS_SRVS = (GET_GRASPS, EXECUTE_GRASP)
#: std_srvs/srv/Trigger.srv (ros2/common_interfaces; comments are not part of the hash)
TRIGGER_SRV = "---\nbool success\nstring message\n"
SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"


def msg_definition_text(name: str) -> str:
    """The text of ``pugsd/msg/<name>.msg`` (packaged with pugsd)."""
    return resources.files("pugsd").joinpath("msg", f"{name}.msg").read_text(encoding="utf-8")


def srv_definition_text(name: str) -> str:
    """The text of ``pugsd/srv/<name>.srv`` (packaged with pugsd)."""
    return resources.files("pugsd").joinpath("srv", f"{name}.srv").read_text(encoding="utf-8")


def service_types(typename: str, srv_text: str) -> dict[str, Any]:
    """The rosbags typesdict of service ``pkg/srv/Name`` from its ``.srv`` text: request,
    response, event and the service itself (see the module docstring)."""
    lines = srv_text.splitlines()
    cut = [i for i, line in enumerate(lines) if line.strip() == "---"]
    if len(cut) != 1:
        raise ValueError(f"{typename}: expected one '---' line between request and response")
    head, tail = "\n".join(lines[: cut[0]]) + "\n", "\n".join(lines[cut[0] + 1 :]) + "\n"
    req, resp, event = typename + "_Request", typename + "_Response", typename + "_Event"
    out: dict[str, Any] = {}
    for name, text in ((req, head), (resp, tail)):
        # rosbags files a name outside msg/ under <pkg>/<kind>/msg/: parse it under msg/, rename
        pkg, _, short = name.split("/")
        parsed = get_types_from_msg(text, f"{pkg}/msg/{short}")
        out[name] = parsed[f"{pkg}/msg/{short}"]
    one = lambda t: (Nodetype.SEQUENCE, ((Nodetype.NAME, t), 1))  # noqa: E731  (T[<=1])
    out[event] = ([], [("info", (Nodetype.NAME, SERVICE_EVENT_INFO)), ("request", one(req)),
                       ("response", one(resp))])  # fmt: skip
    out[typename] = ([], [("request_message", (Nodetype.NAME, req)),
                          ("response_message", (Nodetype.NAME, resp)),
                          ("event_message", (Nodetype.NAME, event))])  # fmt: skip
    return out


def _service_defs() -> dict[str, Any]:
    """Every service pugsd serves, as one typesdict."""
    out = service_types(TRIGGER, TRIGGER_SRV)
    for full in PUGS_SRVS:
        out.update(service_types(full, srv_definition_text(full.rsplit("/", 1)[1])))
    return out


def _register_pugs(ts: Any) -> Any:
    for full in PUGS_MSGS:
        ts.register(get_types_from_msg(msg_definition_text(full.rsplit("/", 1)[1]), full))
    ts.register(_service_defs())
    return ts


@functools.cache
def typestore() -> Any:
    """The shared Jazzy typestore (built once; thread-safe to read afterwards)."""
    return _register_pugs(get_typestore(Stores.ROS2_JAZZY))


def is_service(typename: str) -> bool:
    parts = typename.split("/")
    return len(parts) == 3 and parts[1] == "srv"


@functools.cache
def _service_hash_store() -> Any:
    """A typestore for service hashes: rosbags declares ``ServiceEventInfo.client_gid`` as
    ``char[16]`` (type id 13), while rosidl reads the ``char`` of a ``.msg`` as ``uint8``
    (rosidl_adapter's ``MSG_TYPE_TO_IDL``), which every service's hash covers through its event
    message. Corrected here (and only here), the hashes match ROS's (the goldens in
    tests/wire/test_services.py)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    consts, fields = ts.fielddefs[SERVICE_EVENT_INFO]
    ts.fielddefs[SERVICE_EVENT_INFO] = (
        consts,
        [
            (n, (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), d[1][1])))
            if d[0] == Nodetype.ARRAY and d[1][0] == (Nodetype.BASE, ("char", 0))
            else (n, d)
            for n, d in fields
        ],
    )
    return _register_pugs(ts)


def service_type_hash(store: Any, typename: str) -> str:
    """RIHS01 of service ``typename`` registered in ``store`` (see :func:`_service_hash_store`)."""
    return str(store.hash_rihs01(typename))


def msg_class(typename: str) -> Any:
    """The generated dataclass of a message type (``KeyError`` if unknown)."""
    return typestore().types[typename]


@functools.cache
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex>`` of a message or service type (Jazzy and later)."""
    if is_service(typename):
        return service_type_hash(_service_hash_store(), typename)
    return str(typestore().hash_rihs01(typename))


@functools.cache
def msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text (with dependencies) for MCAP."""
    return str(typestore().generate_msgdef(typename, ros_version=2)[0])


def known_type(typename: str) -> bool:
    return typename in typestore().types
