"""Node parameters: one table per node, declared with ROS descriptors, read into one frozen settings object.

The table is the only place a parameter is named: its descriptor (description, range, choices) is what
`ros2 param describe` shows and what `--help` prints. Ranges are checked by rclpy when the parameter is
declared; everything else (a task's name, p and delta, the choice of L) by the core constructors the
settings feed, in the settings' ``__post_init__``. Any refusal becomes a StartupError with the reason.

A parameter whose ROS value is not the core's type names a ``read`` that converts it, the one place that
conversion happens: a value the task decides is the text ``task`` on the ROS side (a parameter cannot be
unset), None in the core (:func:`task_or_number`). A run's settings are the run request's fields
(npp_ros.run.request), made parameters by :func:`request_params` with the request's help texts.

Overrides are read before they are declared, so that an unknown name is refused with the closest known
one, and a whole number given for a float (``-p epsilon:=30``) or for a text-or-number choice
(``-p lipschitz:=300``) is taken for what it means instead of being refused as the wrong type.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from npp_ros.certificate.choices import parse_lipschitz
from npp_ros.run.request import COUNT, INDEX, LIPSCHITZ, NUMBER, Setting, request_fields
from npp_ros_graph.transport.startup import StartupError

Value = bool | int | float | str
Settings = TypeVar("Settings")

# Declared by rclpy itself on every node; never ours to refuse.
RCLPY_PARAMETERS = ("use_sim_time", "start_type_description_service")
TASK_CHOICE = "task"  # a parameter's value for "the task's own", which the core spells None


def task_or_number(text: str) -> float | None:
    """A task-or-number parameter in the core's type: None for ``task`` (the task decides), else the number."""
    return None if text.strip() == TASK_CHOICE else float(text)


def task_or_choice(text: str) -> str | None:
    """A choice parameter in the core's type: None for ``task`` (the task decides), else the choice."""
    return None if text == TASK_CHOICE else text


def task_or_number_value(value: float | None) -> str | float:
    """The parameter value that :func:`task_or_number` reads back as ``value`` (what a launcher passes)."""
    return TASK_CHOICE if value is None else float(value)


def _reader(setting: Setting) -> Callable[[Any], Any]:
    """How a request field's parameter is read into the field's type: ``task`` is None, else the value parsed."""
    parse: Callable[[Any], Any] = {COUNT: int, INDEX: int, NUMBER: float, LIPSCHITZ: parse_lipschitz}.get(
        setting.kind, str
    )
    return lambda value: None if str(value).strip() == TASK_CHOICE else parse(value)


def request_params(names: Sequence[str] | None = None, *, read_only: bool = True) -> tuple[Param, ...]:
    """The run request's fields (those named) as parameters, with the request's help texts: a field whose value
    the task decides (None) is the text ``task`` until given, and the request checks every value."""
    params = []
    for field, setting in request_fields(tuple(names) if names is not None else None):
        if field.default is not None:
            low, high, choices = setting.low, setting.high, setting.choices
            params.append(Param(field.name, field.default, setting.text(), low, high, choices, read_only))
            continue
        kind = {COUNT: "an integer >= 1", NUMBER: "a number > 0", LIPSCHITZ: "a number > 0"}.get(setting.kind)
        choices = (TASK_CHOICE, *setting.choices, *([kind] if kind else []))
        params.append(Param(field.name, TASK_CHOICE, setting.text(), choices=choices, read_only=read_only,
                            read=_reader(setting)))  # fmt: skip
    return tuple(params)


