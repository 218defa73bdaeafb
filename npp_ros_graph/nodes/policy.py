"""npp-policy: answers every plant state with the greedy NPP action from the current dataset.

The dataset arrives trajectory by trajectory on /npp/dataset/trajectory; on start, after a
restart, or when it sees a gap in the trajectory indices, the node catches up through the
supervisor's /npp/dataset/get service, so nothing else needs restarting. With no data it says
so and publishes nothing: it never invents an action.

A state is answered in its callback, the fastest path round the control loop, unless the
worker thread holds the data (bringing the search index up to date, which takes seconds at 10^6
points); then the state waits in the worker's one-state mailbox. Either way only the newest state
is answered: the callback first takes any states that arrived after its own off the wire, and a
state overtaken by a newer one before it was answered is dropped (counted on
/npp/policy/dropped_states and in the log). Under a state stream faster than the policy, it
answers the newest state and never builds a queue.

The path policy (npp_ros.policy.path) remembers its path within an episode: the node starts it afresh on an
episode's first state (the sim's state stamped 0, which every reset publishes first, a repeated episode too) and
on a state of another episode; a state it already answered (the sim's watchdog sends it again) gets the same
action again without advancing the path, so a rollout through the graph is the in-process one.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from builtin_interfaces.msg import Time
from npp_interfaces.msg import PlantDescription
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import GetTrajectories
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32, UInt64

from npp_ros.policy.bounds import NonparametricPolicy, PathEpisode
from npp_ros.policy.dataset import Dataset, DatasetError
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health
from npp_ros_graph.runtime.mailbox import Mailbox
from npp_ros_graph.runtime.node import ThrottledWarnings, publishers_of, run_node
from npp_ros_graph.transport.convert import (
    policy_spec_from_msg,
    refill_action,
    state_from_joint_state,
    trajectory_from_msg,
)
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.parameters import declare_settings
from npp_ros_graph.transport.topics import (
    ACTION,
    CONTROL_QOS,
    DATASET_SERVICE,
    DATASET_TOPIC,
    LATCHED_QOS,
    LATCHED_READER_QOS,
    PLANT,
    POLICY_DROPPED,
    POLICY_STATUS,
    REPORT_QOS,
    STATE,
)

CATCH_UP_TIMEOUT_S = 5.0  # a catch-up request unanswered this long is withdrawn and sent again
REPORT_EVERY_S = 1.0
IDLE_S = 0.1  # no state for this long: the control loop is idle, the worker may bring the index up to date

Pending = tuple[int, np.ndarray, Time, str]  # (arrival number, state, its stamp, its episode): a state to answer

USAGE = f"""npp-policy: greedy NPP actions for every state (ROS 2 node "npp_policy").

