"""An identification file put to use by npp-deploy: the certified policy checked at the robot identified from its
own motion, before it moves, with a lower confidence bound on that robot's success.

A certificate on a set of robots is an average over the set and says nothing of one robot of it. npp-deploy given
an identification of its robot (``npp-identify ... --json`` of a recording of that robot) rolls the certified
policy out at each point of the identified region (the estimate and the corners of the identified combinations'
intervals) from n s0 ~ rho, and refuses to command when the worst point's one-sided Clopper-Pearson bound lies
below the operator's threshold (npp_ros.identification.check). No expert is asked. The claim is about the model at
those points: a robot whose motion the set's parameters cannot express is the model monitor's to find.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from npp_ros.identification.check import MoveCheck, check_before_move
from npp_ros.run.read import Run
from npp_ros.tasks.uncertainty import Robot


class IdentifiedRobotError(ValueError):
    """An identification that cannot be used for this run, with the reason."""


def identified_region(path: Path, run: Run) -> tuple[list[Robot], str]:
    """The points of the region an identification of this run's task and set names (npp-identify's --json output,
    or its ``identification`` record alone), and the identified robot in words."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise IdentifiedRobotError(f"cannot read the identified robot {path}: {exc}") from None
    record = record.get("identification", record) if isinstance(record, dict) else record
    if not isinstance(record, dict) or "region" not in record:
        raise IdentifiedRobotError(f"{path} is no identification with a region (npp-identify --out writes one)")
    if record.get("task") != run.task.name:
        raise IdentifiedRobotError(f"{path} identifies a {record.get('task')!r} robot; the run is {run.task.name!r}")
    robots = run.robots
    if robots is None:
        raise IdentifiedRobotError("the run is certified on the exact model: there is no set to place a robot in")
    if record.get("set") != robots.describe():
        raise IdentifiedRobotError(
            f"{path} placed the robot against another set ({record.get('set')}) than the run's ({robots.describe()})"
        )
    try:
        region = [Robot.from_record(json.dumps(item)) for item in record["region"]]
    except (TypeError, ValueError) as exc:
        raise IdentifiedRobotError(f"{path} holds a region that is no list of robots: {exc}") from None
    if not region:
        raise IdentifiedRobotError(f"{path} holds an empty region")
    combos = ", ".join(
        f"{c.get('label')} {c.get('value'):.4g} [{c.get('low'):.4g}, {c.get('high'):.4g}]"
        for c in record.get("combinations", [])
        if isinstance(c, dict)
    )
    words = f"{combos}; delay {record.get('delay')}; {record.get('verdict')} the certified set"
    return region, words


def check_identified_robot(
    run: Run,
    path: Path,
    *,
    n: int,
    p: float | None,
    delta_g: float,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[MoveCheck, str]:
    """The check before the robot moves, at the region ``path`` names: the verdict, and the robot in words."""
    region, words = identified_region(path, run)
    return check_before_move(run, region, n=n, p=p, delta_g=delta_g, progress=progress), words
