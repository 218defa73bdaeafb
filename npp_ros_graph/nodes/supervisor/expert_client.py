"""The oracle of Algorithm 1 over the graph: the expert service, a deadline per call, retries, a clear failure."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory
from rclpy.client import Client
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.task import Future

from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.tasks.uncertainty import Robot, as_robot
from npp_ros_graph.nodes.supervisor.answer_check import AnswerCheck
from npp_ros_graph.runtime.deadlines import RESEND_S, call_with_deadline
from npp_ros_graph.transport.convert import float64_array, robot_to_field, trajectory_from_response
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.topics import BUSY, EXPERT_SERVICE, NOT_READY

RETRY_PAUSE_S = 0.25  # first pause between expert attempts; doubles each time, capped at expert_timeout


class ExpertUnavailable(RuntimeError):
    pass


class RosExpert:
    """The oracle over /npp/expert/trajectory: a deadline per call, retries, clear failure.

    It gets what it uses: the service client, the run's plant, seal and identity, the node's stop event
    and logger, a count of the service's servers (what a refusal names), and the check of an answer: one
    that fails it (wrong dimensions, non-finite values, values that contradict its own trajectory on the
    supervisor's plant) counts as a failed attempt, with the reason, and nothing of it is stored.

    Asking ahead (``ahead``: the s0 of the episodes after the one that asks, known in advance because
    every episode draws its s0 from its own seeded stream): in the oracle mode every episode needs the
    expert, so the answers for the next episodes are asked for at once and computed while this episode
    runs (by an expert with several workers, at the same time). An early answer is only kept: it is
    checked like any other and reaches the loop when the loop asks for that s0, so it cannot change a
    test that is running. One lost in a pause or a restart is asked for again the usual way; answers
    asked ahead of a run that then certifies are never used (at most as many as are asked ahead).

    Under model uncertainty each request names the episode's robot, the expert plans on it, and the answer is
    checked on the supervisor's plant made into that robot; an answer asked ahead is kept for its s0 and robot.
    """

    def __init__(
        self,
        client: Client,
        plant: PlantDescription,
        seal: RunSeal,
        run_id: str,
        *,
        stop: threading.Event,
        logger: RcutilsLogger,
        servers: Callable[[], int],
        timeout: float,
        retries: int,
        check: AnswerCheck,
        ahead: Callable[[], Sequence[tuple[FloatArray, Robot | None]]] = tuple,
    ) -> None:
        self.client, self.plant, self.seal, self.run_id = client, plant, seal, run_id
        self.stop, self.logger, self.servers = stop, logger, servers
        self.timeout, self.retries, self.check = timeout, retries, check
        self.ahead = ahead
        # (s0's bytes, robot) -> request, answer
        self._early: dict[tuple[bytes, str], tuple[ExpertTrajectory.Request, Future]] = {}

    def _request(self, initial_state: FloatArray, robot: Robot | None) -> ExpertTrajectory.Request:
        return ExpertTrajectory.Request(
            state=float64_array(initial_state), horizon=0, run=self.run_id, robot=robot_to_field(robot)
        )

    @staticmethod
    def _key(initial_state: FloatArray, robot: Robot | None) -> tuple[bytes, str]:
        return np.asarray(initial_state, dtype=np.float64).tobytes(), robot_to_field(robot)

    def ask_ahead(self) -> None:
        """Ask now for the s0 (and robots) the next episodes will ask about (see the class docstring)."""
        for state, robot in self.ahead():
            key = self._key(state, robot)
            if key not in self._early and self.client.service_is_ready():
                request = self._request(state, robot)
                self._early[key] = (request, self.client.call_async(request))

    def _early_answer(self, request: ExpertTrajectory.Request, future: Future) -> ExpertTrajectory.Response | None:
        """The answer asked for ahead, once it is here and checks; None (ask the usual way) when it was refused
        or lost: its server left the graph, this process was paused, or expert_timeout passed."""
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        deadline = time.monotonic() + self.timeout
        while not done.is_set():
            before = time.monotonic()
            if done.wait(min(RESEND_S, max(deadline - before, 0.0))):
                break
            if (
                self.stop.is_set()
                or time.monotonic() >= deadline
                or not self.client.service_is_ready()
                or (time.monotonic() - before > 3 * RESEND_S)
            ):
                self.client.remove_pending_request(future)
                future.cancel()
                return None
        response = future.result()
        if response is None:
            return None
        refusal, _ = self._refusal(response, request)
        if refusal is not None:
            self.logger.info(f"an answer asked for ahead was refused ({refusal}); asking again")
            return None
        return response

    def trajectory(self, initial_state: FloatArray, robot: Robot | None = None) -> Trajectory:
        """The expert's checked answer from ``initial_state``, planned on ``robot`` (None: the nominal model)."""
        early = self._early.pop(self._key(initial_state, robot), None)
        self.ask_ahead()
        if early is not None and (response := self._early_answer(*early)) is not None:
            try:
                return self._checked(response, initial_state, robot)
            except ValueError as exc:
                self.logger.warning(f"refused the expert's answer asked for ahead: {exc}; asking again")
        last = "no answer"
        for attempt in range(1, self.retries + 1):
            response, last = self._attempt(initial_state, robot)
            if response is not None:
                try:
                    return self._checked(response, initial_state, robot)
                except ValueError as exc:  # DatasetError, AnswerError: the answer is wrong, not the link
                    last = f"refused the expert's answer: {exc}"
            self.logger.warning(f"expert call {attempt}/{self.retries} failed: {last}")
            if attempt < self.retries:
                self.stop.wait(min(self.timeout, RETRY_PAUSE_S * 2 ** (attempt - 1)))
        raise ExpertUnavailable(f"the expert did not deliver after {self.retries} attempts: {last}")

    def _checked(
        self, response: ExpertTrajectory.Response, initial_state: FloatArray, robot: Robot | None
    ) -> Trajectory:
        """The answer as a trajectory once it passes the answer check, replayed on the robot it was planned on;
        its ValueError names the failed check."""
        answer = trajectory_from_response(response)
        with as_robot(self.check.plant, robot):
            self.check(answer, initial_state)
        return answer

    def _attempt(self, initial_state: FloatArray, robot: Robot | None) -> tuple[ExpertTrajectory.Response | None, str]:
        """One attempt: a trajectory within expert_timeout, or why not.

        "busy:" and "not ready:" refusals (an expert with a full queue, or just restarted and still
        waiting for the plant) are asked again within the attempt, after growing pauses, and so are
        answers that are not this run's expert's (another server on the domain won the race).
        """
        deadline = time.monotonic() + self.timeout
        pause = RETRY_PAUSE_S
        request = self._request(initial_state, robot)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self.client.wait_for_service(timeout_sec=remaining):
                return None, f"service /{EXPERT_SERVICE} not available after {self.timeout:g} s"
            response = call_with_deadline(self.client, request, remaining, self.logger)
            if response is None:
                return None, f"no answer within {self.timeout:g} s"
            refusal, retry = self._refusal(response, request)
            if refusal is None:
                return response, ""
            if not retry or deadline - time.monotonic() <= pause:
                return None, refusal
            self.logger.info(refusal + "; asking again", throttle_duration_sec=5.0)
            if self.stop.wait(pause):
                return None, refusal
            pause = min(2 * pause, 2.0)

    def _refusal(
        self, response: ExpertTrajectory.Response, request: ExpertTrajectory.Request
    ) -> tuple[str | None, bool]:
        """(None, _) for a trajectory from this run's expert for this run's plant; else why not, and
        whether asking again may help."""
        if not response.success and response.message.startswith((BUSY, NOT_READY)):
            return f"expert refused: {response.message}", True
        if response.success and response.plant != self.plant.model_sha256:
            return (
                f"refused an answer for another plant (fingerprint {response.plant[:12] or 'none'}, this run's is "
                f"{self.plant.model_sha256[:12]}): a second sim or expert on the domain?"
            ), True
        try:
            self.seal.check(response, "the expert's answer", answering=request)
        except SealError as exc:
            return f"refused: {exc} ({self.servers()} servers of /{EXPERT_SERVICE} on the domain)", True
        if not response.success:
            return f"expert refused: {response.message}", False
        return None, False
