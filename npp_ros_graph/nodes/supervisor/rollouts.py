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
from npp_ros.run.loop import EpisodeInterrupted
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.runtime.deadlines import RESEND_S, call_with_deadline
from npp_ros_graph.transport.convert import float64_array, robot_to_field
from npp_ros_graph.transport.message_seal import RunSeal, SealError
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
        self.closed = False

    def close(self) -> None:
        """Wake every waiter: the node is closing."""
        with self._changed:
            self.closed = True
            self._changed.notify_all()

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
            return (
                self._changed.wait_for(
                    lambda: self._policy_holds >= trajectories or self.closed, max(deadline - time.monotonic(), 0.0)
                )
                and not self.closed
            )

    def wait_for_rollout(self, episode: int, deadline: float) -> tuple[EpisodeResult, str] | None:
        """The sim's result for `episode` and the data it was driven with, or None when the deadline passes
        first; results of earlier episodes that finish late (skipped ones) are discarded."""
        with self._changed:
            self._changed.wait_for(
                lambda: episode in self._results or self.closed, max(deadline - time.monotonic(), 0.0)
            )
            result = self._results.pop(episode, None)
            for late in [k for k in self._results if k < episode]:
                del self._results[late]
        return result


class RosRollouts:
    """Episode driver: reset the sim to s0 and let the policy node drive; returns the sim's return.

    A check is decided by the policy's return, never by a fault: nothing here gives an episode up. A
    result lost on its way (a pause past the middleware's lease, a restarted node, a dropped message) is
    asked for again every RESEND_S by repeating the reset, which the sim answers without restarting the
    episode (it sends a finished episode's result again); an attempt that has run `timeout` seconds with
    no result, or whose result was earned by a policy over other data, is run again from the same s0
    (the plant is deterministic and the policy under test frozen, so the return is the same). Under model
    uncertainty the reset names the episode's robot, and only a result the sim says it ran on that robot
    counts. While it
    waits it says for what; when the node closes it raises EpisodeInterrupted and nothing is recorded.

    It gets what it uses: the reset client, the run's seal and identity, the handshake the node's
    callbacks fill, a way to send the policy the trajectories it lacks, and the node's stop event and logger.
    """

    def __init__(
        self,
        reset: Client,
        seal: RunSeal,
        run_id: str,
        handshake: RolloutHandshake,
        send_trajectories: Callable[[int, int], None],
        *,
        stop: threading.Event,
        logger: RcutilsLogger,
        timeout: float,
    ) -> None:
        self.reset, self.seal, self.run_id = reset, seal, run_id
        self.handshake, self.send_trajectories = handshake, send_trajectories
        self.stop, self.logger, self.timeout = stop, logger, timeout
        self.waiting = ""  # what the running episode has waited for beyond the usual ("": nothing), for /diagnostics

    def _wait(self, text: str, warn: bool = False) -> None:
        """Say what the episode waits for: in the log (throttled) and, until it ends, on /diagnostics."""
        self.waiting = text
        # One call site per severity: rclpy refuses a logging call site whose severity changes between calls.
        if warn:
            self.logger.warning(text, throttle_duration_sec=10.0)
        else:
            self.logger.info(text, throttle_duration_sec=10.0)

    def run_episode(
        self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> float:
        held = policy.dataset.num_trajectories
        robot_field = robot_to_field(robot)
        attempt = 0
        while True:
            self._policy_up_to_date(episode, held)
            request = self.seal.seal(
                ResetEpisode.Request(state=float64_array(initial_state), episode=episode, attempt=attempt,
                                     run=self.run_id, robot=robot_field)
            )  # fmt: skip
            outcome = self._result(episode, request)
            self.waiting = ""
            attempt += 1
            if outcome is None:
                self.logger.warning(
                    f"episode {episode}: no result after {self.timeout:g} s (rollout_timeout); running it again"
                )
                continue
            result, driven_with = outcome
            if result.robot != robot_field:
                self.logger.error(
                    f"episode {episode}: the sim ran it on {result.robot or 'the nominal model'}, not on "
                    f"{robot_field or 'the nominal model'}; running the episode again"
                )
                continue
            if driven_with == str(held):
                return float(result.policy_return)
            self.logger.error(
                f"episode {episode}: the return was earned by a policy over {driven_with or 'unknown'} trajectories, "
                f"not the {held} under test; running the episode again"
            )

    def _interrupted(self, episode: int) -> None:
        if self.stop.is_set():
            raise EpisodeInterrupted(f"the node is closing during episode {episode}; it is not recorded")

    def _result(self, episode: int, request: ResetEpisode.Request) -> tuple[EpisodeResult, str] | None:
        """The sim's result for this attempt, or None once it has run `timeout` seconds without one."""
        handshake = self.handshake
        started = time.monotonic()
        while time.monotonic() - started < self.timeout:
            self._interrupted(episode)
            problem = self._reset(request)
            if problem is not None:
                self._wait(f"episode {episode} waits for the sim: {problem}", warn=True)
                self.stop.wait(RESEND_S / 4)
                continue
            outcome = handshake.wait_for_rollout(episode, time.monotonic() + RESEND_S)
            if outcome is not None:
                return outcome
            self._wait(
                f"episode {episode} waits for the policy's rollout ({time.monotonic() - started:.0f} s); "
                "asking the sim where it stands"
            )
        self._interrupted(episode)
        return None

    def _policy_up_to_date(self, episode: int, held: int) -> None:
        """Wait until the policy holds `held` trajectories; what it still lacks is sent again every RESEND_S."""
        handshake = self.handshake
        while not handshake.wait_for_policy(held, time.monotonic() + RESEND_S):
            self._interrupted(episode)
            reported = handshake.policy_reported
            self._wait(
                f"episode {episode} waits for the policy: it holds {max(reported, 0)} of {held} trajectories; "
                "sending the missing ones again"
            )
            self.send_trajectories(max(reported, 0), held)

    def _reset(self, request: ResetEpisode.Request) -> str | None:
        """Ask the sim to start (or, repeated, to report on) the episode: None once it has, else why not."""
        if not self.reset.wait_for_service(timeout_sec=RESEND_S):
            return f"the reset service /{RESET_SERVICE} is not available"
        response = call_with_deadline(self.reset, request, RESEND_S, self.logger)
        if response is None:
            return "no answer to the reset"
        try:
            self.seal.check(response, "the sim's reset answer", answering=request)
        except SealError as exc:
            self.stop.wait(0.05)  # the other sim's answer may win every race; let ours arrive
            return f"refused: {exc} (servers of /{RESET_SERVICE}: a second sim on the domain?)"
        return None if response.success else f"the sim refused the reset: {response.message}"
