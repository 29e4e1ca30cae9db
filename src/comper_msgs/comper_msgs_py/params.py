"""Hyper-parameter specifications: one place per package defines each default (no ROS imports).

A configuration is a frozen dataclass whose fields are made with :func:`param`; each carries its
description, the thesis value and section it comes from, and its allowed values. Nodes declare
ROS parameters from it (``comper_msgs_py.ros_params.declare_config``), command-line tools build
``--help`` from it, and cores read the typed values.

    @dataclass(frozen=True)
    class MemoryConfig:
        delta: float = param(1e-4, "similarity threshold on squared L2 distance",
                             thesis="1e-4 (section 5.3.2); Table 34 lists 0.0", minimum=0.0)
"""
from __future__ import annotations

import dataclasses
import typing
from typing import Any

__all__ = ["param", "ConfigError", "config_from_dict", "describe", "spec_of", "config_to_dict"]


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


def param(default: Any, description: str, *, thesis: str | None = None,
          choices: tuple | None = None, minimum: float | None = None,
          maximum: float | None = None, deviation: str | None = None) -> Any:
    """A dataclass field with documentation and validation metadata.

    thesis: the thesis value and where it is given (shown in descriptions and docs).
    deviation: why the default differs from the thesis text (method.md section 6), if it does.
    """
    meta = {"description": description, "thesis": thesis, "choices": choices,
            "minimum": minimum, "maximum": maximum, "deviation": deviation}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: typing.cast(Any, type(default)(default)),
                                 metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def spec_of(cls) -> list[tuple[dataclasses.Field, Any, type]]:
    """(field, default, python type) for each field of a config dataclass."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out.append((f, default, hints[f.name]))
    return out


def describe(f: dataclasses.Field) -> str:
    m = f.metadata
    text = m.get("description", "")
    if m.get("choices"):
        text += f" One of: {', '.join(map(str, m['choices']))}."
    if m.get("thesis"):
        text += f" Thesis: {m['thesis']}."
    if m.get("deviation"):
        text += f" Deviation: {m['deviation']}."
    return text


def _coerce(name: str, value: Any, typ: type) -> Any:
    origin = typing.get_origin(typ)
    try:
        if typ is bool:
            if isinstance(value, str):
                if value.lower() in ("true", "1", "yes"):
                    return True
                if value.lower() in ("false", "0", "no"):
                    return False
                raise ValueError(value)
            if not isinstance(value, (bool, int)):
                raise ValueError(value)
            return bool(value)
        if typ is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            if isinstance(value, bool):
                raise ValueError(value)
            return int(value)
        if typ is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if typ is str:
            return str(value)
        if origin in (list, tuple):
            (item,) = set(typing.get_args(typ)) - {Ellipsis} or {str}
            seq = value.split(",") if isinstance(value, str) else list(value)
            return type(origin())(_coerce(name, v, item) for v in seq if v != "")
    except (TypeError, ValueError):
        raise ConfigError(f"parameter '{name}': cannot use {value!r} as {getattr(typ, '__name__', typ)}") from None
    return value


def _check(f: dataclasses.Field, value: Any) -> None:
    m = f.metadata
    if m.get("choices") and value not in m["choices"]:
        raise ConfigError(f"parameter '{f.name}': {value!r} is not one of {list(m['choices'])}")
    if m.get("minimum") is not None and value < m["minimum"]:
        raise ConfigError(f"parameter '{f.name}': {value!r} is below the minimum {m['minimum']}")
    if m.get("maximum") is not None and value > m["maximum"]:
        raise ConfigError(f"parameter '{f.name}': {value!r} is above the maximum {m['maximum']}")


def config_from_dict(cls, values: dict | None = None, *, ignore_unknown: bool = False):
    """Build and validate a config from a mapping (YAML, ROS parameters, CLI)."""
    values = dict(values or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - known
    if unknown and not ignore_unknown:
        raise ConfigError(f"unknown parameter(s) {sorted(unknown)}; known: {sorted(known)}")
    kwargs = {}
    for f, default, typ in spec_of(cls):
        value = _coerce(f.name, values[f.name], typ) if f.name in values else default
        _check(f, value)
        kwargs[f.name] = value
    return cls(**kwargs)


def config_to_dict(cfg) -> dict:
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}
