"""A task file's ``[success]``: when an episode did the task, as a band on one quantity over its last seconds.

::

    [success]
    joint = "hinge"            # a joint's position as stored (wrapped to (-pi, pi] where [state] wraps it)
    # or: site = "tip" and axis = "z"            (a site's world position along x, y or z)
    # or: distance = ["fingertip", "target"]     (between two sites)
    # or: speed = "tip"                          (a site's speed in the world, m/s)
    within = [-0.14, 0.14]     # the band the quantity must stay in
    last_seconds = 1.0         # over the episode's last seconds (all of a shorter episode); default 1
    description = "the pole within 8 degrees of upright"   # optional: the words certificates use

Several bands, each a ``[[success]]`` table, must all hold, over the same last seconds (a reach: the hand
within 2 cm of the target and slower than 5 cm/s).

Every run judges the expert's answers and the policy's rollouts on it, and the certificate states both counts
(npp_ros.tasks.success). A site's position is computed from the stored state by the model's kinematics, so it
is the same on the expert's answers, the policy's rollouts and any replay. Every refusal names its key
(npp_ros.tasks.task_file.reader).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.success import SuccessCriterion, WithinBand, steps_for
from npp_ros.tasks.task_file.model import in_model_order, model_ids, named_objects
from npp_ros.tasks.task_file.reader import Reader

SUCCESS_KEYS = {"joint", "site", "axis", "distance", "speed", "within", "last_seconds", "description"}
SUCCESS_QUANTITIES = ("joint", "site", "distance", "speed")
AXES = ("x", "y", "z")
DEFAULT_LAST_SECONDS = 1.0


@functools.lru_cache(maxsize=8)
def _kinematics(model_path: str) -> tuple[Any, Any]:
    """The compiled model and a data of its own, per process (one per model file)."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(model_path)
    return model, mujoco.MjData(model)


@dataclass(frozen=True)
class SiteBand:
    """A site's coordinate (``axis``), its speed (``speed``), or the distance between two sites, within
    [low, high] in every state."""

    model_path: str
    sites: tuple[int, ...]  # one site (a coordinate, or its speed) or two (their distance)
    axis: int
    low: float
    high: float
    speed: bool = False

    def values(self, states: FloatArray) -> FloatArray:
        """The quantity in each stored state: its qpos (and, for a speed, qvel) set, the model's kinematics run."""
        import mujoco

        model, data = _kinematics(self.model_path)
        out = np.empty(len(states))
        jac = np.zeros((3, model.nv))
        for k, state in enumerate(states):
            data.qpos[:] = state[: model.nq]
            mujoco.mj_kinematics(model, data)
            if self.speed:
                mujoco.mj_comPos(model, data)
                mujoco.mj_jacSite(model, data, jac, None, self.sites[0])
                out[k] = np.linalg.norm(jac @ state[model.nq : model.nq + model.nv])
            elif len(self.sites) == 1:
                out[k] = data.site_xpos[self.sites[0], self.axis]
            else:
                out[k] = np.linalg.norm(data.site_xpos[self.sites[0]] - data.site_xpos[self.sites[1]])
        return out

    def __call__(self, states: FloatArray) -> bool:
        values = self.values(states)
        return bool(np.all((values >= self.low) & (values <= self.high)))


@dataclass(frozen=True)
class AllBands:
    """Every band of several ``[[success]]`` tables holds."""

    bands: tuple[Any, ...]

    def __call__(self, states: FloatArray) -> bool:
        return all(band(states) for band in self.bands)


