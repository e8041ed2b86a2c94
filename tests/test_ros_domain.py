# SPDX-License-Identifier: Apache-2.0
"""The ROS domain: a --set override, then ROS_DOMAIN_ID (when set and not empty), then [topics]
domain_id of the file, then 0; a ROS_DOMAIN_ID that is not a domain is refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from pugsd.config import load_config
from pugsd.errors import ConfigError
from pugsd.wire.topics import key_for


def test_ros_domain_id_precedence(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "pugsd.toml"
    path.write_text("[topics]\ndomain_id = 5\n")
    assert load_config(path, env={}).topics.domain_id == 5
    assert load_config(path, env={"ROS_DOMAIN_ID": ""}).topics.domain_id == 5  # empty: unset
    cfg = load_config(path, env={"ROS_DOMAIN_ID": " 7 "})
    assert cfg.topics.domain_id == 7 and key_for(cfg.topics, "grasps").startswith("7/pugs/grasps/")
    assert load_config(path, ["topics.domain_id=3"], env={"ROS_DOMAIN_ID": "7"}).topics.domain_id == 3
    assert load_config(None, env={"ROS_DOMAIN_ID": "42"}).topics.domain_id == 42
    monkeypatch.setenv("ROS_DOMAIN_ID", "9")  # the process environment by default
    assert load_config(path).topics.domain_id == 9
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert load_config(None).topics.domain_id == 0


@pytest.mark.parametrize("bad", ["abc", "-1", "233", "1.5"])
def test_a_ros_domain_id_that_is_no_domain_is_refused(bad: str) -> None:
    with pytest.raises(ConfigError, match=f"ROS_DOMAIN_ID={bad!r} is not a domain id"):
        load_config(None, env={"ROS_DOMAIN_ID": bad})
