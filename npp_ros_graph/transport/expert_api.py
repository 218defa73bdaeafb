"""The expert service contract for experts in other processes: names, QoS and the seal (a stable helper).

An expert written outside npp_ros (README, "Experts from any process") subscribes to the sim's
plant description, serves ``npp_interfaces/srv/ExpertTrajectory`` under :data:`EXPERT_SERVICE`,
and seals each answer with the run's key before returning it::

    from npp_ros_graph.transport.expert_api import EXPERT_SERVICE, PLANT_TOPIC, PLANT_QOS, SERVICE_QOS, answer_seal

    def on_plant(description):          # the sim's latched PlantDescription
        self.seal = answer_seal(description)   # SealError: not this run's sim (another key)

    def on_request(request, response):
        if request.robot:                          # a drawn robot: plan on it, or refuse saying why
            response.success, response.message = False, robot_refusal(self.task)
        else:
            ... fill success, message, state_dim, action_dim, states, actions, values, expert_return ...
        return self.seal.seal(response, request)   # sets response.plant, then the tag

A request's ``robot`` names a drawn robot (a run under model uncertainty, npp_ros.tasks.uncertainty; '' for the
nominal model): an expert answers it only by planning on that robot, and one that plans on its nominal model only
refuses it, with :func:`robot_refusal`'s reason, rather than answer for another plant.

The run's key comes from ``NPP_RUN_KEY`` in the environment (npp-run sets it for its nodes; export
the same key for an expert started by hand). What this module names is kept stable across npp_ros
versions: an expert built on it keeps working.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal, SealError
from npp_ros_graph.transport.topics import BUSY, EXPERT_SERVICE, LATCHED_READER_QOS, NOT_READY, PLANT, SERVICE_QOS

PLANT_TOPIC = PLANT
PLANT_QOS = LATCHED_READER_QOS  # a reader's: one description per publisher, so a stranger's cannot hide the run's
NOMINAL_ONLY = "cannot plan on a drawn robot"  # how a refusal of a request that names a robot starts
__all__ = [
    "BUSY", "EXPERT_SERVICE", "KEY_ENV", "NOMINAL_ONLY", "NOT_READY", "PLANT_QOS", "PLANT_TOPIC", "SERVICE_QOS",
    "AnswerSeal", "SealError", "answer_seal", "robot_refusal",
]  # fmt: skip


def robot_refusal(task: str) -> str:
    """The refusal of an expert that plans on its nominal model only, asked about a drawn robot: a run under model
    uncertainty stops with this reason instead of storing an answer for the nominal plant."""
    return (
        f"{NOMINAL_ONLY}: the expert of {task} plans on its nominal model only (model uncertainty needs an expert "
        "that plans on the robot a request names); ask with robot '' or run without uncertainty"
    )


@dataclass(frozen=True)
class AnswerSeal:
    """Seals answers about one plant for one run: what the supervisor checks before it reads an answer."""

    fingerprint: str  # the plant's model fingerprint, as the sim described it
    run_seal: RunSeal  # the run's seal for that plant

    def seal(self, response: Any, request: Any) -> Any:
        """Set ``response.plant`` to the plant's fingerprint and ``response.seal`` to the tag over the response
        and the request it answers (an answer cannot be passed off for another request); returns ``response``.

        The tag is made for the asking run, whose identity comes with the request (``request.run``): an
        answer made for one run does not check in another. Call it last: the tag covers every field, so a
        field set afterwards breaks the seal.
        """
        response.plant = self.fingerprint
        seal = self.run_seal.for_run(request.run) if request.run else self.run_seal
        return seal.seal(response, answering=request)


def answer_seal(description: Any, key: str | None = None) -> AnswerSeal:
    """The seal for answers about the plant a sim describes; SealError when the description is not this run's.

    ``key``: the run's key; None reads ``NPP_RUN_KEY`` from the environment (without one, the public
    key that nodes started without a key share).
    """
    run = RunSeal.from_environment() if key is None else RunSeal.from_environment({KEY_ENV: key})
    run.check(description, "the plant description")
    return AnswerSeal(description.model_sha256, run.for_plant(description.model_sha256))