def read_success(
    reader: Reader, doc: dict[str, Any], model: Any, model_path: Path, dt: float
) -> SuccessCriterion | None:
    """``[success]`` (or several ``[[success]]``): the criterion it states, or None when the file has none."""
    if "success" not in doc:
        return None
    given = doc["success"]
    if not isinstance(given, list):
        holds, words, seconds = _band(reader, reader.table(given, "success"), "success", model, model_path)
        return SuccessCriterion(words, holds, steps=steps_for(seconds, dt), seconds=seconds)
    if not given:
        raise reader.fail("success", "is an empty list: give one [[success]] table per band")
    read = [_band(reader, reader.table(t, f"success[{i}]"), f"success[{i}]", model, model_path)
            for i, t in enumerate(given)]  # fmt: skip
    seconds = read[0][2]
    for i, (_, _, other) in enumerate(read):
        if other != seconds:
            raise reader.fail(f"success[{i}].last_seconds", f"is {other:g} s, the first band's {seconds:g} s: the "
                              "bands of one criterion hold over the same last seconds")  # fmt: skip
    words = " and ".join(w for _, w, _ in read)
    return SuccessCriterion(
        words, AllBands(tuple(h for h, _, _ in read)), steps=steps_for(seconds, dt), seconds=seconds
    )


def _band(reader: Reader, table: dict[str, Any], key: str, model: Any, model_path: Path) -> tuple[Any, str, float]:
    """One band: its predicate, its words and the last seconds it holds over."""
    reader.unknown_keys(table, SUCCESS_KEYS, f"{key}.")
    named = [q for q in SUCCESS_QUANTITIES if q in table]
    if not named:
        raise reader.fail(key, "says nothing to check: give joint = NAME, site = NAME with axis, "
                          "distance = [SITE, SITE] or speed = SITE")  # fmt: skip
    if len(named) > 1:
        raise reader.fail(key, f"one quantity, got {', '.join(named)}")
    if "within" not in table:
        raise reader.fail(f"{key}.within", "missing: give the band [low, high] the quantity must stay in")
    low, high = reader.interval(table["within"], f"{key}.within")
    seconds = reader.number(table.get("last_seconds", DEFAULT_LAST_SECONDS), f"{key}.last_seconds", positive=True)
    quantity = named[0]
    if quantity != "site" and "axis" in table:
        raise reader.fail(f"{key}.axis", "only a site has an axis")
    if quantity == "joint":
        holds, words = _joint(reader, table, key, model, low, high)
    else:
        holds, words = _sites(reader, table, key, quantity, model, model_path, low, high)
    description = reader.text(table["description"], f"{key}.description") if "description" in table else words
    return holds, description, seconds


def _joint(
    reader: Reader, table: dict[str, Any], key: str, model: Any, low: float, high: float
) -> tuple[WithinBand, str]:
    """A joint's stored position: its qpos entry of the state."""
    joints = model_ids(model, "joint")
    name = reader.text(table["joint"], f"{key}.joint")
    if name not in joints:
        raise reader.fail(f"{key}.joint", f"unknown joint {name!r} (the model's: {', '.join(in_model_order(joints))})")
    entry = int(model.jnt_qposadr[joints[name]])
    return WithinBand((entry,), low, high), f"joint {name} within [{low:g}, {high:g}]"


def _sites(
    reader: Reader,
    table: dict[str, Any],
    key: str,
    quantity: str,
    model: Any,
    model_path: Path,
    low: float,
    high: float,
) -> tuple[SiteBand, str]:
    """A site's coordinate along ``axis``, its speed, or the distance between two sites."""
    sites = model_ids(model, "site")
    wanted = named_objects(reader, table[quantity], f"{key}.{quantity}", sites, "site", pair=quantity == "distance")
    ids = tuple(sites[name] for name in wanted)
    if quantity == "distance":
        band = SiteBand(str(model_path), ids, 0, low, high)
        return band, f"sites {wanted[0]} and {wanted[1]} within [{low:g}, {high:g}] m of each other"
    if quantity == "speed":
        return SiteBand(
            str(model_path), ids, 0, low, high, speed=True
        ), f"site {wanted[0]} moving at [{low:g}, {high:g}] m/s"
    axis = table.get("axis")
    if axis not in AXES:
        raise reader.fail(f"{key}.axis", f"a site needs axis x, y or z, got {axis!r}")
    band = SiteBand(str(model_path), ids, AXES.index(axis), low, high)
    return band, f"site {wanted[0]} at {axis} within [{low:g}, {high:g}] m"
