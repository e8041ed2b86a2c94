# SPDX-License-Identifier: Apache-2.0
"""Integer keys: a TOML integer beyond 64 bits is a ConfigError naming the key. tomllib's integers
are unbounded: ``arm.telemetry.status_every = 1000...0`` (400 digits) passed its ``ge=1`` check
and was an OverflowError traceback from the arm's serial-load check (check-config, dump-config,
run), not a one-line error."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pugsd.cli import main
from pugsd.config import PugsdConfig, config_warnings, load_config_dict
from pugsd.errors import ConfigError


def _int_keys(cls: type, prefix: str = "") -> list[tuple[str, bool]]:
    """(dotted key, is a tuple of integers) of every integer key."""
    out = []
    for name, tp in typing.get_type_hints(cls).items():
        dotted = f"{prefix}{name}"
        if dataclasses.is_dataclass(tp):
            out += _int_keys(tp, dotted + ".")  # type: ignore[arg-type]
        elif tp is int or (typing.get_origin(tp) is tuple and typing.get_args(tp)[0] is int):
            out.append((dotted, tp is not int))
    return out


INT_KEYS = _int_keys(PugsdConfig)
KEYS = [k for k, _ in INT_KEYS]
HUGE = st.one_of(st.integers(min_value=1 << 63), st.integers(max_value=-(1 << 63) - 1))


def _with(key: str, value: Any) -> dict[str, Any]:
    data: dict[str, Any] = {}
    node = data
    *parents, last = key.split(".")
    for p in parents:
        node = node.setdefault(p, {})
    node[last] = value
    return data


def test_there_are_integer_keys() -> None:
    assert "arm.telemetry.status_every" in KEYS and len(KEYS) > 20


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(st.sampled_from(INT_KEYS), st.one_of(st.integers(), HUGE))
def test_any_integer_in_an_integer_key_loads_or_is_a_config_error(key: tuple[str, bool], value: int) -> None:
    name, is_tuple = key
    try:
        cfg = load_config_dict(_with(name, [value] if is_tuple else value))
        config_warnings(cfg)
    except ConfigError:
        return
    assert -(1 << 63) <= value < (1 << 63)


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(st.sampled_from(KEYS), HUGE)
def test_an_integer_beyond_64_bits_is_a_config_error_naming_the_key(key: str, value: int) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config_dict(_with(key, value))


def test_status_every_too_large_for_a_float_is_a_config_error(capsys: pytest.CaptureFixture[str]) -> None:
    override = "arm.telemetry.status_every=1" + "0" * 400
    with pytest.raises(ConfigError, match=r"arm\.telemetry\.status_every: expected a 64-bit integer"):
        load_config_dict({}, [override])
    assert main(["dump-config", "--set", override]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pugsd dump-config: error: arm.telemetry.status_every") and err.count("\n") == 1
