"""npp-supervisor: Algorithm 1 over the ROS graph, with the same core loop as npp-learn.

Per episode: sample s0 (the core's seeded stream, so the in-process run gives the same
numbers), compute the gap, call the expert service when it exceeds epsilon (deadline and
retries), persist and hand the trajectory to the policy, reset the sim to s0, let the policy
drive, and publish the gap report and the episode result. Certifies and publishes the
certificate latched. Restarted on the same run folder, it resumes where the file ends.

Algorithm 1 runs in the node's worker thread, which makes synchronous calls with deadlines; the
executor's callbacks only hand data over: the plant through a Mailbox, what the policy holds and
the sim's rollout results through the RolloutHandshake, which the worker waits on.
"""

from __future__ import annotations

import csv
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import rclpy
from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.msg import EpisodeResult, GapReport, PlantDescription
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import ExpertTrajectory, GetTrajectories, ResetEpisode
from rclpy.client import Client
from rclpy.node import Node
from std_msgs.msg import UInt32

from npp_ros.answer_check import AnswerCheck
from npp_ros.bounds import NonparametricPolicy
from npp_ros.certification import (
    CERTIFY_MODES,
    CONDITIONS,
    STOPPING_RULES,
    Certificate,
    CertificationSpec,
    CertificationStatus,
    CheckedQuantity,
    Condition,
    StoppingRule,
)
from npp_ros.choices import LIPSCHITZ_NAMED, parse_lipschitz
from npp_ros.dataset import FloatArray, Trajectory
from npp_ros.lipschitz import LipschitzConstant
from npp_ros.loop import EpisodeInterrupted, NPPLoop, Observer, RunConfig
from npp_ros.run_setup import build_config, initial_state_fn, resolve_lipschitz, value_basis
from npp_ros.storage import EpisodeRow, RunStore
from npp_ros.tasks import get_task
from npp_ros_graph.common import (
    BUSY,
    CERTIFICATE,
    DATASET_SERVICE,
    DATASET_TOPIC,
    EPISODE,
    EXPERT_SERVICE,
    GAP,
    LATCHED_QOS,
    NOT_READY,
    PLANT,
    POLICY_STATUS,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    SERVICE_QOS,
    Mailbox,
    publishers_of,
    run_node,
)
from npp_ros_graph.convert import (
    certificate_to_msg,
    episode_result,
    float64_array,
    gap_report,
    trajectory_from_response,
    trajectory_to_msg,
)
from npp_ros_graph.parameters import Param, declare_settings, parameter_help
from npp_ros_graph.seal import RunSeal, SealError

TASK_DEFAULT = "task"  # a choice the task decides, once the sim names it

PARAMETERS = (
    Param("epsilon", 0.0, "target gap; 0 = the paper's value for the task (50 lqr_2_1, 300 lqr_6_2, 130 pendulum)",
          0.0),
    Param("lipschitz", TASK_DEFAULT, "L: analytic (bounds V*'s slope on the expert's states; lqr), paper (50 / 200 / "
          "4300, not a bound) or a number > 0; task = analytic where the task has it, else paper",
          choices=(TASK_DEFAULT, *LIPSCHITZ_NAMED, "a number > 0")),
    Param("condition", "i", "Theorem 4.1 condition", choices=CONDITIONS),
    Param("certify", TASK_DEFAULT, "the checked quantity (surrogate is the paper's); task = the task's own (rollout "
          "on lqr, oracle for the iLQR experts, whose claims are relative to the expert)",
          choices=(TASK_DEFAULT, *CERTIFY_MODES)),
    Param("rule", "sequential", "stopping rule: sequential (valid however often it looks) or the paper's",
          choices=STOPPING_RULES),
    Param("p", 0.9, "condition (i): share of initial states within epsilon, in (0, 1)", 0.0, 1.0),
    Param("delta", 0.1, "the claim holds with probability >= 1 - delta, in (0, 1)", 0.0, 1.0),
    Param("max_episodes", 1000, "stop uncertified after this many episodes", 1),
    Param("run_dir", "runs/graph", "run folder: run.sqlite, gaps.csv, episodes.csv"),
    Param("expert_timeout", 30.0, "seconds one expert attempt may take (a busy or not-ready expert is asked again)",
          1e-3),
    Param("expert_retries", 3, "expert attempts per episode, 0.25 s (doubling) apart, before the run stops", 1),
    Param("rollouts", True, "let the policy drive each episode through the sim (the sound checks need it)"),
    Param("rollout_timeout", 120.0, "seconds an episode may run without a result before it is run again from its s0 "
          "(a result lost in a pause is asked for again within seconds; no episode is skipped)", 1e-3),
)  # fmt: skip


