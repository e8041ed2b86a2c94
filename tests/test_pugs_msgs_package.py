# SPDX-License-Identifier: Apache-2.0
"""ros2/pugs_msgs, the ROS 2 interface package for consumers of /pugs/grasps and pugsd's
services, cannot drift from pugsd/msg and pugsd/srv: its msg and srv files are byte-identical
copies (so the RIHS01 hashes in the rmw_zenoh keys match), and package.xml and CMakeLists.txt name
every msg, every srv and every package they use.
(No ROS 2 is installed here: the package itself is not built by the tests.)"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

from pugsd.wire.types import PUGS_MSGS, PUGS_SRVS, msg_definition_text, srv_definition_text

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "pugsd" / "msg"
SRV = ROOT / "pugsd" / "srv"
PKG = ROOT / "ros2" / "pugs_msgs"
_ARRAY = re.compile(r"\[[^\]]*\]$")


def msg_names() -> list[str]:
    return sorted(p.stem for p in SRC.glob("*.msg"))


def srv_names() -> list[str]:
    return sorted(p.stem for p in SRV.glob("*.srv"))


def used_packages() -> set[str]:
    """Packages of the field types of pugsd's msgs (``pkg/Type`` or ``pkg/msg/Type``), besides
    pugs_msgs itself."""
    out: set[str] = set()
    files = [SRC / f"{n}.msg" for n in msg_names()] + [SRV / f"{n}.srv" for n in srv_names()]
    for path in files:
        for line in path.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            if not line or line == "---":
                continue
            ftype = _ARRAY.sub("", line.split()[0])
            if "/" in ftype:
                out.add(ftype.split("/", 1)[0])
    return out - {"pugs_msgs"}


def test_msg_files_are_byte_identical_copies() -> None:
    names = msg_names()
    assert names == ["Grasp", "GraspArray"] == sorted(t.rsplit("/", 1)[1] for t in PUGS_MSGS)
    assert sorted(p.stem for p in (PKG / "msg").iterdir()) == names
    for name in names:
        assert (PKG / "msg" / f"{name}.msg").read_bytes() == (SRC / f"{name}.msg").read_bytes(), name
        assert msg_definition_text(name) == (PKG / "msg" / f"{name}.msg").read_text(encoding="utf-8")


def test_srv_files_are_byte_identical_copies() -> None:
    names = srv_names()
    assert names == ["ExecuteGrasp", "GetGrasps"] == sorted(t.rsplit("/", 1)[1] for t in PUGS_SRVS)
    assert sorted(p.stem for p in (PKG / "srv").iterdir()) == names
    for name in names:
        assert (PKG / "srv" / f"{name}.srv").read_bytes() == (SRV / f"{name}.srv").read_bytes(), name
        assert srv_definition_text(name) == (PKG / "srv" / f"{name}.srv").read_text(encoding="utf-8")


def test_package_xml_names_build_tools_and_dependencies() -> None:
    root = ET.parse(PKG / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"

    def texts(tag: str) -> set[str]:
        return {(e.text or "").strip() for e in root.findall(tag)}

    assert texts("name") == {"pugs_msgs"}
    assert {"ament_cmake", "rosidl_default_generators"} <= texts("buildtool_depend")
    assert texts("exec_depend") >= {"rosidl_default_runtime"}
    assert texts("member_of_group") == {"rosidl_interface_packages"}
    assert used_packages() == {"std_msgs", "geometry_msgs"}
    assert texts("depend") == used_packages()
    assert root.find("export/build_type") is not None
    assert (root.findtext("export/build_type") or "").strip() == "ament_cmake"
    m = root.find("maintainer")
    assert m is not None and m.get("email") and root.findtext("license")


def test_cmakelists_generates_every_msg_with_its_dependencies() -> None:
    text = (PKG / "CMakeLists.txt").read_text()
    assert re.search(r"^project\(pugs_msgs\)$", text, flags=re.M)
    call = re.search(r"rosidl_generate_interfaces\(\$\{PROJECT_NAME\}(.*?)\)", text, flags=re.S)
    assert call is not None
    args = call.group(1)
    listed = re.findall(r'"((?:msg|srv)/[^"]+\.(?:msg|srv))"', args)
    assert listed == [f"msg/{n}.msg" for n in msg_names()] + [f"srv/{n}.srv" for n in srv_names()]
    deps = re.search(r"DEPENDENCIES([^)]*)", args)
    assert deps is not None and set(deps.group(1).split()) == used_packages()
    for pkg in ("ament_cmake", "rosidl_default_generators", *sorted(used_packages())):
        assert f"find_package({pkg} REQUIRED)" in text
    assert "ament_package()" in text
