"""npp-trial: a certified run deployed on the simulated robot in real time, episode by episode, against
the same policy in process.

Before a real robot, this is the rehearsal: npp-deploy (its own process) loads the run folder through
its gate exactly as it would for the robot (no override), and npp-robot (a new process per episode,
``start_on_command``) plays the task's MuJoCo plant in real time from a fresh s0, holding it there
until npp-deploy (activated once the robot holds s0, deactivated after the episode) sends its first
command, then stepping once per control period with the latest command held
(a command that misses its period leaves the previous one in force). For every episode it reports:

- the robot's return, recomputed by replaying the efforts the robot reported on the model (the
  replay must reproduce every joint state the robot published, bit for bit: the robot is the model);
- the in-process return of the certified policy from the same s0 (``rollout`` on the plant), the
  gap between the two, and the share of steps whose command was the policy's fresh answer to the
  state just before (the rest ran on a held command: real time, a busy machine);
- on the swing-up tasks, whether the pole ended upright (within 8 degrees over the last half of the
  horizon), on the robot and in process.

The s0 are draws from rho the run never made (episodes 10^6 + k of the run's own stream). A run certified on a
set of robots (``--uncertainty``) is tried on robots drawn from its set the same way (npp-robot's ``robot``
parameter; the in-process reference runs on the same robot), unless ``--robots nominal`` asks for its model; the
robot's return is its reported efforts replayed on that robot's model. Every run
of the tool gets its own ROS_DOMAIN_ID with localhost-only discovery. ``--out DIR`` writes
DIR/trial.json and DIR/trial.md with the command, the date and the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from npp_ros.bench.measure import POLE_ANGLE, UPRIGHT_DEGREES, worst_angle_degrees
from npp_ros.bench.report import write_report
from npp_ros.deployment.gate import Acceptance, Deployment, load_deployment
from npp_ros.deployment.joints import JointLayout, stored_state
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot, UncertaintySet, as_robot
from npp_ros_graph.bench.deploy import transition
from npp_ros_graph.bench.loop import reserved_domain, spawn, stop, wait_for
from npp_ros_graph.transport.topics import JOINT_STATES

MODEL = "the task's model"  # what the robot is when the run names no set or --robots nominal asks for it
FIRST_TRIAL_EPISODE = 10**6  # s0 of episodes no run draws: fresh for the policy
START_TIMEOUT_S = 120.0  # a robot process importing rclpy and MuJoCo on a busy machine
# Every joint state of an episode is kept: the trial replays them all.
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def log(text: str) -> None:
    sys.stderr.write(f"npp-trial: {text}\n")
    sys.stderr.flush()


@dataclass(frozen=True)
class TrialEpisode:
    """One episode on the robot and the same s0 in process."""

    episode: int
    robot_return: float
    in_process_return: float
    fresh_command_share: float  # steps whose command answered the state just before
    first_command_answers_s0: bool  # the robot waited at s0 for the policy's answer to it
    replay_mismatches: int  # published states the model's replay of the robot's efforts does not reproduce
    robot_upright: bool | None  # swing-up tasks: the pole within 8 degrees over the last half; else None
    in_process_upright: bool | None
    robot: str = ""  # the robot of a run certified on a set (Robot.record()); "" = the task's model

    @property
    def gap(self) -> float:
        return self.in_process_return - self.robot_return


class TrialNode(Node):
    """This process's side: npp-deploy's lifecycle client, and the robot's joint states of one episode."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__("npp_trial")
        self.change = self.create_client(ChangeState, "/npp_deploy/change_state")
        self.layout = layout
        self.s0 = np.zeros(0)
        self.raws: list[np.ndarray] = []  # [qpos, qvel] from s0 on
        self.efforts: list[np.ndarray] = []  # efforts[k]: the command applied in step k
        self.create_subscription(JointState, JOINT_STATES, self.on_state, KEEP_ALL)

    def expect(self, s0: np.ndarray) -> None:
        """A new episode from s0: what came before is dropped."""
        self.s0, self.raws, self.efforts = s0, [], []

    def on_state(self, msg: JointState) -> None:
        """The robot publishes s0 while it waits for its first command; the episode starts with the
        last of those, and each message after it is the state after a step and that step's effort."""
        if self.s0.size == 0:
            return
        raw = self.layout.state(msg.name, msg.position, msg.velocity)
        if not self.efforts and np.array_equal(raw, self.s0):
            self.raws = [raw]
            return
        if not self.raws:
            return  # a message of the last episode's robot
        where = [list(msg.name).index(name) for name in self.layout.command_joints]
        self.raws.append(raw)
        self.efforts.append(np.array([msg.effort[i] for i in where]))


