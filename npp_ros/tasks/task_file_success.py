"""A task file's ``[success]``: when an episode did the task, as a band on one quantity over its last seconds.

::

    [success]
    joint = "hinge"            # a joint's position as stored (wrapped to (-pi, pi] where [state] wraps it)
    # or: site = "tip" and axis = "z"            (a site's world position along x, y or z)
    # or: distance = ["fingertip", "target"]     (between two sites)
    within = [-0.14, 0.14]     # the band the quantity must stay in
    last_seconds = 1.0         # over the episode's last seconds (all of a shorter episode); default 1
    description = "the pole within 8 degrees of upright"   # optional: the words certificates use

Every run judges the expert's answers and the policy's rollouts on it, and the certificate states both counts
(npp_ros.tasks.success). A site's position is computed from the stored state by the model's kinematics, so it
is the same on the expert's answers, the policy's rollouts and any replay. Every refusal names its key
(npp_ros.tasks.task_file_reader).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.success import SuccessCriterion, WithinBand, steps_for
from npp_ros.tasks.task_file_model import in_model_order, model_ids, named_objects
from npp_ros.tasks.task_file_reader import Reader

SUCCESS_KEYS = {"joint", "site", "axis", "distance", "within", "last_seconds", "description"}
SUCCESS_QUANTITIES = ("joint", "site", "distance")
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
    """A site's coordinate (``axis``), or the distance between two sites, within [low, high] in every state."""

    model_path: str
    sites: tuple[int, ...]  # one site (a coordinate) or two (their distance)
    axis: int
    low: float
    high: float

    def values(self, states: FloatArray) -> FloatArray:
        """The quantity in each stored state: its qpos set, the model's kinematics run."""
        import mujoco

        model, data = _kinematics(self.model_path)
        out = np.empty(len(states))
        for k, state in enumerate(states):
            data.qpos[:] = state[: model.nq]
            mujoco.mj_kinematics(model, data)
            if len(self.sites) == 1:
                out[k] = data.site_xpos[self.sites[0], self.axis]
            else:
                out[k] = np.linalg.norm(data.site_xpos[self.sites[0]] - data.site_xpos[self.sites[1]])
        return out

    def __call__(self, states: FloatArray) -> bool:
        values = self.values(states)
        return bool(np.all((values >= self.low) & (values <= self.high)))


def read_success(
    reader: Reader, doc: dict[str, Any], model: Any, model_path: Path, dt: float
) -> SuccessCriterion | None:
    """``[success]``: the criterion it states, or None when the file has no such table."""
    if "success" not in doc:
        return None
    table = reader.table(doc["success"], "success")
    reader.unknown_keys(table, SUCCESS_KEYS, "success.")
    named = [q for q in SUCCESS_QUANTITIES if q in table]
    if not named:
        raise reader.fail("success", "says nothing to check: give joint = NAME, site = NAME with axis, or "
                          "distance = [SITE, SITE]")  # fmt: skip
    if len(named) > 1:
        raise reader.fail("success", f"one quantity, got {', '.join(named)}")
    if "within" not in table:
        raise reader.fail("success.within", "missing: give the band [low, high] the quantity must stay in")
    low, high = reader.interval(table["within"], "success.within")
    seconds = reader.number(table.get("last_seconds", DEFAULT_LAST_SECONDS), "success.last_seconds", positive=True)
    quantity = named[0]
    if quantity != "site" and "axis" in table:
        raise reader.fail("success.axis", "only a site has an axis")
    if quantity == "joint":
        holds, words = _joint(reader, table, model, low, high)
    else:
        holds, words = _sites(reader, table, quantity, model, model_path, low, high)
    description = reader.text(table["description"], "success.description") if "description" in table else words
    return SuccessCriterion(description, holds, steps=steps_for(seconds, dt), seconds=seconds)


def _joint(reader: Reader, table: dict[str, Any], model: Any, low: float, high: float) -> tuple[WithinBand, str]:
    """A joint's stored position: its qpos entry of the state."""
    joints = model_ids(model, "joint")
    name = reader.text(table["joint"], "success.joint")
    if name not in joints:
        raise reader.fail("success.joint", f"unknown joint {name!r} (the model's: {', '.join(in_model_order(joints))})")
    entry = int(model.jnt_qposadr[joints[name]])
    return WithinBand((entry,), low, high), f"joint {name} within [{low:g}, {high:g}]"


def _sites(
    reader: Reader, table: dict[str, Any], quantity: str, model: Any, model_path: Path, low: float, high: float
) -> tuple[SiteBand, str]:
    """A site's coordinate along ``axis``, or the distance between two sites."""
    sites = model_ids(model, "site")
    key = f"success.{quantity}"
    wanted = named_objects(reader, table[quantity], key, sites, "site", pair=quantity == "distance")
    ids = tuple(sites[name] for name in wanted)
    if quantity == "distance":
        band = SiteBand(str(model_path), ids, 0, low, high)
        return band, f"sites {wanted[0]} and {wanted[1]} within [{low:g}, {high:g}] m of each other"
    axis = table.get("axis")
    if axis not in AXES:
        raise reader.fail("success.axis", f"a site needs axis x, y or z, got {axis!r}")
    band = SiteBand(str(model_path), ids, AXES.index(axis), low, high)
    return band, f"site {wanted[0]} at {axis} within [{low:g}, {high:g}] m"
