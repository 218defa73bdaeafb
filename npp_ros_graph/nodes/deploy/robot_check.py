"""configure's check before the robot moves, at the robot identified from its own motion (identified_robot,
npp_ros.identification.identified), and the progress a long configure step logs (that check's, and the gate's as it
derives the run again). Each gets the node's logger only."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from rclpy.impl.rcutils_logger import RcutilsLogger

from npp_ros.deployment.gate import Deployment
from npp_ros.identification.identified import check_identified_robot
from npp_ros.run.read import read_run
from npp_ros.tasks.uncertainty import UncertaintySet
from npp_ros_graph.nodes.deploy.settings import DeploySettings


def progress(logger: RcutilsLogger, what: str) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` that logs ``what`` (formatted with done and total) every few seconds and at the
    end: a configure that takes a minute says why."""
    last = [time.monotonic()]

    def report(done: int, total: int) -> None:
        if done == total or time.monotonic() - last[0] >= 5.0:
            last[0] = time.monotonic()
            logger.info(what.format(done=done, total=total))

    return report


def check_robot(settings: DeploySettings, deployment: Deployment, robots: UncertaintySet, logger: RcutilsLogger) -> str:
    """The check before the robot moves, at the robot identified_robot names (npp_ros.identification.identified):
    its verdict in words, or a ValueError with the reason it must not move. Without one, on a set: a warning
    that nothing is known of this robot beyond the set's average."""
    if not settings.identified_robot.strip():
        if robots.empty:
            return ""
        logger.warning(
            "the certificate on the set of robots is an average over the set and promises nothing for this one "
            "robot: give identified_robot (npp-identify --out of its recorded motion) to check the policy at it"
        )
        return "not checked at this robot (no identified_robot)"
    run = read_run(deployment.run_file)
    report = progress(logger, "robot check: point {done} of {total} of the identified region simulated")
    move, words = check_identified_robot(
        run, Path(settings.identified_robot), n=settings.robot_check_starts,
        p=settings.robot_min_success or None, delta_g=settings.robot_check_delta, progress=report,
    )  # fmt: skip
    verdict = move.summary().splitlines()[0]
    if not move.accepted:
        raise ValueError(f"the robot identified from its own motion ({words}): {verdict}; not commanded")
    logger.info(f"robot check ({words}): {verdict}")
    return verdict
