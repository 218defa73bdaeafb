"""A robot's motion as identification reads it: the states it reported and the commands it was sent, step by step.

Row t holds the state read at ``times[t]`` and the command sent in answer to it, which a robot without delay applies
over the control step from t to t+1 (a ros2_control robot holds the latest command until the next arrives).
:meth:`Recording.from_streams` aligns two streams with their own clocks (a bag's joint states and commands) into
that form in one place; :func:`record_motion` makes a recording in process, from a plant made into a hidden robot.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.uncertainty import Robot, RobotEffects, as_robot


@dataclass(frozen=True)
class Recording:
    """States as read ([qpos, qvel], raw: angles not wrapped) and the command sent in answer to each."""

    times: FloatArray  # (T,) seconds
    states: FloatArray  # (T, nq + nv)
    commands: FloatArray  # (T, nu), in the task's actuator order

    def __post_init__(self) -> None:
        times, states, commands = (np.asarray(x, dtype=np.float64) for x in (self.times, self.states, self.commands))
        if times.ndim != 1 or states.ndim != 2 or commands.ndim != 2:
            raise ValueError("a recording needs times (T,), states (T, n) and commands (T, m)")
        if not len(times) == len(states) == len(commands):
            raise ValueError(f"a recording's rows differ: {len(times)} times, {len(states)} states, {len(commands)} "
                             f"commands")  # fmt: skip
        if not (np.isfinite(times).all() and np.isfinite(states).all() and np.isfinite(commands).all()):
            raise ValueError("a recording holds a value that is not finite")
        if len(times) > 1 and not (np.diff(times) > 0).all():
            raise ValueError("a recording's times must increase")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "commands", commands)

    def __len__(self) -> int:
        return len(self.times)

    @property
    def seconds(self) -> float:
        return float(self.times[-1] - self.times[0]) if len(self.times) else 0.0

    def window(self, start: float, seconds: float) -> Recording:
        """The rows from ``start`` s after the first for ``seconds`` s."""
        t = self.times - self.times[0]
        keep = (t >= start) & (t <= start + seconds)
        return Recording(self.times[keep], self.states[keep], self.commands[keep])

    def save(self, path: str | Path) -> None:
        """An .npz file of the three arrays (npp-identify reads it as it reads a bag)."""
        np.savez(path, times=self.times, states=self.states, commands=self.commands)

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        with np.load(path) as data:
            missing = {"times", "states", "commands"} - set(data.files)
            if missing:
                raise ValueError(f"{path} is no recording: it lacks {', '.join(sorted(missing))}")
            return cls(data["times"], data["states"], data["commands"])

    @classmethod
    def from_streams(
        cls,
        state_times: ArrayLike,
        states: ArrayLike,
        command_times: ArrayLike,
        commands: ArrayLike,
        stamps: ArrayLike | None = None,
    ) -> Recording:
        """Two streams on one clock -> rows: each state with the command in force when the robot next stepped,
        the last one sent before the next state (a command that came after it counts for a later step); zero
        before the first command, as a robot applies before it is commanded. ``stamps``: the rows' times on the
        robot's own clock (its states' stamps), when the shared clock is a recorder's arrival times."""
        st = np.asarray(state_times, dtype=np.float64)
        x = np.asarray(states, dtype=np.float64)
        kept = st if stamps is None else np.asarray(stamps, dtype=np.float64)
        ct = np.asarray(command_times, dtype=np.float64)
        u = np.asarray(commands, dtype=np.float64)
        if u.ndim != 2 or len(ct) != len(u):
            raise ValueError("commands must be (K, m) with one time each")
        order = np.argsort(st, kind="stable")
        st, x, kept = st[order], x[order], kept[order]
        corder = np.argsort(ct, kind="stable")
        ct, u = ct[corder], u[corder]
        next_state = np.append(st[1:], np.inf)
        latest = np.searchsorted(ct, next_state, side="left") - 1  # the last command strictly before the next state
        rows = np.where(latest[:, None] >= 0, u[np.maximum(latest, 0)], 0.0)
        return cls(kept, x, rows)


def record_motion(
    plant: Plant,
    robot: Robot,
    controller: Callable[[FloatArray], ArrayLike],
    initial_state: ArrayLike,
    steps: int,
    command: Callable[[int, FloatArray], FloatArray] | None = None,
) -> Recording:
    """``steps`` control steps of ``controller`` on the plant made into ``robot`` (its delay and its noise on the
    states read by :class:`RobotEffects`, as the sim and npp-robot apply them); ``command(t, u)`` may change each
    command before it is sent (an excitation). What is recorded is what a bag would hold: the raw states as read
    (with the noise) and the commands as sent (before the delay)."""
    raw_state = getattr(plant, "raw_state", plant.state)
    represent = getattr(plant, "represent", None)
    effects = RobotEffects(robot, plant.action_dim)
    times = np.arange(steps) * plant.dt
    states = np.empty((steps, plant.state_dim))
    commands = np.empty((steps, plant.action_dim))
    with as_robot(plant, robot):
        plant.reset(initial_state)
        for t in range(steps):
            read = effects.observe(np.asarray(raw_state(), dtype=np.float64))
            u = np.asarray(controller(read if represent is None else represent(read)), dtype=np.float64)
            sent = u if command is None else command(t, u)
            states[t], commands[t] = read, sent
            plant.step(effects.command(sent))
    return Recording(times, states, commands)