subscribes  /{STATE} (sensor_msgs/JointState), /{PLANT} (latched), /{DATASET_TOPIC}
publishes   /{ACTION} (sensor_msgs/JointState: effort = action, stamp = the answered state's)
            /{POLICY_STATUS} (std_msgs/UInt32, latched: trajectories held)
            /{POLICY_DROPPED} (std_msgs/UInt64: states dropped so far because a newer one arrived
            before they were answered; published when it changes, at most every {REPORT_EVERY_S:g} s)
calls       /{DATASET_SERVICE} to catch up with the supervisor's dataset
parameters  none: L and the data come from the supervisor, the plant from the sim

A state with wrong joint names or counts, or non-finite values, is refused with a log line, and so is
anything (plant, state, trajectory, dataset answer) that does not carry the run's seal (NPP_RUN_KEY).
"""


@dataclass(frozen=True)
class PolicySettings:
    """None: L and the data come from the supervisor, the plant from the sim (a stray -p is refused)."""


class PolicyNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_policy")
        declare_settings(self, (), PolicySettings)
        self.plant: PlantDescription | None = None
        self.run_seal = RunSeal.from_environment()
        self.plant_seal: RunSeal | None = None  # the run key's seal for the plant, once described
        self.run = ""  # the identity of the run whose data the policy holds (the supervisor's answers name it)
        self.seal: RunSeal | None = None  # that run's seal
        self._action = JointState()
        self.dataset: Dataset | None = None
        self.policy: NonparametricPolicy | None = None
        self.spec: PolicySpec | None = None  # how the run's policy acts (its L follows the trajectories' messages)
        self._episode: NonparametricPolicy | PathEpisode | None = None  # what acts over the sim's current episode
        self._episode_of: NonparametricPolicy | None = None  # the policy it is of
        self._catch_up_future = None
        self._catch_up_sent = 0.0
        self._catch_up_needed = True
        # Whoever answers or indexes holds the data, so the worker's index build never meets an append.
        self._data_lock = threading.Lock()
        self._inbox: Mailbox[Pending] = Mailbox(keep=1)
        self._arrivals = 0  # states taken off the wire (executor thread)
        self._last_answered = 0  # arrival number of the newest state answered (under the data lock)
        self._last_state_at = time.monotonic()
        # States overtaken by a newer one before they were answered: counted by the executor (mailbox,
        # wire) and by whoever answers (a newer one was answered first); each thread writes its own.
        self._dropped_waiting = 0
        self._dropped_answering = 0
        self.answered = 0
        self._dropped_reported = 0
        # The state answered last (episode, stamp) and its action: the path policy's episode and step.
        self._answered_key: tuple[str, int, int] | None = None
        self._answered_action: np.ndarray | None = None
        self._warn = ThrottledWarnings(self)
        self.action_pub = self.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.status_pub = self.create_publisher(UInt32, POLICY_STATUS, LATCHED_QOS)
        self.dropped_pub = self.create_publisher(UInt64, POLICY_DROPPED, REPORT_QOS)
        self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_READER_QOS)
        self.create_subscription(TrajectoryMsg, DATASET_TOPIC, self.on_trajectory, REPORT_QOS)
        self._state_sub = self.create_subscription(JointState, STATE, self.on_state, CONTROL_QOS)
        self.dataset_client = self.create_client(GetTrajectories, DATASET_SERVICE)
        self.create_timer(0.5, self.maybe_catch_up)
        self.create_timer(REPORT_EVERY_S, self.report_dropped)
        self._worker = threading.Thread(target=self._work, name="npp-policy-worker", daemon=True)
        self._worker.start()
        self.diagnostics = DiagnosticsReporter(self, lambda: Health(
            "waiting for data" if self.policy is None else f"acting on {self.policy.dataset.num_trajectories} "
            "trajectories",
            {"answered": self.answered, "dropped states": self.dropped, "waiting": len(self._inbox)},
            error=self._warn.last))  # fmt: skip

    # ---------------------------------------------------------------- dataset
    def _foreign(self, topic: str, exc: SealError) -> None:
        name = self.resolve_topic_name(topic)
        self._warn(f"foreign {topic}", f"refused: {exc} (publishers of {name}: {publishers_of(self, topic)})")

    def on_plant(self, msg: PlantDescription) -> None:
        try:
            self.run_seal.check(msg, "a plant description")
        except SealError as exc:
            self._foreign(PLANT, exc)
            return
        if self.plant is not None and (msg.task, msg.seed) != (self.plant.task, self.plant.seed):
            self.get_logger().error(f"plant changed from {self.plant.task} to {msg.task}; restart the policy")
            return
        if self.plant is None:
            self.plant_seal = self.run_seal.for_plant(msg.model_sha256)
            self.plant = msg
            self._action = JointState(name=list(msg.actuated_joint_names))  # refilled for every answer
            self.dataset = Dataset(msg.state_dim, msg.action_dim)
            self.get_logger().info(f"plant {msg.task} seed {msg.seed}; catching up with the dataset")

    def on_trajectory(self, msg: TrajectoryMsg) -> None:
        if self.dataset is None or self.policy is None or self.seal is None or msg.run != self.run:
            self._catch_up_needed = True  # the supervisor's dataset service says which run is its own
            return
        try:
            self.seal.check(msg, f"trajectory {msg.index}")
        except SealError as exc:
            self._foreign(DATASET_TOPIC, exc)
            return
        held = self.dataset.num_trajectories
        if msg.index < held:
            return  # already have it (catch-up and topic overlap)
        if msg.index > held:
            self._catch_up_needed = True  # missed some: fetch them in order
            return
        self._append(msg)

    def _append(self, msg: TrajectoryMsg) -> bool:
        assert self.dataset is not None
        try:
            _, traj = trajectory_from_msg(msg)
            with self._data_lock:
                self.dataset.append(traj)
                self._follow_lipschitz(msg.policy_lipschitz)
        except DatasetError as exc:
            self.get_logger().error(f"trajectory {msg.index} refused: {exc}")
            return False
        self.status_pub.publish(UInt32(data=self.dataset.num_trajectories))
        return True

    def _follow_lipschitz(self, lipschitz: float) -> None:
        """The run chose another L for its policy as its data grew (npp_ros.run.policy_lipschitz): act by it, with the
        trajectory that brought it (so the count the sim waits for and the L arrive together). Under the data lock."""
        spec = self.spec
        if spec is None or self.dataset is None or lipschitz <= 0 or lipschitz == spec.lipschitz.value:
            return
        self.spec = replace(spec, lipschitz=LipschitzConstant(lipschitz, "selected"))
        self.policy = self.spec.build(self.dataset)
        self.get_logger().info(f"the run's policy now acts by L = {lipschitz:g} (chosen from its data)")

    def maybe_catch_up(self) -> None:
        pending = self._catch_up_future
        if pending is not None:
            # A supervisor killed mid-request, or a response Fast DDS dropped before it matched this
            # (new) client, never answers: withdraw the request and ask again, or catch-up stalls forever.
            if time.monotonic() - self._catch_up_sent < CATCH_UP_TIMEOUT_S:
                return
            self.dataset_client.remove_pending_request(pending)
            self._catch_up_future = None
            self.get_logger().warning(f"no catch-up answer within {CATCH_UP_TIMEOUT_S:g} s; asking again")
        if self.dataset is None or not self._catch_up_needed:
            return
        if not self.dataset_client.service_is_ready():
            self.get_logger().info("waiting for the supervisor's dataset service", throttle_duration_sec=10.0)
            return
        request = GetTrajectories.Request(start=self.dataset.num_trajectories, max_count=50)
        self._catch_up_sent = time.monotonic()
        self._catch_up_future = future = self.dataset_client.call_async(request)
        future.add_done_callback(lambda done: self.on_catch_up(done, request))

    def on_catch_up(self, future, request: GetTrajectories.Request) -> None:
        if future is not self._catch_up_future:
            return  # a withdrawn request answered late
        self._catch_up_future = None
        response = future.result()
        if response is None or not response.success:
            self.get_logger().warning(f"catch-up failed: {getattr(response, 'message', 'no response')}")
            return
        assert self.plant_seal is not None and self.dataset is not None
        try:
            seal = self.plant_seal.for_run(response.run)
            seal.check(response, "the dataset service's answer", answering=request)
            for msg in response.trajectories:
                if msg.run != response.run:
                    raise SealError(f"trajectory {msg.index} of the dataset service's answer belongs to another run")
                seal.check(msg, f"trajectory {msg.index} of the dataset service's answer")
        except SealError as exc:
            self._catch_up_needed = True
            self._warn("foreign dataset", f"catch-up answer refused: {exc}")
            return
        if response.run != self.run:
            self._start_run(response.run, seal)
            if request.start != 0:
                self._catch_up_needed = True  # this answer paged from the old run's count: ask from the start
                return
        if self.policy is None:
            assert self.dataset is not None and self.plant is not None
            try:
                spec = policy_spec_from_msg(response.policy)  # the run's policy, whole, as the supervisor sends it
                policy = spec.build(self.dataset)
            except ValueError as exc:
                self._catch_up_needed = True
                self._warn("policy", f"cannot act as the supervisor asks: {exc}")
                return
            with self._data_lock:
                self.policy, self.spec = policy, spec
            self.get_logger().info(f"acting greedily as the run certifies: {spec.describe()}")
        for msg in response.trajectories:
            if msg.index == self.dataset.num_trajectories and not self._append(msg):
                break
        self._catch_up_needed = self.dataset.num_trajectories < response.total
        self.status_pub.publish(UInt32(data=self.dataset.num_trajectories))
        if not self._catch_up_needed:
            self.get_logger().info(f"holding {self.dataset.num_trajectories} trajectories ({len(self.dataset)} points)")

    def _start_run(self, run: str, seal: RunSeal) -> None:
        """Hold the data of `run` from now on: the supervisor's run is another than the one the data came from
        (a new run file), so the old data go and the new run's are fetched."""
        assert self.plant is not None
        if self.run:
            self.get_logger().warning(
                f"the supervisor now runs {run[:12]}, not {self.run[:12]} whose data this policy held; starting over"
            )
        with self._data_lock:
            self.run, self.seal = run, seal
            self.dataset = Dataset(self.plant.state_dim, self.plant.action_dim)
            self.policy = self.spec = None
            self._answered_key = None

    # ---------------------------------------------------------------- acting
    @property
    def dropped(self) -> int:
        return self._dropped_waiting + self._dropped_answering

    def on_state(self, msg: JointState) -> None:
        """Answer the newest state: here when the data is free, else through the worker's mailbox."""
        newest = self._newest_state(msg)
        if newest is None:
            return
        self._arrivals += 1
        self._last_state_at = time.monotonic()
        pending = (self._arrivals, *newest)
        if self._data_lock.acquire(blocking=False):
            try:
                self._answer(pending)
            finally:
                self._data_lock.release()
        elif self._inbox.put(pending) is not None:
            self._dropped_waiting += 1

    def _newest_state(self, msg: JointState) -> tuple[np.ndarray, Time, str] | None:
        """The newest answerable state among `msg` and those already behind it on the wire."""
        newest = None
        sub = self._state_sub
        while msg is not None:
            try:
                state, episode = self._state(msg)
            except SealError as exc:
                self._foreign(STATE, exc)
                self._catch_up_needed = True  # a state of another run: has the supervisor started a new one?
            except ValueError as exc:
                problem = str(exc)
                self._warn(problem.split(":")[0], f"state refused: {problem}")
            else:
                if newest is not None:
                    self._dropped_waiting += 1
                newest = (state, msg.header.stamp, episode)
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            msg = None if taken is None else taken[0]
        return newest

    def _state(self, msg: JointState) -> tuple[np.ndarray, str]:
        """The state a message carries and its episode, if the policy can answer it; else a ValueError
        (a SealError for a state from outside the run) saying why not."""
        plant, seal = self.plant, self.seal
        if plant is None:
            raise ValueError("no plant description yet: cannot read states")
        if seal is None:
            raise ValueError("no data yet: the policy has no action to give")
        episode = seal.check_header(msg, "a state")
        if self.policy is None or self.dataset is None or len(self.dataset) == 0:
            raise ValueError("no data yet: the policy has no action to give")
        return state_from_joint_state(msg, plant.joint_names), episode

    def _work(self) -> None:
        """Worker thread: answers the states that came while it held the data; when the control loop
        is idle it brings the search index up to date with newly appended data, so index builds and
        merges (seconds at 10^6 points) happen between episodes, not inside a control step.
        """
        while not self._inbox.closed:
            pending = self._inbox.take(timeout=IDLE_S)
            if pending is not None:
                with self._data_lock:
                    self._answer(pending)
            elif time.monotonic() - self._last_state_at >= IDLE_S:
                self._warm_index()

    def _warm_index(self) -> None:
        policy = self.policy
        if policy is None or policy.index is None:
            return
        with self._data_lock:
            policy.index.sync()

    def _answer(self, pending: Pending) -> None:
        """Publish the greedy action for a state, unless a newer one was answered first (data lock held)."""
        arrival, state, stamp, episode = pending
        if arrival <= self._last_answered:
            self._dropped_answering += 1
            return
        self._last_answered = arrival
        assert self.policy is not None and self.seal is not None
        try:
            action = refill_action(self._action, self._act(state, stamp, episode), stamp)
            # The context says which episode it answers and which data chose it (the sim reports the latter).
            held = self.policy.dataset.num_trajectories
            self.action_pub.publish(self.seal.seal_header(action, f"{episode}/{held}"))
        except Exception as exc:  # neither the executor nor the worker may die of a single bad state
            self.get_logger().error(f"could not answer a state: {type(exc).__name__}: {exc}")
            return
        self.answered += 1

    def _act(self, state: np.ndarray, stamp: Time, episode: str) -> np.ndarray:
        """The policy's action for this state of this episode (data lock held): the episode's first state starts
        the policy afresh; a state answered already gets its action again."""
        assert self.policy is not None
        key = (episode, stamp.sec, stamp.nanosec)
        if self.policy.kind == "path" and key == self._answered_key and self._answered_action is not None:
            return self._answered_action
        new_episode = self._answered_key is None or key[1:] == (0, 0) or episode != self._answered_key[0]
        if new_episode or self._episode is None or self._episode_of is not self.policy:
            self._episode, self._episode_of = self.policy.episode(), self.policy  # new data: the path starts afresh
        self._answered_action = self._episode.act(state)
        self._answered_key = key
        return self._answered_action

    def report_dropped(self) -> None:
        dropped = self.dropped
        if dropped == self._dropped_reported:
            return
        self.dropped_pub.publish(UInt64(data=dropped))
        self.get_logger().warning(
            f"dropped {dropped - self._dropped_reported} stale states in the last {REPORT_EVERY_S:g} s "
            f"({dropped} in all, {self.answered} answered): states arrive faster than the policy answers; "
            "each was overtaken by a newer one"
        )
        self._dropped_reported = dropped

    def destroy_node(self) -> None:
        self._inbox.close()
        self._worker.join(timeout=5.0)
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyNode, argv, USAGE, events=True)  # the control loop: no wait set to rebuild per state


if __name__ == "__main__":
    sys.exit(main())
