"""Declare a node's ROS parameters from a config dataclass (see comper_msgs_py.params).

Each field becomes a declared parameter with a ParameterDescriptor (description with the thesis
value, allowed range), so ``--ros-args -p name:=value`` and ``--params-file config/*.yaml`` work
and bad values are refused with a clear message.
"""
from __future__ import annotations

import difflib
import typing

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

from .params import config_from_dict, describe, spec_of

__all__ = ["declare_config", "UnknownParameter", "refuse_undeclared"]

_PTYPE = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


def _ptype(typ) -> int:
    if typing.get_origin(typ) in (list, tuple):
        (item,) = set(typing.get_args(typ)) - {Ellipsis}
        return {str: ParameterType.PARAMETER_STRING_ARRAY, int: ParameterType.PARAMETER_INTEGER_ARRAY,
                float: ParameterType.PARAMETER_DOUBLE_ARRAY, bool: ParameterType.PARAMETER_BOOL_ARRAY}[item]
    return _PTYPE[typ]


def declare_config(node, cls, *, prefix: str = "", overrides=None, declare_first: tuple = ()):
    """Declare every field of `cls` on `node` (read-only after start) and return the config.

    overrides: defaults to use instead of the dataclass defaults (e.g. an agent choosing the
    memory's reduce_batch), or a function of the values declared so far that returns them (a
    named profile that depends on other parameters); the command line and parameter files still
    win. declare_first: fields declared before the others (those such a function reads).
    """
    values = {}
    specs = sorted(spec_of(cls), key=lambda s: s[0].name not in declare_first)   # stable
    for f, default, typ in specs:
        ov = overrides(values) if callable(overrides) else overrides
        if ov and f.name in ov:
            default = ov[f.name]
        m = f.metadata
        # floats accept integers too (`-p delta:=0`, `-p lease_timeout_s:=60`): rclpy would refuse an
        # INTEGER for a DOUBLE parameter; config_from_dict coerces and range-checks the value below
        desc = ParameterDescriptor(description=describe(f), type=_ptype(typ), read_only=True,
                                   dynamic_typing=typ is float)
        if m.get("choices"):
            desc.additional_constraints = "one of: " + ", ".join(map(str, m["choices"]))
        if typ is int and (m.get("minimum") is not None or m.get("maximum") is not None):
            desc.integer_range = [IntegerRange(from_value=int(m.get("minimum") if m.get("minimum") is not None else -2**63),
                                               to_value=int(m.get("maximum") if m.get("maximum") is not None else 2**63 - 1),
                                               step=0)]
        elif typ is float and (m.get("minimum") is not None or m.get("maximum") is not None):
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(m.get("minimum") if m.get("minimum") is not None else -1e308),
                to_value=float(m.get("maximum") if m.get("maximum") is not None else 1e308), step=0.0)]
        if isinstance(default, tuple):
            default = list(default)
        name = prefix + f.name
        node.declare_parameter(name, default, desc)
        values[f.name] = node.get_parameter(name).value
    return config_from_dict(cls, values)


class UnknownParameter(ValueError):
    """A ``-p name:=value`` (or a parameter file entry) that no node of the process declares."""


def refuse_undeclared(nodes, program: str) -> None:
    """Raise :class:`UnknownParameter` if a parameter given to any of `nodes` (command line, parameter file or the
    overrides a parent passes) is declared by none of them.

    rclpy takes every ``-p`` of the command line as an override of every node in the process and silently ignores
    the ones a node never declares, so a misspelt name would run with the default. `nodes`: all nodes built in this
    process from the same command line (an embedded bring-up shares ``-p`` between the learner and the nodes it
    embeds, so a name counts as known when any of them declares it). Call it after every node has declared its
    parameters and before any work starts. The message names the nearest declared parameters."""
    nodes = list(nodes)
    declared = set()
    for n in nodes:
        declared.update(n._parameters)          # rclpy keeps no public list of declared names
    unknown = sorted({name for n in nodes for name in n._parameter_overrides} - declared)
    if not unknown:
        return
    lines = []
    for name in unknown:
        near = difflib.get_close_matches(name, sorted(declared), n=3, cutoff=0.6)
        hint = ("; did you mean " + " or ".join(f"`{c}`" for c in near) + "?") if near else \
            f" (none is close; `ros2 param list` on a running {program} lists its parameters)"
        lines.append(f"`{name}` is not a parameter of {program}{hint}")
    raise UnknownParameter("; ".join(lines))