@dataclass(frozen=True)
class Param:
    """One parameter: name, default (its type is the parameter's), what it means, and its allowed values."""

    name: str
    default: Value
    description: str
    low: float | None = None  # inclusive bounds, as ROS ranges are
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True  # False: a node that reads it again later (a lifecycle node, at configure)
    read: Callable[[Any], Any] | None = None  # the ROS value in the settings' type; a ValueError refuses it

    def allowed(self) -> str:
        """The allowed values in words ("an integer in [1, 100000]", "one of: i, ii")."""
        if self.choices:
            return "one of: " + ", ".join(self.choices)
        kind = {bool: "true or false", int: "an integer", float: "a number", str: "text"}[type(self.default)]
        if self.low is None and self.high is None:
            return kind
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        return f"{kind} in [{low}, {high}]"

    def descriptor(self) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(name=self.name, description=self.description, read_only=self.read_only)
        if self.choices:
            descriptor.additional_constraints = self.allowed()
        if self.low is not None or self.high is not None:
            low = -math.inf if self.low is None else self.low
            high = math.inf if self.high is None else self.high
            if isinstance(self.default, float):
                descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
            elif isinstance(self.default, int) and not isinstance(self.default, bool):
                lo = int(low) if math.isfinite(low) else -(2**63)
                hi = int(high) if math.isfinite(high) else 2**63 - 1
                descriptor.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
        return descriptor


def parameter_help(params: Sequence[Param]) -> str:
    if not params:
        return "parameters  none"
    lines = ["parameters (--ros-args -p name:=value):"]
    lines += [f"  {p.name:<18} {p.description}; {p.allowed()} (default: {p.default!r})" for p in params]
    return "\n".join(lines)


def _accepted_override(param: Param, given: Parameter) -> Parameter:
    """A whole number for a float, or a number for a text-or-number choice, as the declared type."""
    Type = Parameter.Type
    if isinstance(param.default, float) and given.type_ == Type.INTEGER:
        return Parameter(param.name, Type.DOUBLE, float(given.value))
    if isinstance(param.default, str) and given.type_ in (Type.INTEGER, Type.DOUBLE):
        return Parameter(param.name, Type.STRING, str(given.value))
    return given


def _overrides(node: Node) -> dict[str, Parameter]:
    """The parameter values given to the node (``--ros-args -p``, parameter files), by name, before any is declared.

    rclpy has no public call for them: ``get_parameter``/``get_parameters`` see declared parameters only, and an
    override for a name the node never declares is silently kept unused. So this reads rclpy's private
    ``Node._parameter_overrides`` (the dict ``declare_parameter`` takes its initial values from), here and
    nowhere else: to refuse an unknown name with the closest known one, and to replace a whole number given for a
    float before it is declared. If rclpy renames it, this is the one line to change.
    """
    return node._parameter_overrides


def _refuse_unknown(node: Node, params: Sequence[Param]) -> None:
    known = [p.name for p in params]
    for name in _overrides(node):
        if name in known or name in RCLPY_PARAMETERS or name.startswith("qos_overrides."):
            continue
        close = difflib.get_close_matches(name, known, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; known: {', '.join(known) or 'none'}"
        raise StartupError(f"unknown parameter '{name}'{hint}")


def declare_settings(node: Node, params: Sequence[Param], settings: type[Settings]) -> Settings:
    """Declare every parameter of the table and build the node's settings from their values.

    ``settings`` is a frozen dataclass whose fields are the table's names (or one that names them in
    ``parameter_names()`` and is built by ``from_parameters(**values)``); its construction (the core checks in its
    ``__post_init__``) is where values are validated.
    """
    own = getattr(settings, "parameter_names", None)  # settings that group some parameters (a run request) say so
    names = set(own()) if own is not None else {f.name for f in fields(settings)}  # type: ignore[arg-type]
    assert names == {p.name for p in params}, f"{settings.__name__} and its parameter table disagree"
    _refuse_unknown(node, params)
    overrides = _overrides(node)
    values: dict[str, Any] = {}
    for param in params:
        if param.name in overrides:
            overrides[param.name] = _accepted_override(param, overrides[param.name])
        try:
            value = node.declare_parameter(param.name, param.default, param.descriptor()).value
            values[param.name] = value if param.read is None else param.read(value)
        except (ParameterException, ValueError):
            given = overrides[param.name].value if param.name in overrides else param.default
            raise StartupError(f"parameter {param.name} must be {param.allowed()}, got {given!r}") from None
    try:
        return getattr(settings, "from_parameters", settings)(**values)
    except ValueError as exc:
        raise StartupError(f"bad parameter: {exc}") from None
