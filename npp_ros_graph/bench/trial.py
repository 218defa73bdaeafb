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

A reach whose state holds a target (a task file's ``state.target``): each episode's target is s0's, published on
npp-deploy's target topic (geometry_msgs/PointStamped in frame ``world``, ten times a second from before its
activation to the episode's end), and the episode is judged on the task's success criterion too, on the robot and
in process.

The s0 are draws from rho the run never made (episodes 10^6 + k of the run's own stream). A run certified on a
set of robots (``--uncertainty``) is tried on robots drawn from its set the same way (npp-robot's ``robot``
parameter; the in-process reference runs on the same robot), unless ``--robots nominal`` asks for its model; the
robot's return is its reported efforts replayed on that robot's model. Every run
of the tool gets its own ROS_DOMAIN_ID with localhost-only discovery. ``--out DIR`` writes
DIR/trial.json and DIR/trial.md with the command, the date and the load average.

``--outside SPEC`` tries such a run on one robot *outside* its set instead (SPEC: ``gear=3``, every actuator's
gear x3; ``mass[pole]=1.5``, one element; ``delay=2``, control steps; comma-separated; or a robot record), from
episode 10^6's s0, in three phases, each with its own npp-robot and npp-deploy (robot_model_fingerprint empty:
the gate reads the robot's description):

1. gate: npp-robot publishes its true description; npp-deploy's configure must refuse it, and the refusal (the
   parameter, its value, the range) is read from npp-deploy's /diagnostics;
2. warn: npp-robot publishes the nominal description (a robot that changed without saying so, past the gate),
   on_model_mismatch warn: when /diagnostics went WARN for the model mismatch after activation (seconds and the
   robot's control steps), and the episode's outcome over the horizon;
3. stop: the same with on_model_mismatch stop: when the safe command came after activation, and that no other
   command came after it and the robot's efforts went to zero.

The command's parts: bench/trial_nodes.py, this process's node and the npp-robot it starts; bench/trial_judge.py,
an episode on the robot against the model and against the policy in process; bench/trial_report.py, the summary and
trial.md; bench/trial_outside.py, ``--outside``. This module holds the episode loop and the command.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.executors import SingleThreadedExecutor

from npp_ros.bench.report import write_report
from npp_ros.deployment.gate import Acceptance, Deployment, load_deployment
from npp_ros.deployment.joints import JointLayout
from npp_ros.tasks.uncertainty import PARAMETERS, Robot, UncertaintySet
from npp_ros_graph.bench.deploy import transition
from npp_ros_graph.bench.ros_loop import reserved_domain, spawn, stop, wait_for
from npp_ros_graph.bench.trial_judge import TrialEpisode, judge
from npp_ros_graph.bench.trial_nodes import (
    FIRST_TRIAL_EPISODE,
    START_TIMEOUT_S,
    TrialNode,
    log,
    ros_args,
    spawn_robot,
    wait_for_s0,
)
from npp_ros_graph.bench.trial_outside import WatchingNode, outside_markdown, outside_robot, try_outside
from npp_ros_graph.bench.trial_report import MODEL, markdown, summary


def run_episode(executor: SingleThreadedExecutor, node: TrialNode, deployment: Deployment, episode: int,
                horizon: int, env: dict[str, str], logs: Path, robots: UncertaintySet | None = None,
                ) -> TrialEpisode:  # fmt: skip
    """One robot process from the episode's s0 (and, given ``robots``, as the episode's robot drawn from them),
    for ``horizon`` real-time steps under npp-deploy."""
    task, seed = deployment.task, deployment.metadata.seed
    s0 = task.initial_state(seed, episode)
    drawn = None if robots is None else robots.draw(seed, episode)
    node.expect(s0)
    robot = spawn_robot(deployment, s0, drawn, {}, env, logs / f"robot-{episode}.log")
    limit = START_TIMEOUT_S + 4 * horizon * deployment.plant.dt  # real time: the episode's duration on top
    try:
        wait_for_s0(executor, node, episode, logs)
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


def trial_episodes(executor: SingleThreadedExecutor, node: TrialNode, deployment: Deployment,
                   args: argparse.Namespace, fingerprint: str, horizon: int, env: dict[str, str], logs: Path,
                   robots: UncertaintySet | None) -> list[TrialEpisode]:  # fmt: skip
    """npp-deploy through the gate once (the certified fingerprint), then ``args.episodes`` episodes on npp-robot."""
    params = {"run_dir": str(args.run_dir), "robot_model_fingerprint": fingerprint}
    deploy = spawn(["npp_ros_graph.nodes.deploy.node", "--ros-args", *ros_args(params)], env, logs / "deploy.log")
    rows: list[TrialEpisode] = []
    started = time.monotonic()
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
    return rows


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
    parser.add_argument(
        "--outside",
        metavar="SPEC",
        default="",
        help="a run certified on a set of robots: try it instead on one robot outside the set, in three phases "
        "(the gate refusing the robot's true description; past the gate on the nominal description with "
        "on_model_mismatch warn, then stop: when /diagnostics warned, when the safe command came). SPEC: "
        "PARAMETER=FACTOR scales every element of its kind (gear=3), PARAMETER[ELEMENT]=FACTOR one "
        "(mass[pole]=1.5), delay=STEPS delays each command; comma-separated; or a robot record (JSON). Parameters: "
        f"{', '.join(PARAMETERS)}. --episodes and --robots do not apply; --horizon is the warn phase's episode",
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
    outside: Robot | None = None
    if args.outside:
        certified = UncertaintySet.from_record(uncertainty)
        if certified.empty:
            parser.error(f"--outside tries a run certified on a set of robots; {args.run_dir} is on the exact model")
        try:
            outside = outside_robot(args.outside, deployment.plant)
        except ValueError as exc:
            parser.error(f"--outside {args.outside}: {exc}")
        reasons = certified.contains(outside)
        if not reasons:
            parser.error(f"--outside {args.outside} ({outside.describe()}) lies inside the certified set: "
                         f"{certified.describe()}")  # fmt: skip
        robots = certified
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
    if outside is not None:
        out["outside"] = {"spec": args.outside, "robot": outside.record(), "robot_words": outside.describe(),
                          "outside_reasons": reasons}  # fmt: skip
    rows: list[TrialEpisode] = []
    with reserved_domain() as env:
        executor = SingleThreadedExecutor()
        layout = JointLayout.of_plant(deployment.plant)
        node = TrialNode(layout) if outside is None else WatchingNode(layout)
        executor.add_node(node)
        try:
            if outside is not None:
                out["outside"] |= try_outside(executor, node, deployment, args.run_dir, outside, horizon, env, logs)
            else:
                rows = trial_episodes(executor, node, deployment, args, fingerprint, horizon, env, logs, robots)
        finally:
            executor.remove_node(node)
            node.destroy_node()
            executor.shutdown()
    out["load_average_end"] = list(os.getloadavg())
    if outside is not None:
        figures, tables = write_report(args.out, "trial", out, outside_markdown(out))
        log(f"wrote {figures} and {tables}")
        return 0
    out["summary"] = summary(rows, certificate.spec.epsilon)
    out["episodes"] = [asdict(r) | {"gap": r.gap} for r in rows]
    figures, tables = write_report(args.out, "trial", out, markdown(out))
    log(f"wrote {figures} and {tables}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
