# SPDX-License-Identifier: Apache-2.0
"""pugsd.configbase: the exact error messages of range, choice and unknown-key checks,
the limits of what the loader accepts (64-bit integers, tuples, JSON tables), and the dotted path
a cross-key check gets (a section's own ``__post_init__``), and the documented TOML it writes."""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from typing import Any

import pytest

from pugsd.config import load_config_dict
from pugsd.configbase import opt, to_dict, to_toml
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
    """Inner section."""

    b: int = opt(2, "the b key", unit="m")
    c: str = opt("x", "the c key")


@dataclass(frozen=True)
class _Section:
    """A section."""

    a: float = opt(1.0, "the a key")
    inner: _Inner = field(default_factory=_Inner)


@dataclass(frozen=True)
class _Top:
    sec: _Section = field(default_factory=_Section)
    free: dict[str, Any] = field(default_factory=lambda: {"t": {"u": 1}}, metadata={"doc": "free"})


def test_to_toml_writes_the_first_groups_then_the_rest_under_table_headings() -> None:
    text = to_toml(
        _Top(), "head", first=[("Set these", ("sec.inner.c", "free"))], rest_title="The rest",
        free_docs={"free.t.u": "the u key"},
    )  # fmt: skip
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("# ===")]
    assert lines == [
        "# head",
        "# Set these",
        "# the c key",
        'sec.inner.c = "x"',
        "# the u key",
        "free.t.u = 1",
        "# The rest",
        "# [sec] A section.",
        "# the a key",
        "sec.a = 1.0",
        "# [sec.inner] Inner section.",
        "# the b key [m]",
        "sec.inner.b = 2",
    ]
    assert tomllib.loads(text) == to_dict(_Top())


def test_to_toml_wraps_a_long_meaning_and_keeps_the_unit_on_its_last_line() -> None:
    @dataclass(frozen=True)
    class Long:
        k: float = opt(1.0, "word " * 30 + "end", unit="m")

    @dataclass(frozen=True)
    class Top:
        s: Long = field(default_factory=Long)

    comments = [ln for ln in to_toml(Top()).splitlines() if ln.startswith("# ") and "[s]" not in ln]
    assert len(comments) == 2 and all(len(ln) <= 100 for ln in comments)
    assert comments[-1].endswith("end [m]")


def test_to_toml_refuses_a_first_entry_that_names_no_key_or_one_shown_twice() -> None:
    with pytest.raises(ValueError, match=r"'sec\.inner\.d': no such key"):
        to_toml(_Top(), first=[("x", ("sec.inner.d",))])
    with pytest.raises(ValueError, match=r"'sec\.inner': no such key, or already shown"):
        to_toml(_Top(), first=[("x", ("sec.inner.b",)), ("y", ("sec.inner",))])
