# SPDX-License-Identifier: Apache-2.0
"""Typed, frozen config sections and a strict TOML loader (no silent fallbacks).

Each config table is a frozen dataclass whose fields are declared with :func:`opt`, which carries
the documentation (meaning and unit) and the range checks. :func:`build` turns a nested dict (from
``tomllib``) into the dataclass, rejecting unknown keys, wrong types and out-of-range values with
the dotted path of the offending key. :func:`to_toml` writes the documented reference file.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import re
import textwrap
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

from pugsd.errors import ConfigError

T = TypeVar("T")


def opt(
    default: Any,
    doc: str,
    *,
    unit: str = "",
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """Declare a config field with its documentation, unit and range."""
    meta = {"doc": doc, "unit": unit, "ge": ge, "gt": gt, "le": le, "lt": lt, "choices": choices}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        raise TypeError("opt() takes immutable scalar or tuple defaults; use a default_factory")
    return dataclasses.field(default=default, metadata=meta)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """Check ``value`` against the annotation ``tp`` (a section, ``tuple[X, ...]``, ``dict``, ``float``,
    ``int``, ``bool`` or ``str``); widen int to float; recurse into sections."""
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{path}: expected a table, got {type(value).__name__}")
        return build(tp, value, path)
    if origin is tuple:  # tuple[X, ...]: a TOML array of any length
        args = get_args(tp)
        if len(args) != 2 or args[1] is not Ellipsis:
            raise ConfigError(f"{path}: unsupported config type {tp}")
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected an array, got {type(value).__name__}")
        return tuple(_coerce(v, args[0], f"{path}[{i}]") for i, v in enumerate(value))
    if origin in (dict,) or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{path}: expected a table, got {type(value).__name__}")
        try:
            return json.loads(json.dumps(dict(value), allow_nan=False))
        except (TypeError, ValueError) as exc:  # TOML dates and times, nan and inf
            raise ConfigError(f"{path}: not representable as JSON ({exc})") from None
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {type(value).__name__}")
        try:
            number = float(value)
        except OverflowError:  # a TOML integer beyond the float range (tomllib's are unbounded)
            raise ConfigError(f"{path}: expected a finite number, got an integer beyond 1.8e308") from None
        if not math.isfinite(number):  # TOML's nan and inf: no setting means either
            raise ConfigError(f"{path}: expected a finite number, got {value}")
        return number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {type(value).__name__}")
        if not -(1 << 63) <= value < (1 << 63):  # tomllib's are unbounded; no setting needs more
            raise ConfigError(f"{path}: expected a 64-bit integer, got one of {value.bit_length()} bits")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {type(value).__name__}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {type(value).__name__}")
        return value
    raise ConfigError(f"{path}: unsupported config type {_type_name(tp)}")


def check_range(value: Any, meta: Mapping[str, Any], path: str) -> None:
    """Apply the ``ge/gt/le/lt/choices`` limits of a field (numbers and tuples of numbers)."""
    items = value if isinstance(value, tuple) else (value,)
    for v in items:
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        if meta.get("ge") is not None and not v >= meta["ge"]:
            raise ConfigError(f"{path}: {v} is below the minimum {meta['ge']}")
        if meta.get("gt") is not None and not v > meta["gt"]:
            raise ConfigError(f"{path}: {v} must be greater than {meta['gt']}")
        if meta.get("le") is not None and not v <= meta["le"]:
            raise ConfigError(f"{path}: {v} is above the maximum {meta['le']}")
        if meta.get("lt") is not None and not v < meta["lt"]:
            raise ConfigError(f"{path}: {v} must be less than {meta['lt']}")
    if meta.get("choices") is not None and value not in meta["choices"]:
        raise ConfigError(f"{path}: {value!r} is not one of {list(meta['choices'])}")


def build(cls: type[T], data: Mapping[str, Any], path: str = "") -> T:
    """Build the frozen section ``cls`` from ``data``; unknown keys and bad values raise ConfigError."""
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{path}.{key}" if path else key
        if key not in fields:
            close = difflib.get_close_matches(key, list(fields), n=1)
            hint = f"; did you mean {close[0]}?" if close else ""
            raise ConfigError(f"{dotted}: unknown key{hint} (known: {', '.join(sorted(fields))})")
        coerced = _coerce(value, hints[key], dotted)
        default_factory = fields[key].default_factory
        if isinstance(coerced, dict) and default_factory is not dataclasses.MISSING:
            # free-form tables (zenoh) are merged over their defaults, so a partial table keeps
            # the safe defaults (loopback, scouting off) for every key it does not set
            coerced = deep_merge(default_factory(), coerced)
        check_range(coerced, fields[key].metadata, dotted)
        kwargs[key] = coerced
    try:
        obj = cls(**kwargs)
    except ConfigError as exc:
        # a check across keys names the key it refuses first ("T_B_C_quat_xyzw: ..."): give it
        # the dotted path like every other error ("daemon.T_B_C_quat_xyzw: ...")
        msg = str(exc)
        head = re.match(r"[A-Za-z_][A-Za-z0-9_]*", msg)
        names_key = head is not None and head.group(0) in fields and msg[head.end() :][:1] in (":", "[")
        sep = "." if names_key else ": "
        raise ConfigError(f"{path}{sep}{msg}" if path else msg) from None
    return obj


def deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` merged into ``base`` recursively (tables merge, everything else replaces)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def to_dict(obj: Any) -> Any:
    """A section as plain nested dicts and lists (TOML-ready)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