@dataclass(frozen=True)
class SupervisorSettings:
    """The supervisor's parameters, checked at start by the constructors the run uses.

    CertificationSpec checks condition, certify, rule, p, delta and epsilon (stand-ins for what the
    task the sim will name decides: epsilon 0, certify and L "task", diam(S0)); parse_lipschitz
    reads L once.
    """

    epsilon: float
    lipschitz: str | LipschitzConstant
    condition: Condition
    certify: CheckedQuantity | str
    rule: StoppingRule
    p: float
    delta: float
    max_episodes: int
    run_dir: str
    expert_timeout: float
    expert_retries: int
    rollouts: bool
    rollout_timeout: float

    def __post_init__(self) -> None:
        if not self.run_dir.strip():
            raise ValueError("run_dir must name a folder")
        lipschitz = self.lipschitz
        if isinstance(lipschitz, str) and lipschitz != TASK_DEFAULT:
            lipschitz = parse_lipschitz(lipschitz)
        object.__setattr__(self, "lipschitz", lipschitz)
        CertificationSpec(
            self.condition, self.epsilon or 1.0, self.p, self.delta,
            lipschitz if isinstance(lipschitz, LipschitzConstant) else LipschitzConstant(1.0, "user"),
            1.0, certify="rollout" if self.certify == TASK_DEFAULT else self.certify, rule=self.rule,  # type: ignore[arg-type]
        )  # fmt: skip


USAGE = f"""npp-supervisor: Algorithm 1 over the ROS graph (ROS 2 node "npp_supervisor").

subscribes  /{PLANT} (latched), /{ROLLOUT_DONE}, /{POLICY_STATUS}
publishes   /{GAP} (GapReport), /{EPISODE} (EpisodeResult), /{CERTIFICATE} (latched), /{DATASET_TOPIC}
calls       /{EXPERT_SERVICE}, /{RESET_SERVICE}
serves      /{DATASET_SERVICE}
{parameter_help(PARAMETERS)}
"""


RETRY_PAUSE_S = 0.25  # first pause between expert attempts; doubles each time, capped at expert_timeout
# A sim or policy that was paused (SIGSTOP, a debugger, an overloaded host) may have lost what was sent to
# it meanwhile: a reset unanswered this long is sent again, and trajectories the policy still lacks after
# this long are published again, so an episode never waits its whole rollout_timeout for data already stored.
RESEND_S = 2.0


STOP_WAIT_S = 10.0  # on Ctrl-C, how long the node waits for Algorithm 1 to finish its current write


class ExpertUnavailable(RuntimeError):
    pass


class SupervisorNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_supervisor")
        self.settings = declare_settings(self, PARAMETERS, SupervisorSettings)
        self.loop: NPPLoop | None = None
        self.plant: PlantDescription | None = None
        self.run_seal = RunSeal.from_environment()
        self.plant_seal: RunSeal | None = None  # the run key's seal for the plant, once described
        self.run_id = ""  # the run's identity, from its run file
        self.seal: RunSeal | None = None  # the seal of this run (key, plant and identity), once its file is open
        self.stop = threading.Event()
        self._plants: Mailbox[PlantDescription] = Mailbox(keep=1)
        self.handshake = RolloutHandshake()
        self.gap_pub = self.create_publisher(GapReport, GAP, REPORT_QOS)
        self.episode_pub = self.create_publisher(EpisodeResult, EPISODE, REPORT_QOS)
        self.certificate_pub = self.create_publisher(CertificateMsg, CERTIFICATE, LATCHED_QOS)
        self.trajectory_pub = self.create_publisher(TrajectoryMsg, DATASET_TOPIC, REPORT_QOS)
        self.expert = self.create_client(ExpertTrajectory, EXPERT_SERVICE)
        self.reset = self.create_client(ResetEpisode, RESET_SERVICE)
        self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_QOS)
        self.create_subscription(EpisodeResult, ROLLOUT_DONE, self.on_rollout, REPORT_QOS)
        self.create_subscription(UInt32, POLICY_STATUS, self.handshake.on_policy_status, LATCHED_QOS)
        self.create_service(GetTrajectories, DATASET_SERVICE, self.serve_dataset, qos_profile=SERVICE_QOS)
        self.exit_code = 0
        self.worker = threading.Thread(target=self.run_algorithm, name="npp-algorithm-1", daemon=True)
        self.worker.start()
        self.get_logger().info("waiting for the sim's plant description")

    # ---------------------------------------------------------------- graph inputs
    def refuse_foreign(self, topic: str, exc: SealError) -> None:
        self.get_logger().error(
            f"refused: {exc} (publishers of /{topic}: {publishers_of(self, topic)}); nothing of it enters this run",
            throttle_duration_sec=5.0,
        )

    def on_plant(self, msg: PlantDescription) -> None:
        try:
            self.run_seal.check(msg, "a plant description")
        except SealError as exc:
            self.refuse_foreign(PLANT, exc)
            return
        if self.plant is not None:
            if msg.model_sha256 != self.plant.model_sha256:
                self.get_logger().error(
                    f"the sim now describes another plant ({msg.task} seed {msg.seed}; publishers of /{PLANT}: "
                    f"{publishers_of(self, PLANT)}); this run keeps its own, and refuses data for any other"
                )
            return
        self.plant_seal = self.run_seal.for_plant(msg.model_sha256)
        self.plant = msg
        self._plants.put(msg)

    def on_rollout(self, msg: EpisodeResult) -> None:
        """The sim's rollout results, this run's only; the context names the data the policy drove with."""
        if self.seal is None:
            return
        try:
            driven_with = self.seal.check_header(msg, f"the rollout result of episode {msg.episode}")
        except SealError as exc:
            self.refuse_foreign(ROLLOUT_DONE, exc)
            return
        self.handshake.on_rollout(msg, driven_with)

    def trajectory_msg(self, index: int, trajectory: Trajectory) -> TrajectoryMsg:
        assert self.seal is not None
        return self.seal.seal(trajectory_to_msg(index, trajectory, self.run_id))

    def serve_dataset(self, request: GetTrajectories.Request, response: GetTrajectories.Response):
        loop = self.loop
        if loop is None:
            response.success = False
            response.message = (
                "the run has not started yet (no plant description from the sim)"
                if self.plant is None
                else "the run is starting (opening its run file)"
            )
            return response
        data = loop.policy_data  # what the policy under test holds: never the trajectories a running test holds back
        total = data.num_trajectories
        count = min(request.max_count or 50, 200, max(total - request.start, 0))
        response.success = True
        response.run = self.run_id
        response.total = total
        response.lipschitz = loop.spec.lipschitz.value
        response.lipschitz_source = loop.spec.lipschitz.source
        response.trajectories = [
            self.trajectory_msg(k, data.trajectory(k)) for k in range(request.start, request.start + count)
        ]
        assert self.seal is not None
        return self.seal.seal(response, answering=request)

    # ---------------------------------------------------------------- Algorithm 1
    def run_algorithm(self) -> None:
        """Worker thread: waits for the sim's plant, then runs the episodes."""
        if self._plants.take() is None:
            return  # the node closed before the sim described its plant
        try:
            self._run_algorithm()
        except EpisodeInterrupted as exc:
            self.get_logger().info(f"stopped: {exc}")
        except Exception as exc:  # the run must never die silently: say why and exit non-zero
            if self.stop.is_set():  # the node is closing: what failed was cut off by it
                self.get_logger().info(f"stopped while {exc}")
                return
            self.get_logger().fatal(f"Algorithm 1 stopped: {exc}")
            self.exit_code = 1
            rclpy.try_shutdown()

    def _run_algorithm(self) -> None:
        assert self.plant is not None
        s, plant = self.settings, self.plant
        task, spec = plant.task, get_task(plant.task)
        # The task's expert, built here too: L's analytic bound, V(s0) where closed form, the value basis.
        expert = spec.make_expert(plant.seed, plant.horizon)
        if expert.plant.model_sha256() != plant.model_sha256:
            raise RuntimeError("the sim's plant differs from the task's model: refusing to certify")
        epsilon = spec.epsilon(s.epsilon or None)
        if isinstance(s.lipschitz, LipschitzConstant):
            lipschitz = s.lipschitz
        else:
            choice = spec.default_lipschitz_choice() if s.lipschitz == TASK_DEFAULT else s.lipschitz
            lipschitz = resolve_lipschitz(task, choice, expert)
        certify = None if s.certify == TASK_DEFAULT else s.certify
        config = build_config(
            task, plant.seed, lipschitz, epsilon,
            condition=s.condition, p=s.p, delta=s.delta, horizon=plant.horizon, certify=certify, rule=s.rule,  # type: ignore[arg-type]
        )  # fmt: skip
        run_dir = Path(s.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        store = RunStore.open_or_create(run_dir / "run.sqlite", config.metadata())  # RunFileError: refuse
        try:  # closed also on Ctrl-C, so that the file is one self-contained file again
            assert self.plant_seal is not None
            self.run_id = store.run_id
            self.seal = self.plant_seal.for_run(self.run_id)
            reporter = GraphReporter(self, config, run_dir)
            # Every answer is replayed on the supervisor's own plant before anything of it is stored.
            tail = expert.value_basis().tail
            check = AnswerCheck(spec.make_plant(plant.seed), plant.horizon, tail, spec.reward_range)
            self.loop = loop = NPPLoop(
                config,
                RosExpert(self, plant, s.expert_timeout, s.expert_retries, check),
                initial_state_fn(task, plant.seed),
                store=store,
                driver=RosRollouts(self, s.rollout_timeout) if s.rollouts else None,
                observers=[reporter],
                expert_value=spec.expert_value(expert),
                basis=value_basis(expert, lipschitz.value),
            )
            self.get_logger().info(
                f"{task} seed {plant.seed}: epsilon {epsilon:g}, {lipschitz.describe()}; "
                f"{'resuming at episode ' + str(loop.next_episode) if loop.rows else 'new run'} in {run_dir}"
            )
            self.publish_trajectories(0, loop.policy_data.num_trajectories)  # a restarted policy may listen here
            if loop.certificate is not None:
                reporter.on_certificate(loop.certificate)
            while not self.stop.is_set() and loop.certificate is None and loop.next_episode < s.max_episodes:
                loop.run_episode()
            if loop.certificate is None and not self.stop.is_set():
                self.get_logger().warning(f"not certified after {loop.next_episode} episodes")
        finally:
            store.close()

    def publish_trajectories(self, start: int, stop: int) -> None:
        assert self.loop is not None
        for k in range(start, stop):
            self.trajectory_pub.publish(self.trajectory_msg(k, self.loop.policy_data.trajectory(k)))

    def call(self, client: Client, request, timeout: float):
        """One service call with a deadline; an unanswered request is withdrawn, not left pending forever.

        A request or its answer is lost when either end was paused past the middleware's lease (a
        SIGSTOP, a debugger, a starved host): the server leaves the graph and comes back, or this
        process finds that far more time passed than it waited. Then the request is sent again
        (services here answer a repeated request the same way) instead of waiting out the deadline.
        """
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            done = threading.Event()
            future.add_done_callback(lambda _f, done=done: done.set())
            left = False
            while True:
                before = time.monotonic()
                if done.wait(min(RESEND_S, max(deadline - before, 0.0))):
                    return future.result()
                now = time.monotonic()
                if now >= deadline:
                    client.remove_pending_request(future)
                    future.cancel()
                    return None
                ready = client.service_is_ready()
                left = left or not ready
                if ready and (left or now - before > 3 * RESEND_S):
                    break
            client.remove_pending_request(future)
            future.cancel()
            self.get_logger().info(
                f"{client.srv_name}: the request may have been lost in a pause; sending it again",
                throttle_duration_sec=5.0,
            )

    def destroy_node(self) -> None:
        """Stop Algorithm 1 between two of its steps: an episode under way is left unrecorded (a resumed run
        plays it again), and the run file is closed before the process ends."""
        self.stop.set()
        self._plants.close()
        self.handshake.close()
        self.worker.join(timeout=STOP_WAIT_S)
        super().destroy_node()


class RosExpert:
    """The oracle over /npp/expert/trajectory: a deadline per call, retries, clear failure.

    An answer that fails the AnswerCheck (wrong dimensions, non-finite values, values that contradict
    its own trajectory on the supervisor's plant) counts as a failed attempt, with the reason; nothing
    of it is stored.
    """

    def __init__(
        self, node: SupervisorNode, plant: PlantDescription, timeout: float, retries: int, check: AnswerCheck
    ) -> None:
        self.node, self.plant, self.timeout, self.retries, self.check = node, plant, timeout, retries, check

    def trajectory(self, initial_state: FloatArray) -> Trajectory:
        log = self.node.get_logger()
        last = "no answer"
        for attempt in range(1, self.retries + 1):
            response, last = self._attempt(initial_state)
            if response is not None:
                try:
                    answer = trajectory_from_response(response)
                    self.check(answer, initial_state)
                    return answer
                except ValueError as exc:  # DatasetError, AnswerError: the answer is wrong, not the link
                    last = f"refused the expert's answer: {exc}"
            log.warning(f"expert call {attempt}/{self.retries} failed: {last}")
            if attempt < self.retries:
                self.node.stop.wait(min(self.timeout, RETRY_PAUSE_S * 2 ** (attempt - 1)))
        raise ExpertUnavailable(f"the expert did not deliver after {self.retries} attempts: {last}")

    def _attempt(self, initial_state: FloatArray) -> tuple[ExpertTrajectory.Response | None, str]:
        """One attempt: a trajectory within expert_timeout, or why not.

        "busy:" and "not ready:" refusals (an expert with a full queue, or just restarted and still
        waiting for the plant) are asked again within the attempt, after growing pauses, and so are
        answers that are not this run's expert's (another server on the domain won the race).
        """
        deadline = time.monotonic() + self.timeout
        pause = RETRY_PAUSE_S
        request = ExpertTrajectory.Request(state=float64_array(initial_state), horizon=0, run=self.node.run_id)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self.node.expert.wait_for_service(timeout_sec=remaining):
                return None, f"service /{EXPERT_SERVICE} not available after {self.timeout:g} s"
            response = self.node.call(self.node.expert, request, remaining)
            if response is None:
                return None, f"no answer within {self.timeout:g} s"
            refusal, retry = self._refusal(response, request)
            if refusal is None:
                return response, ""
            if not retry or deadline - time.monotonic() <= pause:
                return None, refusal
            self.node.get_logger().info(refusal + "; asking again", throttle_duration_sec=5.0)
            if self.node.stop.wait(pause):
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
        assert self.node.seal is not None
        try:
            self.node.seal.check(response, "the expert's answer", answering=request)
        except SealError as exc:
            servers = self.node.count_services(EXPERT_SERVICE)
            return f"refused: {exc} ({servers} servers of /{EXPERT_SERVICE} on the domain)", True
        if not response.success:
            return f"expert refused: {response.message}", False
        return None, False


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
    (the plant is deterministic and the policy under test frozen, so the return is the same). While it
    waits it says for what; when the node closes it raises EpisodeInterrupted and nothing is recorded.
    """

    def __init__(self, node: SupervisorNode, timeout: float) -> None:
        self.node, self.timeout = node, timeout

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float:
        node = self.node
        assert node.seal is not None
        held = policy.dataset.num_trajectories
        attempt = 0
        while True:
            self._policy_up_to_date(episode, held)
            request = node.seal.seal(
                ResetEpisode.Request(state=float64_array(initial_state), episode=episode, attempt=attempt,
                                     run=node.run_id)
            )  # fmt: skip
            outcome = self._result(episode, request)
            attempt += 1
            if outcome is None:
                node.get_logger().warning(
                    f"episode {episode}: no result after {self.timeout:g} s (rollout_timeout); running it again"
                )
                continue
            result, driven_with = outcome
            if driven_with == str(held):
                return float(result.policy_return)
            node.get_logger().error(
                f"episode {episode}: the return was earned by a policy over {driven_with or 'unknown'} trajectories, "
                f"not the {held} under test; running the episode again"
            )

    def _interrupted(self, episode: int) -> None:
        if self.node.stop.is_set():
            raise EpisodeInterrupted(f"the node is closing during episode {episode}; it is not recorded")

    def _result(self, episode: int, request: ResetEpisode.Request) -> tuple[EpisodeResult, str] | None:
        """The sim's result for this attempt, or None once it has run `timeout` seconds without one."""
        node, handshake = self.node, self.node.handshake
        started = time.monotonic()
        while time.monotonic() - started < self.timeout:
            self._interrupted(episode)
            problem = self._reset(request)
            if problem is not None:
                node.get_logger().warning(f"episode {episode} waits for the sim: {problem}", throttle_duration_sec=10.0)
                node.stop.wait(RESEND_S / 4)
                continue
            outcome = handshake.wait_for_rollout(episode, time.monotonic() + RESEND_S)
            if outcome is not None:
                return outcome
            node.get_logger().info(
                f"episode {episode} waits for the policy's rollout ({time.monotonic() - started:.0f} s); "
                "asking the sim where it stands",
                throttle_duration_sec=10.0,
            )
        self._interrupted(episode)
        return None

    def _policy_up_to_date(self, episode: int, held: int) -> None:
        """Wait until the policy holds `held` trajectories; what it still lacks is sent again every RESEND_S."""
        node, handshake = self.node, self.node.handshake
        while not handshake.wait_for_policy(held, time.monotonic() + RESEND_S):
            self._interrupted(episode)
            reported = handshake.policy_reported
            node.get_logger().info(
                f"episode {episode} waits for the policy: it holds {max(reported, 0)} of {held} trajectories; "
                "sending the missing ones again",
                throttle_duration_sec=10.0,
            )
            node.publish_trajectories(max(reported, 0), held)

    def _reset(self, request: ResetEpisode.Request) -> str | None:
        """Ask the sim to start (or, repeated, to report on) the episode: None once it has, else why not."""
        node = self.node
        assert node.seal is not None
        if not node.reset.wait_for_service(timeout_sec=RESEND_S):
            return f"the reset service /{RESET_SERVICE} is not available"
        response = node.call(node.reset, request, RESEND_S)
        if response is None:
            return "no answer to the reset"
        try:
            node.seal.check(response, "the sim's reset answer", answering=request)
        except SealError as exc:
            node.stop.wait(0.05)  # the other sim's answer may win every race; let ours arrive
            return f"refused: {exc} (servers of /{RESET_SERVICE}: a second sim on the domain?)"
        return None if response.success else f"the sim refused the reset: {response.message}"


class GraphReporter(Observer):
    """Publishes gap reports, episode results and the certificate; appends the CSV logs."""

    def __init__(self, node: SupervisorNode, config: RunConfig, run_dir: Path) -> None:
        self.node, self.config = node, config
        self.gap_log = run_dir / "gaps.csv"
        self.episode_log = run_dir / "episodes.csv"

    @staticmethod
    def _append(path: Path, header: list[str], row: list[object]) -> None:
        new = not path.exists()
        with path.open("a", newline="") as fh:
            writer = csv.writer(fh)
            if new:
                writer.writerow(header)
            writer.writerow(row)

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        node = self.node
        stamp = node.get_clock().now().to_msg()
        gap = gap_report(row, self.config, stamp)
        node.gap_pub.publish(node.run_seal.seal_header(gap))
        node.episode_pub.publish(node.run_seal.seal_header(episode_result(row, self.config.horizon, stamp)))
        self._append(
            self.gap_log,
            ["episode", "gap", "v_lb", "v_ub", "epsilon", "oracle_called", "dataset_size", "oracle_calls", "quiet"],
            [row.episode, row.gap, row.v_lb, row.v_ub, gap.epsilon, int(row.oracle_called), row.dataset_size,
             row.oracle_calls, row.quiet_episodes],
        )  # fmt: skip
        self._append(
            self.episode_log,
            ["episode", "initial_state", "policy_return", "expert_value", "v_lb", "oracle_called"],
            [row.episode, " ".join(f"{x:.17g}" for x in row.initial_state), row.policy_return, row.expert_value,
             row.v_lb, int(row.oracle_called)],
        )  # fmt: skip

    def on_trajectory(self, index: int, trajectory: Trajectory) -> None:
        self.node.trajectory_pub.publish(self.node.trajectory_msg(index, trajectory))

    def on_certificate(self, certificate: Certificate) -> None:
        node = self.node
        node.certificate_pub.publish(
            node.run_seal.seal_header(certificate_to_msg(certificate, node.get_clock().now().to_msg()))
        )
        self.node.get_logger().info("\n" + certificate.summary())


def main(argv: list[str] | None = None) -> int:
    return run_node(SupervisorNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
