# SPDX-License-Identifier: Apache-2.0
"""An override whose VALUE holds more than one TOML statement is refused, not partly dropped."""

from __future__ import annotations

import pytest

from pugsd.config import parse_override
from pugsd.errors import ConfigError


@pytest.mark.parametrize("text", ["grasp.top_k=3\ngrasp.gamma=9", "grasp.top_k=3\n[daemon]\nprefix='x'"])
def test_a_value_with_a_second_toml_statement_is_refused(text: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_override(text)
    assert str(exc.value) == f"override {text!r}: VALUE must be a single TOML value"


def test_a_single_value_with_a_comment_still_loads() -> None:
    assert parse_override("grasp.top_k=3 # three") == ("grasp.top_k", 3)
