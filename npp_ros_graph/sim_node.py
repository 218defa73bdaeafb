"""npp-sim: the dm_control lqr plant stepped in lockstep with whoever answers its states.

It publishes a state, then waits: only an action stamped with that state's time moves the plant,
so a slow or restarted policy can never make it skip or double a step. Anything else arriving on
the action topic is ignored with a (throttled) warning. The plant description goes out latched so
that an expert started at any time models exactly this plant.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from npp_interfaces.msg import EpisodeResult, PlantDescription
from npp_interfaces.srv import ResetEpisode
from rclpy.node import Node
from sensor_msgs.msg import JointState

from npp_ros.lqr import MAX_HORIZON, TASKS, LQRPlant, UnknownTaskError, check_task, episode_rng, sample_initial_state
from npp_ros_graph.common import (
    ACTION,
    CONTROL_QOS,
    LATCHED_QOS,
    PLANT,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    SERVICE_QOS,
    STATE,
    StartupError,
    ThrottledWarnings,
    declare_all,
    float64_array,
    parameter_help,
    run_node,
)

PARAMETERS: list[tuple[str, Any, str]] = [
    ("task", "lqr_2_1", f"dm_control lqr task, one of {', '.join(sorted(TASKS))}"),
    ("seed", 0, "task seed: the plant's stiffnesses depend on it; also seeds s0 ~ rho per episode"),
    ("horizon", 1000, f"control steps per episode, in [1, {MAX_HORIZON}]"),
    ("resend_after", 1.0, "seconds without an answer before the current state is sent again (0 = never)"),
]

USAGE = f"""npp-sim: the lqr plant in lockstep (node "npp_sim").

After a reset it publishes the episode's first state, then steps once per action answering the
latest state, and publishes the next state; after `horizon` steps it reports the episode. A state
left unanswered for `resend_after` seconds is sent again with the same stamp, so a policy node
started or restarted mid-episode picks the episode up where it stopped.

publishes   /{PLANT} (npp_interfaces/msg/PlantDescription, latched)
            /{STATE} (sensor_msgs/JointState: position = qpos, velocity = qvel, stamp = simulated time)
            /{ROLLOUT_DONE} (npp_interfaces/msg/EpisodeResult: return and steps of the finished episode)
subscribes  /{ACTION} (sensor_msgs/JointState: effort = action, name = actuated joints or empty,
            stamp = the stamp of the state it answers; anything else is ignored with a warning)
serves      /{RESET_SERVICE} (npp_interfaces/srv/ResetEpisode: empty state = sample s0 ~ rho for
            the given episode index, else reset to the given state)