@dataclasses.dataclass(frozen=True)
class _Key:
    path: str  # dotted: "grasp.gripper.max_width_m"
    table: str  # "grasp.gripper"
    value: Any  # TOML-ready (to_dict)
    comment: str  # "meaning [unit]"; empty for free-form tables


def _keys(obj: Any, table: str, titles: dict[str, str], free_docs: Mapping[str, str]) -> list[_Key]:
    """Every key under ``obj`` in declaration order; ``titles`` gets each table's heading."""
    out: list[_Key] = []
    if dataclasses.is_dataclass(obj):
        doc = (type(obj).__doc__ or "").strip()
        titles[table] = doc.splitlines()[0] if doc else ""
        for f in dataclasses.fields(obj):
            v, path = getattr(obj, f.name), f"{table}.{f.name}"
            if dataclasses.is_dataclass(v) or isinstance(v, dict):
                if isinstance(v, dict):
                    titles[path] = f.metadata.get("doc", "")
                out.extend(_keys(v, path, titles, free_docs))
                continue
            unit = f.metadata.get("unit", "")
            comment = f.metadata.get("doc", "") + (f"\xa0[{unit}]" if unit else "")  # kept on its line
            out.append(_Key(path, table, to_dict(v), comment))
    else:  # a free-form table (zenoh's), under one heading; documented by free_docs, if at all

        def flat(d: Mapping[str, Any], prefix: str) -> None:
            for k, v in d.items():
                if isinstance(v, dict):
                    flat(v, f"{prefix}.{k}")
                else:
                    path = f"{prefix}.{k}"
                    out.append(_Key(path, table, to_dict(v), free_docs.get(path, "")))

        flat(obj, table)
    return out


def _rule(title: str) -> list[str]:
    bar = "# " + "=" * 98
    return ["", bar, *_comment(title), bar]


def _comment(text: str) -> list[str]:
    """``text`` as comment lines of at most 100 characters (a no-break space joins, then is a space)."""
    lines = textwrap.wrap(
        text, width=100, initial_indent="# ", subsequent_indent="# ", break_long_words=False,
        break_on_hyphens=False,
    )  # fmt: skip
    return [line.replace("\xa0", " ") for line in lines]


def _emit(lines: list[str], key: _Key) -> None:
    lines.extend(_comment(key.comment))
    lines.append(f"{key.path} = {_toml_value(key.value)}")


def to_toml(
    obj: Any,
    header: str = "",
    first: Sequence[tuple[str, Sequence[str]]] = (),
    rest_title: str = "",
    free_docs: Mapping[str, str] | None = None,
) -> str:
    """Render a top-level config object as a documented TOML file of dotted keys
    (``section.key = value``, the form an override takes), each under its meaning and unit.

    The groups of ``first`` come first, each under its title and in its order; an entry names a
    key or a whole table (every key under it). Every other key follows under ``rest_title``, in
    declaration order, under a heading per table. ``free_docs`` documents keys of free-form
    tables (dotted path to meaning). Dotted keys let one table's keys appear in both
    parts, which ``[table]`` headers cannot: TOML defines a header's table once.
    """
    titles: dict[str, str] = {}
    keys: list[_Key] = []
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if not dataclasses.is_dataclass(v):
            titles[f.name] = f.metadata.get("doc", "")
        keys.extend(_keys(v, f.name, titles, free_docs or {}))
    lines: list[str] = [f"# {h}" if h else "#" for h in header.splitlines()]
    shown: set[str] = set()
    for title, entries in first:
        lines.extend([*_rule(title), ""])
        for entry in entries:
            chosen = [k for k in keys if k.path == entry or k.path.startswith(entry + ".")]
            if not chosen or any(k.path in shown for k in chosen):
                raise ValueError(f"{entry!r}: no such key, or already shown")
            for k in chosen:
                _emit(lines, k)
                shown.add(k.path)
    rest = [k for k in keys if k.path not in shown]
    if rest and first:
        lines.extend(_rule(rest_title))
    table = None
    for k in rest:
        if k.table != table:
            table = k.table
            title = titles.get(table, "")
            lines.extend(["", *_comment(f"[{table}]" + (f" {title}" if title else ""))])
        _emit(lines, k)
    return "\n".join(lines).lstrip("\n") + "\n"