def judge(deployment: Deployment, episode: int, s0: np.ndarray, raws: np.ndarray, efforts: np.ndarray,
          horizon: int, drawn: Robot | None = None) -> TrialEpisode:  # fmt: skip
    """The robot's episode against the model (the drawn robot's) and against the policy in process on it.

    The efforts are the commands the actuator applied (after the robot's delay), so they are replayed on the
    robot's model without a delay; the in-process reference meets the delay and the noise itself."""
    plant, policy = deployment.plant, deployment.policy
    layout = JointLayout.of_plant(plant)
    actions = np.array([layout.action(effort) for effort in efforts[:horizon]])
    model_only = None if drawn is None else Robot(drawn.scales)
    with as_robot(plant, model_only):
        replayed = _raw_states(plant, s0, actions)
    mismatches = int(np.sum(np.any(replayed[1:] != raws[1 : horizon + 1], axis=1)))
    robot = rollout(plant, _replayer(actions), s0, horizon, model_only)
    stored = np.array([stored_state(plant, raw) for raw in raws[:horizon]])
    fresh = float(
        np.mean([np.array_equal(policy.act(state), action) for state, action in zip(stored, actions, strict=True)])
    )
    reference = rollout(plant, policy.act, s0, horizon, drawn)
    first = bool(np.array_equal(actions[0], reference.actions[0]))
    angle = POLE_ANGLE.get(deployment.task.name)
    upright: tuple[bool | None, bool | None] = (None, None)
    if angle is not None:
        hold, acrobot = max(1, horizon // 2), deployment.task.name == "acrobot_swingup"
        upright = tuple(  # type: ignore[assignment]
            worst_angle_degrees(states, angle, hold, acrobot) <= UPRIGHT_DEGREES
            for states in (stored, reference.states)
        )
    record = "" if drawn is None else drawn.record()
    return TrialEpisode(
        episode, robot.total_return, reference.total_return, fresh, first, mismatches, *upright, robot=record
    )


def _replayer(actions: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    steps: Iterator[np.ndarray] = iter(actions)
    return lambda _state: next(steps)


def _raw_states(plant: Any, s0: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """[qpos, qvel] after each of ``actions`` from s0, as the robot publishes them (angles unwrapped)."""
    plant.reset(s0)
    data = plant.physics.data
    out = [np.concatenate([data.qpos, data.qvel])]
    for action in actions:
        plant.step(action)
        out.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(out)


def run_episode(executor: SingleThreadedExecutor, node: TrialNode, deployment: Deployment, episode: int,
                horizon: int, env: dict[str, str], logs: Path, robots: UncertaintySet | None = None,
                ) -> TrialEpisode:  # fmt: skip
    """One robot process from the episode's s0 (and, given ``robots``, as the episode's robot drawn from them),
    for ``horizon`` real-time steps under npp-deploy."""
    task, seed = deployment.task, deployment.metadata.seed
    s0 = task.initial_state(seed, episode)
    drawn = None if robots is None else robots.draw(seed, episode)
    node.expect(s0)
    params = {"task": task.name, "seed": str(seed), "initial_state": ",".join(repr(float(x)) for x in s0),
              "start_on_command": "true"}  # fmt: skip
    if drawn is not None:
        params["robot"] = f"'{drawn.record()}'"  # a YAML string: the record's JSON braces would read as a mapping
    ros_args = [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]
    robot = spawn(["npp_ros_graph.nodes.robot", "--ros-args", *ros_args], env, logs / f"robot-{episode}.log")
    limit = START_TIMEOUT_S + 4 * horizon * deployment.plant.dt  # real time: the episode's duration on top
    try:
        # npp-deploy is inactive while the robot starts: this node sees the robot hold s0 before any command
        if not wait_for(executor, lambda: len(node.raws) > 0, START_TIMEOUT_S):
            raise RuntimeError(f"no joint state at episode {episode}'s s0 within {START_TIMEOUT_S:.0f} s; see {logs}")
        transition(executor, node, "activate", 60.0)
        try:
            if not wait_for(executor, lambda: len(node.efforts) >= horizon, limit):
                raise RuntimeError(
                    f"the robot ran {len(node.efforts)} of {horizon} steps from episode {episode}'s s0 within "
                    f"{limit:.0f} s; see {logs}"
                )
        finally:
            transition(executor, node, "deactivate", 60.0)
    finally:
        stop(robot)
    raws, efforts = np.array(node.raws), np.array(node.efforts)
    node.expect(np.zeros(0))
    return judge(deployment, episode, s0, raws, efforts, horizon, drawn)


def summary(rows: list[TrialEpisode], epsilon: float) -> dict[str, Any]:
    robot = np.array([r.robot_return for r in rows])
    ref = np.array([r.in_process_return for r in rows])
    gaps = ref - robot
    out: dict[str, Any] = {
        "episodes": len(rows),
        "robot_return_median": float(np.median(robot)),
        "in_process_return_median": float(np.median(ref)),
        "gap_median": float(np.median(gaps)),
        "gap_p90": float(np.percentile(gaps, 90)),
        "gap_max": float(gaps.max()),
        "within_epsilon_of_in_process": float(np.mean(gaps <= epsilon)),
        "fresh_command_share_median": float(np.median([r.fresh_command_share for r in rows])),
        "fresh_command_share_min": float(min(r.fresh_command_share for r in rows)),
        "replay_mismatches": int(sum(r.replay_mismatches for r in rows)),
    }
    if rows and rows[0].robot_upright is not None:
        out["robot_upright"] = int(sum(bool(r.robot_upright) for r in rows))
        out["in_process_upright"] = int(sum(bool(r.in_process_upright) for r in rows))
    return out


def markdown(out: dict[str, Any]) -> str:
    s, c = out["summary"], out["certificate"]
    lines = [
        "# npp-trial: the certified policy on the real-time robot",
        "",
        f"Command: `{out['command']}` ({out['date']}; load average {out['load_average_start'][0]:.2f} at the start, "
        f"{out['load_average_end'][0]:.2f} at the end; {os.cpu_count()} cores).",
        "",
        f"Run: {out['run']} ({out['task']} seed {out['seed']}, H {out['horizon']}); certificate: epsilon "
        f"{c['epsilon']:g}, p {c['p']:g}, delta {c['delta']:g}, certify={c['certify']}, rule={c['rule']}, "
        f"{c['policy_trajectories']} trajectories in the policy, acting {out.get('policy', 'open-loop')}. npp-deploy "
        "loaded it through its gate "
        f"(no override); npp-robot ran each episode in real time ({out['control_period_ms']:g} ms period) "
        f"from a fresh s0, on {out.get('robots', MODEL)}.",
        "",
        "| episodes | return robot / in process (median) | gap in process - robot: median / p90 / max "
        "| within epsilon of in process | fresh commands (median, min) | replay mismatches "
        "| upright robot / in process |",
        "|---|---|---|---|---|---|---|",
        f"| {s['episodes']} | {s['robot_return_median']:.1f} / {s['in_process_return_median']:.1f} | "
        f"{s['gap_median']:.2f} / {s['gap_p90']:.2f} / {s['gap_max']:.2f} | {s['within_epsilon_of_in_process']:.0%} | "
        f"{s['fresh_command_share_median']:.1%}, {s['fresh_command_share_min']:.1%} | {s['replay_mismatches']} | "
        + (f"{s['robot_upright']} / {s['in_process_upright']} |" if "robot_upright" in s else "- |"),
        "",
        "- return robot: the efforts the robot reported, replayed on the model from s0 (replay mismatches: joint "
        "states the replay does not reproduce bit for bit; 0 means the robot moved exactly as the model does).",
        "- fresh commands: steps whose command was the policy's answer to the state just before; the others ran "
        "on a held command (the answer missed its control period).",
        "- upright: the pole within 8 degrees of upright over the last half of the horizon.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="npp-trial", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a certified run folder (its run.sqlite)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes on the robot, each from a fresh s0")
    parser.add_argument("--horizon", type=int, default=0, help="steps per episode (0: the run's H)")
    parser.add_argument("--logs", type=Path, default=None, help="folder for the nodes' logs (default: OUT/logs)")
    parser.add_argument("--out", type=Path, default=Path("runs/trial"), help="write OUT/trial.json and OUT/trial.md")
    parser.add_argument(
        "--robots",
        choices=("drawn", "nominal"),
        default="drawn",
        help="a run certified on a set of robots: each episode's robot drawn from the set (drawn, the default) or "
        "the task's model (nominal); a run on the exact model is always tried on it",
    )
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    from npp_ros.run.setup import plant_fingerprint
    from npp_ros.run.store import RunStore

    run_file = args.run_dir / "run.sqlite"
    if not run_file.exists():
        parser.error(f"{args.run_dir} holds no run.sqlite")
    with RunStore.open(run_file) as store:
        meta = store.metadata
    fingerprint = plant_fingerprint(meta.task, meta.seed)
    deployment = load_deployment(args.run_dir, Acceptance(model_fingerprint=fingerprint))
    certificate = deployment.certificate
    assert certificate is not None  # the gate passed without an override: the run's own certificate
    horizon = args.horizon or meta.horizon
    uncertainty = str(getattr(meta, "uncertainty", ""))
    robots = UncertaintySet.from_record(uncertainty) if uncertainty and args.robots == "drawn" else None
    logs = args.logs or args.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {
        "command": "npp-trial " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "load_average_start": list(os.getloadavg()),
        "run": str(args.run_dir), "task": meta.task, "seed": meta.seed, "horizon": horizon,
        "control_period_ms": deployment.plant.dt * 1e3,
        "certificate": {k: certificate.record()[k] for k in ("epsilon", "p", "delta", "certify", "rule",
                                                             "policy_trajectories")},
        "policy": deployment.policy.kind,
        "robots": robots.describe() if robots is not None else MODEL,
    }  # fmt: skip
    rows: list[TrialEpisode] = []
    started = time.monotonic()
    with reserved_domain() as env:
        params = {"run_dir": str(args.run_dir), "robot_model_fingerprint": fingerprint}
        ros_args = [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]
        deploy = spawn(["npp_ros_graph.nodes.deploy", "--ros-args", *ros_args], env, logs / "deploy.log")
        executor = SingleThreadedExecutor()
        node = TrialNode(JointLayout.of_plant(deployment.plant))
        executor.add_node(node)
        try:
            transition(executor, node, "configure", 900.0)  # the gate; each episode activates and deactivates
            for k in range(args.episodes):
                episode = FIRST_TRIAL_EPISODE + k
                rows.append(run_episode(executor, node, deployment, episode, horizon, env, logs, robots))
                r = rows[-1]
                log(f"episode {k + 1}/{args.episodes} ({time.monotonic() - started:.0f} s): return robot "
                    f"{r.robot_return:.1f}, in process {r.in_process_return:.1f}, fresh commands "
                    f"{r.fresh_command_share:.1%}")  # fmt: skip
        finally:
            stop(deploy)
            executor.remove_node(node)
            node.destroy_node()
            executor.shutdown()
    out["load_average_end"] = list(os.getloadavg())
    out["summary"] = summary(rows, certificate.spec.epsilon)
    out["episodes"] = [asdict(r) | {"gap": r.gap} for r in rows]
    figures, tables = write_report(args.out, "trial", out, markdown(out))
    log(f"wrote {figures} and {tables}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
