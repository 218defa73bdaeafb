"""A task file's ``[uncertainty]`` table: what of the robot is uncertain (npp_ros.tasks.uncertainty).

Each physical parameter is a scale range of the model's own values, for every element of its kind or for the named
ones; ``action_delay`` is the largest delay in control steps; ``state_noise`` the standard deviation on each
stored state entry. A run draws from this set only when asked (``--uncertainty``)::

    [uncertainty]
    mass = [0.8, 1.2]                                  # every body's mass and inertia x [0.8, 1.2]
    gear = { range = [0.8, 1.2], names = ["motor"] }   # only the actuator named motor
    damping = [0.5, 1.5]
    action_delay = 1
"""

from __future__ import annotations

from typing import Any

from npp_ros.tasks.task_file.reader import Reader
from npp_ros.tasks.uncertainty import EXACT, PARAMETERS, ScaleRange, UncertaintySet

UNCERTAINTY_KEYS = {*PARAMETERS, "action_delay", "state_noise"}
RANGE_KEYS = {"range", "names"}


def read_uncertainty(reader: Reader, doc: dict[str, Any], model: Any) -> UncertaintySet:
    """``[uncertainty]`` checked against the model (every name exists); the exact model when the file has none."""
    if "uncertainty" not in doc:
        return EXACT
    table = reader.table(doc["uncertainty"], "uncertainty")
    reader.unknown_keys(table, UNCERTAINTY_KEYS, "uncertainty.")
    scales = []
    for parameter in PARAMETERS:
        if parameter in table:
            scales.append(_scale(reader, parameter, table[parameter]))
    delay = table.get("action_delay", 0)
    if isinstance(delay, bool) or not isinstance(delay, int) or delay < 0:
        raise reader.fail("uncertainty.action_delay", f"must be a whole number of control steps >= 0, got {delay!r}")
    noise = reader.non_negative(table.get("state_noise", 0.0), "uncertainty.state_noise")
    try:
        return UncertaintySet(tuple(scales), delay, noise).resolved(model)
    except ValueError as exc:
        raise reader.fail("uncertainty", str(exc).removeprefix("uncertainty: ")) from None


def _scale(reader: Reader, parameter: str, value: Any) -> ScaleRange:
    key = f"uncertainty.{parameter}"
    names: list[str] = []
    if isinstance(value, dict):
        reader.unknown_keys(value, RANGE_KEYS, f"{key}.")
        if "range" not in value:
            raise reader.fail(key, "a table needs range = [low, high] (and optionally names = [...])")
        names = reader.names(value.get("names", []), f"{key}.names") if "names" in value else []
        value = value["range"]
    low, high = reader.interval(value, key)
    if low <= 0:
        raise reader.fail(key, f"a scale must be > 0, got low {low:g}")
    return ScaleRange(parameter, low, high, tuple(names))
