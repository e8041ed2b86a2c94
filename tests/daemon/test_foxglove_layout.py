# SPDX-License-Identifier: Apache-2.0
"""docs/foxglove/pugsd-layout.json shows what the daemon publishes: every topic it names is a
default [topics] topic, the cloud is coloured by a field the PointCloud2 has, the 3D panel
follows the frame the outputs are in, the diagnostics panels read the node the daemon names, and
every panel of the layout tree is configured."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pugsd.config import PugsdConfig
from pugsd.wire import codec
from pugsd.wire.topics import INPUT_ROLES, OUTPUT_ROLES

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove" / "pugsd-layout.json"


def _leaves(node: Any) -> list[str]:
    if isinstance(node, str):
        return [node]
    return _leaves(node["first"]) + _leaves(node["second"])


def test_the_layout_names_the_daemons_topics_and_fields() -> None:
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]
    assert sorted(_leaves(layout["layout"])) == sorted(panels)
    cfg = PugsdConfig()
    topics = {getattr(cfg.topics, r) for r in INPUT_ROLES + OUTPUT_ROLES}
    named: set[str] = set()
    for panel in panels.values():
        named |= set(panel.get("topics", {}))
        named |= {v for k, v in panel.get("imageMode", {}).items() if k.endswith("Topic")}
        if "topicToRender" in panel:
            named.add(panel["topicToRender"])
        if "topicPath" in panel:
            named.add(panel["topicPath"].split(".", 1)[0])
    assert named <= topics, named - topics
    three_d = panels["3D!pugs"]
    assert three_d["followTf"] == cfg.daemon.world_frame
    cloud = three_d["topics"][cfg.topics.cloud]
    fields = codec.decode_cloud(
        codec.encode_cloud(np.zeros((1, 3)), 0, sigma2_occ=np.zeros(1), pugs_confidence=np.zeros(1))
    ).fields
    assert cloud["colorField"] == "sigma2_occ" and "sigma2_occ" in fields
    for name in ("DiagnosticSummary!pugs", "DiagnosticStatusPanel!pugs"):
        assert panels[name]["topicToRender"] == cfg.topics.diagnostics
    assert panels["DiagnosticStatusPanel!pugs"]["selectedName"] == f"{cfg.daemon.node_name}: health"
