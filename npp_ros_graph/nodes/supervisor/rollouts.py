"""The episode driver over the graph: the sim reset to s0, the policy node driving, the sim's return back.

The node's callbacks fill the RolloutHandshake (what the policy holds, the sim's results); the worker
thread that runs Algorithm 1 waits on it in RosRollouts, never polls.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from npp_interfaces.msg import EpisodeResult
from npp_interfaces.srv import ResetEpisode
from rclpy.client import Client
from rclpy.impl.rcutils_logger import RcutilsLogger
from std_msgs.msg import UInt32

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros_graph.runtime.deadlines import RESEND_S, call_with_deadline
from npp_ros_graph.transport.convert import float64_array
from npp_ros_graph.transport.seal import RunSeal, SealError
from npp_ros_graph.transport.topics import RESET_SERVICE


class RolloutHandshake:
    """What an episode's rollout waits for: the policy holding the current dataset, then the sim's
    result for that episode. Subscription callbacks record both and notify; the worker waits on the
    same Condition, so it wakes when either arrives, never polls.
    """

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._policy_holds = -1  # trajectories the policy reported last (-1: no report yet)
        self._results: dict[int, tuple[EpisodeResult, str]] = {}  # episode -> (result, data it was driven with)

    def on_policy_status(self, msg: UInt32) -> None:
        with self._changed:
            self._policy_holds = int(msg.data)
            self._changed.notify_all()

    def on_rollout(self, msg: EpisodeResult, driven_with: str) -> None:
        with self._changed:
            self._results[int(msg.episode)] = (msg, driven_with)
            self._changed.notify_all()

    def policy_holds(self, trajectories: int) -> bool:
        return self._policy_holds >= trajectories

    @property
    def policy_reported(self) -> int:
        return self._policy_holds

    def wait_for_policy(self, trajectories: int, deadline: float) -> bool:
        """Whether the policy holds at least `trajectories` by the deadline (time.monotonic)."""
        with self._changed:
            return self._changed.wait_for(
                lambda: self._policy_holds >= trajectories, max(deadline - time.monotonic(), 0.0)
            )

    def wait_for_rollout(self, episode: int, deadline: float) -> tuple[EpisodeResult, str] | None:
        """The sim's result for `episode` and the data it was driven with, or None when the deadline passes
        first; results of earlier episodes that finish late (skipped ones) are discarded."""
        with self._changed:
            self._changed.wait_for(lambda: episode in self._results, max(deadline - time.monotonic(), 0.0))
            result = self._results.pop(episode, None)
            for late in [k for k in self._results if k < episode]:
                del self._results[late]
        return result


class RosRollouts:
    """Episode driver: reset the sim to s0 and let the policy node drive; returns the sim's return.

    It gets what it uses: the reset client, the run's seal, the handshake the node's callbacks fill,
    a way to send the policy the trajectories it lacks, and the node's stop event and logger.
    """

    def __init__(
        self,
        reset: Client,
        seal: RunSeal,
        handshake: RolloutHandshake,
        send_trajectories: Callable[[int, int], None],
        *,
        stop: threading.Event,
        logger: RcutilsLogger,
        timeout: float,
    ) -> None:
        self.reset, self.seal, self.handshake, self.send_trajectories = reset, seal, handshake, send_trajectories
        self.stop, self.logger, self.timeout = stop, logger, timeout

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float | None:
        log, handshake = self.logger, self.handshake
        held = policy.dataset.num_trajectories
        deadline = time.monotonic() + self.timeout
        if not self._policy_up_to_date(held, deadline):
            log.warning(f"episode {episode}: the policy is not up to date; no rollout this episode")
            return None
        problem = self._reset(episode, initial_state, deadline)
        if problem is not None:
            log.warning(f"episode {episode}: {problem}; no rollout this episode")
            return None
        outcome = handshake.wait_for_rollout(episode, max(deadline, time.monotonic() + 1.0))
        if outcome is None:
            log.warning(f"episode {episode}: the policy's episode did not finish in time; no return recorded")
            return None
        result, driven_with = outcome
        if driven_with != str(held):
            log.error(
                f"episode {episode}: the return was earned by a policy over {driven_with or 'unknown'} trajectories, "
                f"not the {held} under test; no return recorded"
            )
            return None
        return float(result.policy_return)

    def _policy_up_to_date(self, held: int, deadline: float) -> bool:
        """Wait until the policy holds `held` trajectories; what it still lacks is sent again every RESEND_S."""
        handshake = self.handshake
        while not handshake.policy_holds(held):
            now = time.monotonic()
            if now >= deadline:
                return False
            if handshake.wait_for_policy(held, min(deadline, now + RESEND_S)):
                return True
            reported = handshake.policy_reported
            self.logger.info(
                f"the policy holds {max(reported, 0)} of {held} trajectories; sending the missing ones again",
                throttle_duration_sec=10.0,
            )
            self.send_trajectories(max(reported, 0), held)
        return True

    def _reset(self, episode: int, initial_state: FloatArray, deadline: float) -> str | None:
        """Reset the sim for `episode`, asking again every RESEND_S: a paused sim loses requests, and an
        answer that is not this run's sim's (a second sim on the domain) does not count. None once done."""
        request = self.seal.seal(ResetEpisode.Request(state=float64_array(initial_state), episode=episode))
        problem = "sim reset service unavailable"
        while (remaining := deadline - time.monotonic()) > 0:
            if not self.reset.wait_for_service(timeout_sec=min(remaining, RESEND_S)):
                continue
            response = call_with_deadline(self.reset, request, min(remaining, RESEND_S), self.logger)
            if response is None:
                problem = "no answer to the sim reset"
                continue
            try:
                self.seal.check(response, "the sim's reset answer", answering=request)
            except SealError as exc:
                problem = f"refused: {exc} (servers of /{RESET_SERVICE}: a second sim on the domain?)"
                self.logger.warning(problem, throttle_duration_sec=5.0)
                self.stop.wait(0.05)  # the other sim's answer may win every race; let ours arrive
                continue
            if response.success:
                return None
            problem = f"sim reset failed: {response.message}"
            if self.stop.wait(min(RESEND_S, max(deadline - time.monotonic(), 0.0))):
                break
        return problem