{parameter_help(PARAMETERS)}
"""


def _stamp(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


class SimNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_sim")
        params = declare_all(self, PARAMETERS)
        self.task, self.seed, self.horizon, self.resend_after = self._validated(params)
        self.plant: LQRPlant | None = None
        self.dt_ns = 0
        # The running episode; `stamp` is the last published state's time, None when no episode runs.
        self.episode = 0
        self.steps = 0
        self.episode_return = 0.0
        self.initial_state = np.zeros(0)
        self.stamp: Time | None = None
        self._last_state: JointState | None = None
        self._last_sent = 0.0
        self.ignored_actions = 0
        self._warn = ThrottledWarnings(self)
        self.plant_pub = self.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
        self.state_pub = self.create_publisher(JointState, STATE, CONTROL_QOS)
        self.done_pub = self.create_publisher(EpisodeResult, ROLLOUT_DONE, REPORT_QOS)
        self.create_subscription(JointState, ACTION, self.on_action, CONTROL_QOS)
        self.create_service(ResetEpisode, RESET_SERVICE, self.on_reset, qos_profile=SERVICE_QOS)
        self._build_timer = self.create_timer(0.0, self._build)  # MuJoCo loads after init, not inside it
        if self.resend_after > 0:
            self.create_timer(min(self.resend_after, 0.25), self._resend_if_unanswered)

    @staticmethod
    def _validated(params: dict[str, Any]) -> tuple[str, int, int, float]:
        """All parameter checks in one place, so a bad launch fails at once with the reason."""
        task, seed, horizon = params["task"], params["seed"], params["horizon"]
        try:
            check_task(str(task))
        except UnknownTaskError as exc:
            raise StartupError(f"parameter task: {exc}") from None
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
            raise StartupError(f"parameter seed must be an integer in [0, 2^32), got {seed!r}")
        if isinstance(horizon, bool) or not isinstance(horizon, int) or not 1 <= horizon <= MAX_HORIZON:
            raise StartupError(f"parameter horizon must be an integer in [1, {MAX_HORIZON}], got {horizon!r}")
        resend_after = params["resend_after"]
        if not 0 <= resend_after < float("inf"):
            raise StartupError(f"parameter resend_after must be >= 0 seconds, got {resend_after!r}")
        return str(task), int(seed), int(horizon), float(resend_after)

    def _build(self) -> None:
        self._build_timer.cancel()
        self.destroy_timer(self._build_timer)
        try:
            plant = LQRPlant(self.task, self.seed)
        except Exception as exc:  # run_node turns this into a clean exit with the reason
            raise StartupError(f"cannot build the plant {self.task} seed {self.seed}: {exc}") from exc
        self.plant = plant
        self.dt_ns = round(plant.dt * 1e9)
        desc = PlantDescription(
            task=self.task,
            seed=self.seed,
            horizon=self.horizon,
            timestep=plant.dt,
            state_dim=plant.state_dim,
            action_dim=plant.action_dim,
            joint_names=list(plant.joint_names),
            actuated_joint_names=list(plant.actuated_joint_names),
            model_sha256=plant.model_sha256(),
        )
        self.plant_pub.publish(desc)
        self.get_logger().info(
            f"plant {self.task} seed {self.seed} ready: joints {plant.joint_names}, "
            f"actuated {plant.actuated_joint_names}, dt {plant.dt} s, horizon {self.horizon}"
        )

    # ------------------------------------------------------------------ reset
    def on_reset(self, request: ResetEpisode.Request, response: ResetEpisode.Response) -> ResetEpisode.Response:
        try:
            problem = self._reset(request)
        except Exception as exc:  # never let an exception escape into the executor
            self.get_logger().error(f"reset failed: {type(exc).__name__}: {exc}")
            problem = f"internal error during reset: {exc}"
        if problem is not None:
            self.get_logger().warning(f"refused a reset: {problem}", throttle_duration_sec=1.0)
            response.success, response.message = False, problem
            return response
        response.success = True
        response.message = f"episode {self.episode} started"
        response.state = float64_array(self.initial_state)
        return response

    def _reset(self, request: ResetEpisode.Request) -> str | None:
        plant = self.plant
        if plant is None:
            return f"the plant {self.task} seed {self.seed} is still being built; retry shortly"
        n = plant.state_dim
        if len(request.state) == 0:
            s0 = sample_initial_state(self.task, episode_rng(self.seed, request.episode))
        else:
            s0 = np.asarray(request.state, dtype=np.float64)
            if s0.shape != (n,):
                return (
                    f"state has {s0.size} entries, expected {n} (qpos then qvel of {plant.bodies} joints of "
                    f"{self.task}), or none to sample s0"
                )
            bad = np.flatnonzero(~np.isfinite(s0))
            if bad.size:
                return "state must be finite: " + ", ".join(f"state[{i}] = {s0[i]}" for i in bad[:5])
        if self.stamp is not None:
            self.get_logger().info(f"episode {self.episode} abandoned after {self.steps} steps by a reset")
        self.initial_state = plant.reset(s0)
        self.episode = int(request.episode)
        self.steps = 0
        self.episode_return = 0.0
        self._publish_state()
        return None

    # -------------------------------------------------------------- lockstep
    def on_action(self, msg: JointState) -> None:
        try:
            problem = self._step(msg)
        except Exception as exc:  # never let an exception escape into the executor
            self.get_logger().error(f"step failed: {type(exc).__name__}: {exc}")
            problem = f"internal error: {exc}"
        if problem is not None:
            self.ignored_actions += 1
            self._warn(problem.split(":")[0], f"ignored an action: {problem}")

    def _step(self, msg: JointState) -> str | None:
        """Apply the action if it answers the current state; else say why not."""
        plant = self.plant
        if plant is None or self.stamp is None:
            return "no episode is running (reset the sim first)"
        got = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        want = (self.stamp.sec, self.stamp.nanosec)
        if got != want:
            return (
                f"stale: it answers the state stamped {got[0]}.{got[1]:09d}, the current one is {want[0]}.{want[1]:09d}"
            )
        if len(msg.name) and list(msg.name) != plant.actuated_joint_names:
            return f"wrong joint names: {list(msg.name)}, expected {plant.actuated_joint_names} (or none)"
        u = np.asarray(msg.effort, dtype=np.float64)
        if u.shape != (plant.action_dim,):
            return f"wrong effort length: {u.size} entries, expected {plant.action_dim} for {self.task}"
        bad = np.flatnonzero(~np.isfinite(u))
        if bad.size:
            return "non-finite effort: " + ", ".join(f"effort[{i}] = {u[i]}" for i in bad[:5])
        self.episode_return += plant.step(u)
        self.steps += 1
        if self.steps >= self.horizon:
            self._finish()
        else:
            self._publish_state()
        return None

    def _publish_state(self) -> None:
        assert self.plant is not None
        x = self.plant.state()
        b = self.plant.bodies
        self.stamp = _stamp(self.steps * self.dt_ns)
        msg = JointState()
        msg.header.stamp = self.stamp
        msg.name = list(self.plant.joint_names)
        msg.position = float64_array(x[:b])
        msg.velocity = float64_array(x[b:])
        self._send(msg)

    def _send(self, msg: JointState) -> None:
        self._last_state, self._last_sent = msg, time.monotonic()
        self.state_pub.publish(msg)

    def _resend_if_unanswered(self) -> None:
        """Lockstep watchdog: a policy that (re)joins mid-episode never saw the pending state."""
        if self.stamp is None or self._last_state is None:
            return
        if time.monotonic() - self._last_sent >= self.resend_after:
            self.get_logger().info(
                f"no answer to the state at step {self.steps} of episode {self.episode}; sending it again",
                throttle_duration_sec=10.0,
            )
            self._send(self._last_state)

    def _finish(self) -> None:
        result = EpisodeResult(
            episode=self.episode,
            policy_return=self.episode_return,
            steps=self.steps,
            initial_state=float64_array(self.initial_state),
            expert_value_known=False,
            expert_value=0.0,
            v_lb=0.0,
        )
        result.header.stamp = _stamp(self.steps * self.dt_ns)
        self.stamp = None  # no more states until the next reset
        self.done_pub.publish(result)
        self.get_logger().info(
            f"episode {self.episode} done: {self.steps} steps, return {self.episode_return:.3f}"
            + (f", {self.ignored_actions} actions ignored so far" if self.ignored_actions else "")
        )


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(SimNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
