"""A short, bounded excitation added to a robot's commands, so that its motion says which robot it is.

Under its policy alone a robot's commands follow its state, and a recording then cannot tell the motor's gear from
the forces the state causes (damping, gravity); a signal that does not depend on the state separates them.

What it is: per actuator, a multisine, a sum of sines at the whole multiples of 1/duration inside a band (0.2 Hz up
to 5 Hz or a quarter of the control rate, the lower), Schroeder phases (a low peak for its power), the actuators on
interleaved frequencies (so each one's effect is told apart from the others'), scaled to a peak of exactly
``fraction`` of the actuator's half range, faded in and out over half a second, zero after ``seconds``. It is fixed
by its seed, so a recording can be made again.

Why it is safe: (1) bounded, it moves a command by at most ``fraction`` of the actuator's half range (0.2 by
default: a fifth of what the policy may command); (2) the command sent, the policy's plus the excitation, is clipped
to the actuator's limits, so nothing beyond what the robot already accepts is ever sent; (3) short, it is zero after
``seconds`` (10 by default) and zero-mean, with no step at its start or end; (4) it is added to the certified policy's
command, which keeps closing the loop, and npp-deploy's watchdog and model monitor keep watching. It is not covered by
the certificate (the policy was certified without it): run it where a few seconds of a slightly disturbed policy are
acceptable, before the check of :mod:`npp_ros.identification.check` lets the robot do its task.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant

DEFAULT_SECONDS = 10.0
DEFAULT_FRACTION = 0.2
BAND_HZ = (0.2, 5.0)
FADE_SECONDS = 0.5


@dataclass(frozen=True)
class Excitation:
    """The signal, one row per control step, and the actuator limits a command is clipped to."""

    signal: FloatArray  # (steps, m): added to the command at step t; zero after the last row
    low: FloatArray  # (m,) the actuator's lower limit (-inf: none)
    high: FloatArray  # (m,)
    dt: float

    @property
    def steps(self) -> int:
        return len(self.signal)

    @property
    def seconds(self) -> float:
        return self.steps * self.dt

    def at(self, step: int) -> FloatArray:
        """What is added at control step ``step`` (0 before the start and after the end)."""
        if 0 <= step < self.steps:
            return self.signal[step]
        return np.zeros(self.signal.shape[1])

    def apply(self, step: int, command: ArrayLike) -> FloatArray:
        """The command to send at ``step``: the policy's ``command`` plus the excitation, within the limits."""
        return np.clip(np.asarray(command, dtype=np.float64) + self.at(step), self.low, self.high)


def multisine(
    plant: Plant,
    seconds: float = DEFAULT_SECONDS,
    fraction: float = DEFAULT_FRACTION,
    seed: int = 0,
    amplitude: ArrayLike | None = None,
) -> Excitation:
    """The excitation of the module's docstring for ``plant``'s actuators. ``amplitude`` (per actuator, in command
    units) replaces ``fraction`` x half range; an actuator without limits needs it."""
    dt = float(plant.dt)
    steps = round(seconds / dt)
    if steps < 2 or not 0 < fraction <= 1:
        raise ValueError(f"an excitation needs at least two control steps and 0 < fraction <= 1, got {seconds} s, "
                         f"{fraction}")  # fmt: skip
    m = plant.action_dim
    low = np.asarray(getattr(plant, "action_low", np.full(m, -np.inf)), dtype=np.float64)
    high = np.asarray(getattr(plant, "action_high", np.full(m, np.inf)), dtype=np.float64)
    if amplitude is None:
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            raise ValueError(f"{plant.task}: an actuator has no limits; give the excitation's amplitude itself")
        peak = fraction * (high - low) / 2
    else:
        peak = np.broadcast_to(np.asarray(amplitude, dtype=np.float64), (m,)).copy()
        if not (np.isfinite(peak).all() and (peak > 0).all()):
            raise ValueError(f"an excitation's amplitude must be finite and > 0, got {amplitude!r}")
    t = np.arange(steps) * dt
    base = 1.0 / (steps * dt)
    top = min(BAND_HZ[1], 0.25 / dt)
    harmonics = np.arange(max(1, math.ceil(BAND_HZ[0] / base)), math.floor(top / base) + 1)
    if len(harmonics) < m:
        raise ValueError(f"{seconds} s hold too few frequencies in the band for {m} actuators")
    rng = np.random.default_rng(seed)
    fade = np.clip(np.minimum(t, t[-1] - t) / FADE_SECONDS, 0.0, 1.0)
    envelope = 0.5 - 0.5 * np.cos(math.pi * fade)
    signal = np.empty((steps, m))
    for i in range(m):
        own = harmonics[i::m]
        k = np.arange(1, len(own) + 1)
        phases = -math.pi * k * (k - 1) / len(own) + rng.uniform(0, 2 * math.pi)
        wave = np.sin(2 * math.pi * np.outer(t, own * base) + phases).sum(axis=1) * envelope
        signal[:, i] = peak[i] * wave / np.abs(wave).max()
    return Excitation(signal, low, high, dt)
