"""npp-robot-run: Algorithm 1 with a robot as its plant, certifying the policy on that robot itself.

Every check is one of the robot's own episodes from its reset; after a failed check the expert plans from the start
the robot measures (on the identified robot's model, npp-identify's, or the task's nominal one) and the plan runs on
the robot by its feedback law: what the robot did joins the data (npp_ros.run.on_robot). The claim is the success
claim over this robot's starts, with no model in its assumptions, and npp-deploy takes such a run for this robot only.

Before anything moves, the worker reads the robot's description (/robot_description, MJCF) and refuses a robot whose
structure is not the task's model's; the description's fingerprint is the robot's identity in the run file, so a
resume on another robot is another run and is refused. The run is a run folder as every run is (run.sqlite,
episodes.csv, the certificate), stopped and resumed the same way: an episode a fault or a stop cuts is kept and
marked, never counted, and a check the robot finished before a stop is judged when the run resumes, not run anew.
"""

from __future__ import annotations

import sys
import threading
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from npp_interfaces.srv import ResetRobot
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String

from npp_ros.deployment.joints import JointLayout, parse_names
from npp_ros.deployment.robot_model import DescriptionError, mjcf_fingerprint
from npp_ros.deployment.robot_set import compiled, structure_reasons
from npp_ros.run.loop import EpisodeInterrupted, NPPLoop
from npp_ros.run.on_robot.episodes import DEFAULT_MAX_FAULTS
from npp_ros.run.on_robot.identity import STARTS, STARTS_HELP, RobotIdentity, identified_planning_model
from npp_ros.run.on_robot.link import RobotGone
from npp_ros.run.on_robot.setup import build_robot_loop
from npp_ros.run.progress import StatusLine
from npp_ros.run.records import RunFileError, UnrecordedSettings, write_episode_log
from npp_ros.run.request import FIELD_NAMES, RunRequest, resolve_run
from npp_ros.run.store import RUN_FILE
from npp_ros.tasks.registry import get_task
from npp_ros_graph.nodes.robot_run.link import RosRobotLink, StateInbox
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health
from npp_ros_graph.runtime.mailbox import Mailbox
from npp_ros_graph.runtime.node import request_stop, run_node
from npp_ros_graph.transport.parameters import Param, declare_settings, parameter_help, request_params
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES, LATCHED_QOS, SERVICE_QOS

STOP_WAIT_S = 10.0
RUN_PARAMETERS = request_params(FIELD_NAMES)
PARAMETERS = (
    *RUN_PARAMETERS,
    Param("run_dir", "runs/robot", "run folder: run.sqlite (the robot's episodes in it too), episodes.csv"),
    Param("joint_states_topic", JOINT_STATES, "the robot's joint states (sensor_msgs/JointState)"),
    Param("command_topic", FORWARD_COMMANDS, "the controller's command topic (std_msgs/Float64MultiArray)"),
    Param("robot_description_topic", "/robot_description", "the robot's model as MJCF text (latched)"),
    Param("reset_service", "/npp_robot/reset", "the robot's reset (npp_interfaces/srv/ResetRobot)"),
    Param("command_joints", "", "the controller's joints in command order, comma-separated; empty = the task's "
          "actuated joints"),
    Param("starts", "rho", STARTS_HELP, choices=STARTS),
    Param("identified_robot", "", "the model the expert plans on: an identification of this robot (npp-identify "
          "--out FILE); empty = the task's nominal model"),
    Param("start_from", "", "a run folder of the task (a run on its set of robots, say) whose certified policy's "
          "trajectories the run starts with: data, never checks; empty = none"),
    Param("state_timeout", 0.5, "seconds without a joint state before the episode is cut short (a fault)", 1e-3),
    Param("reset_timeout", 30.0, "seconds the robot's reset may take", 1e-3),
    Param("description_timeout", 30.0, "seconds to wait for the robot's description before refusing", 1e-3),
    Param("max_faults", DEFAULT_MAX_FAULTS, "faults in a row after which the robot is taken to be gone (the run "
          "stops, everything kept, and resumes where it stopped)", 1),
)  # fmt: skip


