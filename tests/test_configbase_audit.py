# SPDX-License-Identifier: Apache-2.0
"""configbase (mutation audit): the exact error messages of range, choice and unknown-key checks,
the limits of what the loader accepts (64-bit integers, tuples, JSON tables), and the dotted path
a cross-key check gets (a section's own ``__post_init__``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import pytest

from pugsd.config import load_config_dict
from pugsd.configbase import build, opt
from pugsd.errors import ConfigError


def _error(data: dict[str, Any], overrides: tuple[str, ...] = ()) -> str:
    with pytest.raises(ConfigError) as exc:
        load_config_dict(data, list(overrides))
    return str(exc.value)


def test_range_and_choice_messages_name_the_key_the_value_and_the_limit() -> None:
    assert _error({"daemon": {"pose_max_gap_s": 1e300}}) == (
        "daemon.pose_max_gap_s: 1e+300 is above the maximum 3600.0"
    )
    assert _error({"cubature": {"variance_form": "B"}}) == (
        "cubature.variance_form: 'B' is not one of ['total', 'paper_literal']"
    )
    assert _error({"fof": {"k_neighbours": 0}}) == "fof.k_neighbours: 0 is below the minimum 1"


def test_an_exclusive_upper_bound_refuses_the_bound_itself() -> None:
    assert _error({"grasp": {"friction_cone_deg": 90}}) == (
        "grasp.friction_cone_deg: 90.0 must be less than 90.0"
    )
    assert load_config_dict({"grasp": {"friction_cone_deg": 89.9}}).grasp.friction_cone_deg == 89.9


def test_an_unknown_key_lists_the_sections_known_keys() -> None:
    known = sorted(f.name for f in dataclasses.fields(load_config_dict({}).fof))
    assert _error({"fof": {"bogus_key_xyz": 1}}) == (
        f"fof.bogus_key_xyz: unknown key (known: {', '.join(known)})"
    )


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_number_in_the_zenoh_table_is_a_config_error(value: str) -> None:
    """zenoh reads JSON5; Python's json would write NaN/Infinity, which zenoh's parser refuses."""
    assert _error({}, (f"zenoh.scouting.timeout={value}",)).startswith("zenoh: not representable as JSON")


def test_a_check_of_the_whole_config_keeps_its_message_unprefixed() -> None:
    """The top-level cross-key check (no dotted path of its own) names its keys itself."""
    msg = _error({"topics": {"ros_graph_tokens": "on"}, "daemon": {"node_name": "a-b"}})
    assert msg.startswith("topics.ros_graph_tokens = 'on', but daemon.node_name: 'a-b' is not"), msg


def test_a_cross_key_message_that_does_not_start_with_a_key_gets_a_colon() -> None:
    assert _error({"arm": {"can": {"tx_base": 0x100, "rx_base": 0x100}}}) == (
        "arm.can: tx_base and rx_base must differ"
    )


# a toy section: the loader is generic, so its corners are checked on a section made for them


@dataclass(frozen=True)
class _Inner:
    lo: tuple[float, ...] = opt((0.0, 1.0), "limits", ge=0.0)
    mode: str = opt("a", "a mode")

    def __post_init__(self) -> None:
        if self.mode == "item":
            raise ConfigError("lo[1]: below lo[0]")
        if self.mode == "word":
            raise ConfigError("bounds: inverted")  # 'bounds' is no key of this section
        if self.mode == "prose":
            raise ConfigError("lo and mode disagree")


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    n: int = opt(0, "a 64-bit integer")


def _build_error(data: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as exc:
        build(_Outer, data)
    return str(exc.value)


@pytest.mark.parametrize(
    ("mode", "message"),
    [
        ("item", "inner.lo[1]: below lo[0]"),
        ("word", "inner: bounds: inverted"),
        ("prose", "inner: lo and mode disagree"),
    ],
)
def test_a_cross_key_error_is_prefixed_with_the_sections_path(mode: str, message: str) -> None:
    assert _build_error({"inner": {"mode": mode}}) == message


def test_every_item_of_a_tuple_is_range_checked() -> None:
    assert build(_Outer, {"inner": {"lo": [0, 2.5]}}).inner.lo == (0.0, 2.5)
    assert _build_error({"inner": {"lo": [0.0, -1.0]}}) == "inner.lo: -1.0 is below the minimum 0.0"


@pytest.mark.parametrize("n", [-(1 << 63), (1 << 63) - 1])
def test_both_ends_of_the_64_bit_range_load(n: int) -> None:
    assert build(_Outer, {"n": n}).n == n


@pytest.mark.parametrize("n", [-(1 << 63) - 1, 1 << 63])
def test_one_past_either_end_of_the_64_bit_range_is_refused(n: int) -> None:
    assert _build_error({"n": n}) == "n: expected a 64-bit integer, got one of 64 bits"


def test_a_type_the_loader_does_not_check_is_a_config_error_not_a_silent_pass() -> None:
    @dataclass(frozen=True)
    class Pair:
        xy: tuple[int, int] = opt((0, 0), "a fixed-length tuple")

    @dataclass(frozen=True)
    class Listed:
        xs: list = field(default_factory=list)  # type: ignore[type-arg]

    with pytest.raises(ConfigError, match=r"^xy: unsupported config type tuple\[int, int\]$"):
        build(Pair, {"xy": [1, 2]})
    with pytest.raises(ConfigError, match=r"^xs: unsupported config type list$"):
        build(Listed, {"xs": [1]})
