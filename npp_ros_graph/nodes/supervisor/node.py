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

import sys
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.msg import EpisodeResult, GapReport, PlantDescription
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import ExpertTrajectory, GetTrajectories, ResetEpisode
from rclpy.node import Node
from std_msgs.msg import UInt32

from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.run.loop import EpisodeInterrupted, NPPLoop, RunConfig
from npp_ros.run.progress import claim_header
from npp_ros.run.records import UnrecordedSettings
from npp_ros.run.request import FIELD_NAMES, PLANT_FIELDS, RunRequest, resolve_run
from npp_ros.run.setup import build_loop, initial_state_fn, robot_fn
from npp_ros.run.store import RUN_FILE, RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.nodes.supervisor.answer_check import AnswerCheck
from npp_ros_graph.nodes.supervisor.expert_client import RosExpert
from npp_ros_graph.nodes.supervisor.reporter import GraphReporter
from npp_ros_graph.nodes.supervisor.rollouts import RolloutHandshake, RosRollouts
from npp_ros_graph.runtime.diagnostics import WARN, DiagnosticsReporter, Health
from npp_ros_graph.runtime.mailbox import Mailbox
from npp_ros_graph.runtime.node import publishers_of, request_stop, run_node
from npp_ros_graph.runtime.reports import report_context
from npp_ros_graph.transport.convert import policy_spec_to_msg, trajectory_to_msg
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.parameters import Param, declare_settings, parameter_help, request_params
from npp_ros_graph.transport.topics import (
    CERTIFICATE,
    DATASET_SERVICE,
    DATASET_TOPIC,
    EPISODE,
    EXPERT_SERVICE,
    GAP,
    LATCHED_QOS,
    LATCHED_READER_QOS,
    PLANT,
    POLICY_STATUS,
    REPORT_HISTORY_QOS,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    SERVICE_QOS,
)

RUN_PARAMETERS = request_params([name for name in FIELD_NAMES if name not in PLANT_FIELDS])
"""The run's settings (the sim's plant names its task, seed and horizon), with the request's help texts."""

PARAMETERS = (
    *RUN_PARAMETERS,
    Param("run_dir", "runs/graph", "run folder: run.sqlite, gaps.csv, episodes.csv"),
    Param("expert_timeout", 30.0, "seconds one expert attempt may take (a busy or not-ready expert is asked again)",
          1e-3),
    Param("expert_retries", 3, "expert attempts per episode, 0.25 s (doubling) apart, before the run stops", 1),
    Param("expert_ahead", 2, "oracle mode: how many later episodes' expert answers are asked for while an episode "
          "runs (their s0 are known in advance; an expert with several workers computes them at once); 0 = none",
          0),
    Param("rollouts", True, "let the policy drive each episode through the sim (the sound checks need it)"),
    Param("rollout_timeout", 120.0, "seconds an episode may run without a result before it is run again from its s0 "
          "(a result lost in a pause is asked for again within seconds; no episode is skipped)", 1e-3),
)  # fmt: skip


@dataclass(frozen=True)
class SupervisorSettings:
    """The supervisor's parameters: the run's request and how the node runs it.

    The request checks its values when it is made (RunRequest, with the checks CertificationSpec uses), before the
    task is known; what the task decides (None: epsilon, certify, rule, L, the expert's options) is resolved when the
    sim names the task, seed and horizon. The request's fields read through (``settings.epsilon``).
    """

    request: RunRequest  # its task, seed and horizon are replaced by those the sim's plant names
    run_dir: str
    expert_timeout: float
    expert_retries: int
    expert_ahead: int
    rollouts: bool
    rollout_timeout: float

    def __post_init__(self) -> None:
        if not self.run_dir.strip():
            raise ValueError("run_dir must name a folder")

    def __getattr__(self, name: str) -> Any:
        if name in FIELD_NAMES:
            return getattr(self.request, name)
        raise AttributeError(name)

    @classmethod
    def parameter_names(cls) -> list[str]:
        return [f.name for f in fields(cls) if f.name != "request"] + [p.name for p in RUN_PARAMETERS]

    @classmethod
    def from_parameters(cls, **values: Any) -> SupervisorSettings:
        run = {p.name: values.pop(p.name) for p in RUN_PARAMETERS}
        return cls(RunRequest(**run), **values)