@dataclass(frozen=True)
class RobotRunSettings:
    """The run's request and how the node reaches its robot."""

    request: RunRequest
    run_dir: str
    joint_states_topic: str
    command_topic: str
    robot_description_topic: str
    reset_service: str
    command_joints: str
    starts: str
    identified_robot: str
    start_from: str
    state_timeout: float
    reset_timeout: float
    description_timeout: float
    max_faults: int

    def __post_init__(self) -> None:
        if not self.run_dir.strip():
            raise ValueError("run_dir must name a folder")
        if self.request.certify not in (None, "success"):
            raise ValueError(f"a run on a robot certifies the success claim only (certify success), not "
                             f"{self.request.certify}")  # fmt: skip

    @classmethod
    def parameter_names(cls) -> list[str]:
        return [f.name for f in fields(cls) if f.name != "request"] + [p.name for p in RUN_PARAMETERS]

    @classmethod
    def from_parameters(cls, **values: Any) -> RobotRunSettings:
        run = {p.name: values.pop(p.name) for p in RUN_PARAMETERS}
        run["certify"] = run.get("certify") or "success"
        return cls(RunRequest(**run), **values)


USAGE = f"""npp-robot-run: Algorithm 1 on a robot itself (ROS 2 node "npp_robot_run").

Certifies the success claim P_(s0 ~ the robot's resets)[success] >= p for the robot it runs on: each check is one of
the robot's own episodes, judged on the states it measured; after a failed check the expert plans from the robot's
measured start and its plan runs on the robot by its feedback law. No model of the robot is assumed.

subscribes  joint_states_topic (sensor_msgs/JointState), robot_description_topic (std_msgs/String, MJCF, latched)
publishes   command_topic (std_msgs/Float64MultiArray: one effort per command joint; zero between episodes)
calls       reset_service (npp_interfaces/srv/ResetRobot: bring the robot to a start and hold it there)
publishes   /diagnostics

Refused before the robot moves: no description within description_timeout, a robot whose structure is not the task's
model's, a claim other than success, a run folder of another robot or run. A fault (no joint state within
state_timeout, a failed reset) cuts the episode: it is stored and marked, never counted, and runs again.

{parameter_help(PARAMETERS)}
"""


class RobotRunNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_robot_run")
        self.settings = settings = declare_settings(self, PARAMETERS, RobotRunSettings)
        self.exit_code = 0
        self.stop = threading.Event()
        self.states = StateInbox()
        self._descriptions: Mailbox[str] = Mailbox(keep=1)
        self.loop: NPPLoop | None = None
        self.doing = "waiting for the robot's description"
        self.command_pub = self.create_publisher(Float64MultiArray, settings.command_topic, CONTROL_QOS)
        self.create_subscription(JointState, settings.joint_states_topic, self.states.put, CONTROL_QOS)
        self.create_subscription(String, settings.robot_description_topic, self.on_description, LATCHED_QOS)
        self.reset_client = self.create_client(ResetRobot, settings.reset_service, qos_profile=SERVICE_QOS)
        self.diagnostics = DiagnosticsReporter(self, self.health)
        self.worker = threading.Thread(target=self.run_on_robot, name="npp-robot-run", daemon=True)
        self.worker.start()

    def on_description(self, msg: String) -> None:
        self._descriptions.put(msg.data)

    def health(self) -> Health:
        loop = self.loop
        values: dict[str, object] = {"joint states received": self.states.received}
        if loop is not None:
            values |= {"episodes": loop.next_episode, "expert calls": loop.oracle_calls}
        return Health(self.doing, values)

    # ------------------------------------------------------------------ the worker
    def run_on_robot(self) -> None:
        log = self.get_logger()
        try:
            self._run()
        except EpisodeInterrupted as exc:
            log.info(f"stopped: {exc}; the run resumes from its folder")
        except (RobotGone, RunFileError, DescriptionError, ValueError) as exc:
            log.error(f"npp-robot-run: {exc}")
            self.exit_code = 1
        except Exception as exc:  # the run must never die silently: say why and exit non-zero
            if not self.stop.is_set():
                log.error(f"npp-robot-run stopped: {type(exc).__name__}: {exc}")
                self.exit_code = 1
        finally:
            if not self.stop.is_set():
                request_stop()

    def _identity(self, plant: Any) -> RobotIdentity:
        s = self.settings
        mjcf = self._descriptions.take(timeout=s.description_timeout)
        if mjcf is None:
            if self.stop.is_set():
                raise EpisodeInterrupted("the node stopped before the robot described itself")
            raise ValueError(f"no robot description on {s.robot_description_topic} within {s.description_timeout:g} s")
        reasons = structure_reasons(plant.physics.model, compiled(mjcf))
        if reasons:
            raise ValueError(f"the robot on {s.robot_description_topic} is not a {s.request.task} robot: "
                             + "; ".join(reasons))  # fmt: skip
        planning = identified_planning_model(Path(s.identified_robot), s.request.task) if s.identified_robot else ""
        return RobotIdentity(mjcf_fingerprint(plant, mjcf), planning, s.starts)  # type: ignore[arg-type]

    def _run(self) -> None:
        s, log = self.settings, self.get_logger()
        task = get_task(s.request.task)
        plant = task.make_plant(s.request.seed)
        identity = self._identity(plant)
        run_dir = Path(s.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        resolved = resolve_run(s.request, run_file=run_dir / RUN_FILE)
        link = RosRobotLink(
            plant, JointLayout.of_plant(plant, parse_names(s.command_joints)), self.command_pub.publish,
            self.reset_client, self.states, state_timeout=s.state_timeout, reset_timeout=s.reset_timeout,
            stop=self.stop, logger=log, name=s.joint_states_topic,
        )  # fmt: skip
        config = resolved.config
        status = StatusLine(config.spec.epsilon, config.spec.condition, every=0.0, max_episodes=s.request.max_episodes,
                            prefix="npp-robot-run: ", certify="success")  # fmt: skip
        with warnings.catch_warnings(record=True) as notices:
            warnings.simplefilter("always", UnrecordedSettings)
            self.loop = loop = build_robot_loop(
                resolved.config, resolved.expert, link, identity, store_path=run_dir / RUN_FILE, observers=[status],
                max_faults=s.max_faults, log=log.warning, prior_run=Path(s.start_from) if s.start_from else None,
            )  # fmt: skip
        for notice in notices:
            log.warning(str(notice.message))
        try:
            log.info(f"run on the robot ({identity.describe()}) in {run_dir}: "
                     f"{loop.next_episode} episodes so far, {loop.oracle_calls} expert calls")  # fmt: skip
            self.doing = "running episodes on the robot"
            result = loop.run(s.request.max_episodes)
            write_episode_log(run_dir / "episodes.csv", loop.rows)
            if result.certificate is not None:
                self.doing = "certified"
                log.info(f"[certificate] {result.certificate.statement}")
                for item in result.certificate.assumptions:
                    log.info(f"              assumes: {item}")
            else:
                self.doing = "not certified"
                log.warning(f"not certified after {result.episodes} episodes ({result.oracle_calls} expert calls)")
        finally:
            assert loop.store is not None
            loop.store.close()

    def destroy_node(self) -> None:
        """Stop between two control periods: the episode under way is kept, marked as stopped, and not counted."""
        self.stop.set()
        self._descriptions.close()
        self.worker.join(timeout=STOP_WAIT_S)
        super().destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(RobotRunNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
