"""A plug-in task: dm_control's pendulum swing-up under another name, defined entirely outside npp_ros."""

from __future__ import annotations

from dataclasses import replace

from npp_ros.tasks.builtin.pendulum import SWINGUP, PendulumPlant

NAME = "demo_pendulum"


class DemoPendulumPlant(PendulumPlant):
    """The swing-up plant reporting this plug-in's task name (what the sim describes)."""

    task = NAME


DEMO_PENDULUM = replace(SWINGUP, name=NAME, plant_factory=DemoPendulumPlant, default_time_budget=1.0)