USAGE = f"""npp-supervisor: Algorithm 1 over the ROS graph (ROS 2 node "npp_supervisor").

subscribes  /{PLANT} (latched), /{ROLLOUT_DONE}, /{POLICY_STATUS}
publishes   /{GAP} (GapReport), /{EPISODE} (EpisodeResult), /{CERTIFICATE} (latched), /{DATASET_TOPIC}
calls       /{EXPERT_SERVICE}, /{RESET_SERVICE}
serves      /{DATASET_SERVICE}
{parameter_help(PARAMETERS)}
"""


STOP_WAIT_S = 10.0  # on Ctrl-C, how long the node waits for Algorithm 1 to finish its current write


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
        self.gap_pub = self.create_publisher(GapReport, GAP, REPORT_HISTORY_QOS)
        self.episode_pub = self.create_publisher(EpisodeResult, EPISODE, REPORT_HISTORY_QOS)
        self.certificate_pub = self.create_publisher(CertificateMsg, CERTIFICATE, LATCHED_QOS)
        self.trajectory_pub = self.create_publisher(TrajectoryMsg, DATASET_TOPIC, REPORT_QOS)
        self.expert = self.create_client(ExpertTrajectory, EXPERT_SERVICE)
        self.reset = self.create_client(ResetEpisode, RESET_SERVICE)
        self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_READER_QOS)
        self.create_subscription(EpisodeResult, ROLLOUT_DONE, self.on_rollout, REPORT_QOS)
        self.create_subscription(UInt32, POLICY_STATUS, self.handshake.on_policy_status, LATCHED_READER_QOS)
        self.create_service(GetTrajectories, DATASET_SERVICE, self.serve_dataset, qos_profile=SERVICE_QOS)
        self.exit_code = 0
        self.worker = threading.Thread(target=self.run_algorithm, name="npp-algorithm-1", daemon=True)
        self.worker.start()
        self.rollouts: RosRollouts | None = None
        self.diagnostics = DiagnosticsReporter(self, self.health)
        self.get_logger().info("waiting for the sim's plant description")

    def health(self) -> Health:
        """What /diagnostics says of the run: its episode, or what an episode has been waiting for."""
        loop, rollouts = self.loop, self.rollouts
        if loop is None:
            return Health("waiting for the sim's plant description")
        values = {"oracle calls": loop.oracle_calls, "episode": loop.next_episode}
        if rollouts is not None and rollouts.waiting:
            return Health(rollouts.waiting, values, WARN)
        return Health(f"episode {loop.next_episode}" + (", certified" if loop.certificate else ""), values)

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
        """A trajectory, sealed for this run, with the L the run's policy acts by now (it may choose its own)."""
        assert self.seal is not None
        spec = self.loop.policy_spec if self.loop is not None else None
        lipschitz = 0.0 if spec is None else spec.lipschitz.value
        return self.seal.seal(trajectory_to_msg(index, trajectory, self.run_id, lipschitz))

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
        spec = loop.policy_spec
        if spec is None:  # every task's plant states its control space; a plug-in's that does not cannot act here
            response.success = False
            response.message = f"{loop.config.task} states no control space: the policy node cannot act for it"
            return response
        response.policy = policy_spec_to_msg(spec)
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
            self.get_logger().error(f"Algorithm 1 stopped: {exc}")
            self.exit_code = 1
            request_stop()  # run_node tears the node down in order; the context goes last

    def _run_algorithm(self) -> None:
        assert self.plant is not None
        s, plant = self.settings, self.plant
        run_dir = Path(s.run_dir)
        request = replace(s.request, task=plant.task, seed=int(plant.seed), horizon=int(plant.horizon))
        # The task's expert, built here too with the expert node's options: L (analytic, or measured on its answers
        # for 'data'), V(s0) where closed form, the value basis.
        run = resolve_run(request, run_file=run_dir / RUN_FILE)
        task, spec, config, expert = plant.task, get_task(plant.task), run.config, run.expert
        if expert.plant.model_sha256() != plant.model_sha256:
            raise RuntimeError("the sim's plant differs from the task's model: refusing to certify")
        run_dir.mkdir(parents=True, exist_ok=True)
        store = RunStore.open_or_create(run_dir / RUN_FILE, config.metadata())  # RunFileError: refuse
        try:  # closed also on Ctrl-C, so that the file is one self-contained file again
            assert self.plant_seal is not None
            self.run_id = store.run_id
            self.seal = self.plant_seal.for_run(self.run_id)
            log = self.get_logger()
            reporter = GraphReporter(
                gaps=self.gap_pub, episodes=self.episode_pub, certificates=self.certificate_pub,
                send_trajectory=self.send_trajectory, seal=self.seal,
                context=report_context(plant.model_sha256, self.run_id), clock=self.get_clock(), logger=log,
                config=config, run_dir=run_dir, max_episodes=s.max_episodes,
            )  # fmt: skip
            # Every answer is replayed on the supervisor's own plant before anything of it is stored.
            tail = expert.value_basis().tail
            check = AnswerCheck(spec.make_plant(plant.seed), plant.horizon, tail, spec.reward_range)
            oracle = RosExpert(
                self.expert, plant, self.seal, self.run_id, stop=self.stop, logger=log,
                servers=lambda: self.count_services(EXPERT_SERVICE), timeout=s.expert_timeout, retries=s.expert_retries,
                check=check,
                ahead=self.upcoming_states(config, s.expert_ahead),
            )  # fmt: skip
            self.rollouts = rollouts = RosRollouts(
                self.reset, self.seal, self.run_id, self.handshake, self.publish_trajectories,
                stop=self.stop, logger=log, timeout=s.rollout_timeout,
            )  # fmt: skip
            with warnings.catch_warnings(record=True) as notices:
                warnings.simplefilter("always", UnrecordedSettings)
                self.loop = loop = build_loop(
                    config, expert, store=store, oracle=oracle, driver=rollouts if s.rollouts else None,
                    observers=[reporter],
                )  # fmt: skip
            for notice in notices:  # a resumed file that never recorded some settings: said at every resume
                log.warning(str(notice.message))
            self.get_logger().info(
                f"{task} seed {plant.seed}: {claim_header(config.spec, config.policy_lipschitz)}; "
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

    def send_trajectory(self, index: int, trajectory: Trajectory) -> None:
        """One trajectory to the policy (and whoever listens), sealed for this run."""
        self.trajectory_pub.publish(self.trajectory_msg(index, trajectory))

    def upcoming_states(self, config: RunConfig, count: int) -> Callable[[], list[tuple[FloatArray, Robot | None]]]:
        """The s0 (and, under model uncertainty, the robot) of the `count` episodes after the running one, where
        every episode asks the expert (oracle). An expert that plans on the nominal model is asked for no robot."""
        if config.spec.certify != "oracle" or count == 0:
            return list
        s0 = initial_state_fn(config.task, config.seed)
        robots = None if config.expert_model == "nominal" else robot_fn(config)

        def upcoming() -> list[tuple[FloatArray, Robot | None]]:
            loop = self.loop
            if loop is None:
                return []
            episodes = range(loop.next_episode + 1, loop.next_episode + 1 + count)
            return [(s0(k), None if robots is None else robots(k)) for k in episodes]

        return upcoming

    def publish_trajectories(self, start: int, stop: int) -> None:
        assert self.loop is not None
        for k in range(start, stop):
            self.trajectory_pub.publish(self.trajectory_msg(k, self.loop.policy_data.trajectory(k)))

    def destroy_node(self) -> None:
        """Stop Algorithm 1 between two of its steps: an episode under way is left unrecorded (a resumed run
        plays it again), and the run file is closed before the process ends."""
        self.stop.set()
        self._plants.close()
        self.handshake.close()
        self.worker.join(timeout=STOP_WAIT_S)
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    return run_node(SupervisorNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
