# SPDX-License-Identifier: Apache-2.0
"""Config validation at its edges: a TOML boolean is not an integer, an empty depth band and an
SVGP of fewer than 8 inducing points are refused, each with the dotted path of the key."""

from __future__ import annotations

import pytest

from pugsd.config import load_config_dict
from pugsd.errors import ConfigError


@pytest.mark.parametrize("key", ["fof.k_neighbours", "svgp.seed", "queues.stereo"])
@pytest.mark.parametrize("value", [True, False])
def test_a_boolean_is_not_an_integer(key: str, value: bool) -> None:
    """Python's bool is an int: ``k_neighbours = true`` would load as 1 without the check."""
    section, name = key.split(".")
    with pytest.raises(ConfigError, match=rf"{section}\.{name}: expected an integer, got bool"):
        load_config_dict({section: {name: value}})


def test_the_depth_band_must_not_be_empty() -> None:
    with pytest.raises(ConfigError, match=r"stereo\.max_depth_m: must exceed min_depth_m"):
        load_config_dict({"stereo": {"min_depth_m": 1.0, "max_depth_m": 1.0}})
    cfg = load_config_dict({"stereo": {"min_depth_m": 1.0, "max_depth_m": 1.001}})
    assert cfg.stereo.max_depth_m == 1.001


@pytest.mark.parametrize("m", [1, 7])
def test_num_inducing_is_zero_or_at_least_eight(m: int) -> None:
    with pytest.raises(ConfigError, match=rf"svgp\.num_inducing: 0 \(auto\) or at least 8, got {m}"):
        load_config_dict({"svgp": {"num_inducing": m}})
    assert load_config_dict({"svgp": {"num_inducing": 8}}).svgp.num_inducing == 8
    assert load_config_dict({"svgp": {"num_inducing": 0}}).svgp.num_inducing == 0
