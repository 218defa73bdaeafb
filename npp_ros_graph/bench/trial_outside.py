"""npp-trial ``--outside``: a run certified on a set of robots, tried on one robot outside the set, in three
phases (gate, warn, stop: npp-trial's doc, bench/trial.py), each with its own npp-robot and npp-deploy.

outside_robot reads the robot SPEC names; WatchingNode is TrialNode keeping npp-deploy's /diagnostics and its
commands too; outside_phase runs one phase (configure: the gate's answer; watch_warn and watch_stop: what
npp-deploy did past the gate; monitor_found: when its model monitor said so in its log), try_outside all three; and
phase_words and outside_markdown put what they found in words, for the log and trial.md.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.deployment.gate import Deployment
from npp_ros.deployment.joints import JointLayout
from npp_ros.tasks.uncertainty import MAX_ACTION_DELAY, PARAMETERS, Robot, model_elements
from npp_ros_graph.bench.deploy import transition
from npp_ros_graph.bench.ros_loop import spawn, stop, wait_for
from npp_ros_graph.bench.trial_judge import judge
from npp_ros_graph.bench.trial_nodes import (
    FIRST_TRIAL_EPISODE,
    KEEP_ALL,
    START_TIMEOUT_S,
    TrialNode,
    log,
    ros_args,
    spawn_robot,
    wait_for_s0,
)
from npp_ros_graph.bench.trial_report import report_head
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, WARN, Health, health_of
from npp_ros_graph.transport.topics import FORWARD_COMMANDS

# --outside: npp-deploy's words for what each phase waits for (npp_ros/deployment/state.py, nodes/deploy/node.py)
DEPLOY_NODE = "/npp_deploy"
REFUSED = "configure refused: "
LEAVES = "leave the certified set of robots"  # WARN while active
LEFT = "left the certified set of robots"  # the reason named while inactive after on_model_mismatch stop
MONITOR_WAIT_S = 60.0  # after the horizon's steps, how long a phase keeps the robot under npp-deploy for the monitor
STEPS_AFTER_STOP = 25  # the robot's steps watched after the safe command
MONITOR_LINE = "the robot's transitions leave the certified set of robots"  # npp-deploy's log, warn or stop
LOGGED = re.compile(r"^\[\w+\] \[(?P<at>\d+\.\d+)\]")  # a ROS log line's severity and wall-clock time
SPEC_PART = re.compile(r"^(?P<name>[a-z]+)(?:\[(?P<element>[^\]]+)\])?=(?P<value>[^=]+)$")


class WatchingNode(TrialNode):
    """TrialNode that also keeps npp-deploy's /diagnostics statuses and its commands, each with its arrival
    (monotonic) and the robot's steps by then (--outside)."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__(layout)
        self.statuses: list[tuple[float, int, Health]] = []
        self.commands: list[tuple[float, int, list[float]]] = []
        self.state_times: list[float] = []  # wall-clock arrival of each joint state after s0 (efforts[k]'s)
        self.since = 0.0
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)
        self.create_subscription(Float64MultiArray, FORWARD_COMMANDS, self.on_command, KEEP_ALL)

    def expect(self, s0: np.ndarray) -> None:
        """As TrialNode's; joint states and statuses stamped before now are an earlier phase's nodes' (the phases
        share s0: an earlier robot's s0, delivered late, would start the episode before this robot is heard)."""
        super().expect(s0)
        self.statuses, self.commands, self.state_times = [], [], []
        self.since = time.time()

    def on_state(self, msg: JointState) -> None:
        if _seconds(msg.header.stamp) < self.since:
            return
        before = len(self.efforts)
        super().on_state(msg)
        if len(self.efforts) > before:
            self.state_times.append(time.time())

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        if _seconds(msg.header.stamp) < self.since:
            return
        self.statuses += [(time.monotonic(), len(self.efforts), health_of(s)) for s in msg.status
                          if s.name == DEPLOY_NODE]  # fmt: skip

    def on_command(self, msg: Float64MultiArray) -> None:
        self.commands.append((time.monotonic(), len(self.efforts), list(msg.data)))

    def first_status(self, holds: Callable[[Health], bool]) -> tuple[float, int, Health] | None:
        return next((item for item in self.statuses if holds(item[2])), None)

    def steps_by(self, wall: float) -> int:
        """The robot's steps whose joint state had arrived by wall-clock time ``wall``."""
        return int(np.searchsorted(np.array(self.state_times), wall, side="right"))


def _seconds(stamp: Any) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def outside_robot(spec: str, plant: Any) -> Robot:
    """The robot ``--outside`` names: a robot record (JSON), or comma-separated PARAMETER=FACTOR (every element of
    its kind), PARAMETER[ELEMENT]=FACTOR (one element) and delay=STEPS; a ValueError says what is wrong."""
    text = spec.strip()
    if text.startswith("{"):
        robot = Robot.from_record(text)
    else:
        elements = model_elements(plant.physics.model)
        factors: dict[tuple[str, str], float] = {}
        delay = 0
        for part in (part.strip() for part in text.split(",")):
            match = SPEC_PART.match(part)
            if match is None:
                raise ValueError(f"{part!r} is not PARAMETER=FACTOR, PARAMETER[ELEMENT]=FACTOR or delay=STEPS")
            name, element, value = match["name"], match["element"], match["value"].strip()
            if name == "delay":
                if element is not None or not value.isdigit() or int(value) > MAX_ACTION_DELAY:
                    raise ValueError(f"{part!r}: a delay is a whole number of control steps, 0 to {MAX_ACTION_DELAY}")
                delay = int(value)
                continue
            if name not in PARAMETERS:
                raise ValueError(f"{part!r}: no parameter {name!r} (known: {', '.join(PARAMETERS)}, delay)")
            kind = PARAMETERS[name][0]
            if element is not None and element not in elements[kind]:
                raise ValueError(f"{part!r}: the model has no {kind} {element!r} (its {kind}s: "
                                 f"{', '.join(elements[kind])})")  # fmt: skip
            try:
                factor = float(value)
            except ValueError:
                factor = math.nan
            if not (math.isfinite(factor) and factor > 0):
                raise ValueError(f"{part!r}: a factor is a positive number")
            for target in elements[kind] if element is None else (element,):
                factors[(name, target)] = factor
        robot = Robot(tuple((p, n, f) for (p, n), f in factors.items()), delay)
    if robot.state_noise:
        raise ValueError("a robot with noise on its states is not tried: the trial replays the states it published")
    return robot


def configure(executor: SingleThreadedExecutor, node: WatchingNode, log_path: Path) -> str:
    """npp-deploy's configure: "" when it passed, else its refusal as its /diagnostics status states it (its log's
    line when no status says so within 30 s)."""
    try:
        transition(executor, node, "configure", 900.0)
        return ""
    except RuntimeError as exc:
        if "refused" not in str(exc):
            raise  # no lifecycle service: nothing was asked

    def refused() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.doing.startswith(REFUSED))

    if wait_for(executor, lambda: refused() is not None, 30.0):
        return refused()[2].doing[len(REFUSED) :]  # type: ignore[index]
    lines = [line for line in log_path.read_text(errors="replace").splitlines() if REFUSED in line]
    return lines[-1].split(REFUSED, 1)[1] if lines else f"(no reason on /diagnostics or in {log_path})"


def monitor_found(node: WatchingNode, log_path: Path, activated_wall: float) -> dict[str, Any]:
    """When the model monitor first found the mismatch: its first log line saying so (the ROS log's wall-clock time),
    in seconds after activation and the robot's steps by then ({} when the log has no such line)."""
    for line in log_path.read_text(errors="replace").splitlines():
        found = LOGGED.match(line)
        if found is not None and MONITOR_LINE in line:
            at = float(found["at"])
            return {"found_after_s": at - activated_wall, "found_after_steps": node.steps_by(at)}
    return {}


def outside_phase(executor: SingleThreadedExecutor, node: WatchingNode, deployment: Deployment, run_dir: Path,
                  outside: Robot, phase: str, horizon: int, env: dict[str, str], logs: Path,
                  ) -> dict[str, Any]:  # fmt: skip
    """One --outside phase, "gate", "warn" or "stop" (npp-trial's doc, bench/trial.py), with its own npp-robot (as
    ``outside``) and npp-deploy, from episode 10^6's s0; what it found, as the report keeps it."""
    episode = FIRST_TRIAL_EPISODE
    s0 = deployment.task.initial_state(deployment.metadata.seed, episode)
    node.expect(s0)
    described = "robot" if phase == "gate" else "nominal"
    mismatch = "stop" if phase == "stop" else "warn"
    deploy_log = logs / f"deploy-{phase}.log"
    robot = spawn_robot(deployment, s0, outside, {"publish_description": described}, env, logs / f"robot-{phase}.log")
    # robot_model_fingerprint left empty: the gate reads the robot's description (waiting for it up to 60 s)
    params = {"run_dir": str(run_dir), "description_timeout": "60.0", "on_model_mismatch": mismatch}
    deploy = spawn(["npp_ros_graph.nodes.deploy.node", "--ros-args", *ros_args(params)], env, deploy_log)
    result: dict[str, Any] = {"publish_description": described, "on_model_mismatch": mismatch}
    limit = START_TIMEOUT_S + 4 * horizon * deployment.plant.dt
    activated_wall = math.nan
    try:
        wait_for_s0(executor, node, episode, logs)
        refusal = configure(executor, node, deploy_log)
        if phase == "gate":
            result |= {"refused": bool(refusal), "reason": refusal}
        elif refusal:
            raise RuntimeError(f"npp-deploy refused the nominal description ({phase} phase): {refusal}")
        else:
            transition(executor, node, "activate", 60.0)
            activated, activated_wall = time.monotonic(), time.time()
            if phase == "warn":
                result |= watch_warn(executor, node, horizon, limit, activated)
            else:
                result |= watch_stop(executor, node, outside, horizon, limit, activated)
    finally:
        stop(deploy)
        stop(robot)
    if phase != "gate":
        result |= monitor_found(node, deploy_log, activated_wall)  # its log is whole once it exited
    if phase == "warn":
        row = judge(deployment, episode, s0, np.array(node.raws), np.array(node.efforts), horizon, outside)
        result["episode"] = asdict(row) | {"gap": row.gap}
    node.expect(np.zeros(0))
    return result


def watch_warn(
    executor: SingleThreadedExecutor, node: WatchingNode, horizon: int, limit: float, activated: float
) -> dict[str, Any]:
    """on_model_mismatch warn: the horizon's steps, and npp-deploy kept active until /diagnostics says WARN for the
    mismatch (up to MONITOR_WAIT_S more); when it did."""

    def warned() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.level == WARN and LEAVES in h.doing)

    try:
        if not wait_for(executor, lambda: len(node.efforts) >= horizon, limit):
            raise RuntimeError(f"the robot ran {len(node.efforts)} of {horizon} steps within {limit:.0f} s")
        wait_for(executor, lambda: warned() is not None, MONITOR_WAIT_S)
    finally:
        transition(executor, node, "deactivate", 60.0)
    seen = warned()
    if seen is None:
        return {"warned": False, "steps_watched": len(node.efforts)}
    at, steps, health = seen
    return {
        "warned": True, "warn_after_s": at - activated, "warn_after_steps": steps, "status": health.doing,
        "error": health.error,  # the model monitor's figures
    }  # fmt: skip


def watch_stop(
    executor: SingleThreadedExecutor, node: WatchingNode, outside: Robot, horizon: int, limit: float, activated: float
) -> dict[str, Any]:
    """on_model_mismatch stop: until npp-deploy says it stopped for the mismatch (the horizon's steps and up to
    MONITOR_WAIT_S more); when the safe command came, what came after it, and the robot's efforts after it."""

    def stopped() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.values.get("lifecycle state") == "inactive" and LEFT in h.doing)

    if not wait_for(executor, lambda: stopped() is not None or len(node.efforts) >= horizon, limit):
        transition(executor, node, "deactivate", 60.0)
        raise RuntimeError(f"the robot ran {len(node.efforts)} of {horizon} steps within {limit:.0f} s")
    if not wait_for(executor, lambda: stopped() is not None, MONITOR_WAIT_S):
        transition(executor, node, "deactivate", 60.0)
        return {"stopped": False, "steps_watched": len(node.efforts)}
    # The safe command: the first of the zero commands that end the list (the status may come before it does).
    wait_for(executor, lambda: bool(node.commands) and not any(node.commands[-1][2]), 30.0)
    first_zero = len(node.commands)
    while first_zero > 0 and not any(node.commands[first_zero - 1][2]):
        first_zero -= 1
    if first_zero == len(node.commands):
        return {"stopped": True, "commands_zero": False, "last_command": node.commands[-1][2] if node.commands else []}
    at, steps, safe = node.commands[first_zero]
    wait_for(executor, lambda: len(node.efforts) >= steps + outside.action_delay + STEPS_AFTER_STOP, 60.0)
    # The robot's efforts are the commands it applied (after its delay): zero from some step on, once it held the safe
    # command; that step against the robot's steps when the safe command reached this node.
    efforts = np.array(node.efforts)
    nonzero = np.flatnonzero(np.any(efforts != 0, axis=1))
    zero_from = int(nonzero[-1]) + 1 if nonzero.size else 0
    health = stopped()[2]  # type: ignore[index]
    return {
        "stopped": True, "stop_after_s": at - activated, "stop_after_steps": steps, "safe_command": safe,
        "commands_zero": True, "commands_after_safe": len(node.commands) - first_zero - 1,
        "robot_zero_from_step": zero_from, "robot_steps_zero": len(efforts) - zero_from,
        "status": health.doing, "model_monitor": str(health.values.get("model monitor", "")),
    }  # fmt: skip


def try_outside(executor: SingleThreadedExecutor, node: WatchingNode, deployment: Deployment, run_dir: Path,
                outside: Robot, horizon: int, env: dict[str, str], logs: Path) -> dict[str, Any]:  # fmt: skip
    out: dict[str, Any] = {}
    for phase in ("gate", "warn", "stop"):
        out[phase] = outside_phase(executor, node, deployment, run_dir, outside, phase, horizon, env, logs)
        log(f"{phase}: {phase_words(phase, out[phase])}")
    return out


def phase_words(phase: str, r: dict[str, Any]) -> str:
    """A phase's finding in one sentence (the log and trial.md)."""
    if phase == "gate":
        if r["refused"]:
            return f"npp-deploy's configure refused the robot's true description: {r['reason']}"
        return "npp-deploy's configure accepted the robot's true description (a delay shows in no description)"
    if phase == "warn":
        if not r["warned"]:
            return f"no WARN for the model mismatch on /diagnostics in {r['steps_watched']} steps"
        found = (f" (the monitor found it {r['found_after_s']:.2f} s, {r['found_after_steps']} steps, after activation)"
                 if "found_after_s" in r else "")  # fmt: skip
        return (f"/diagnostics went WARN {r['warn_after_s']:.2f} s ({r['warn_after_steps']} control steps) after "
                f"activation{found}")  # fmt: skip
    if not r["stopped"]:
        return f"npp-deploy did not stop in {r['steps_watched']} steps"
    if not r["commands_zero"]:
        return f"npp-deploy stopped, but its last command was {r['last_command']}"
    found = (f" (the monitor found it {r['found_after_s']:.2f} s, {r['found_after_steps']} steps, after activation)"
             if "found_after_s" in r else "")  # fmt: skip
    return (
        f"npp-deploy deactivated and sent the safe command {r['safe_command']} {r['stop_after_s']:.2f} s "
        f"({r['stop_after_steps']} control steps) after activation{found}; {r['commands_after_safe']} commands after "
        f"it; the robot's efforts zero from its step {r['robot_zero_from_step']} on, over the {r['robot_steps_zero']} "
        "steps watched"
    )


def outside_markdown(out: dict[str, Any]) -> str:
    o = out["outside"]
    lines = [
        *report_head(out, "the certified policy on a robot outside its set", f"; certified on {out['robots']}."),
        f"The robot tried: {o['robot_words']}, outside the set ({'; '.join(o['outside_reasons'])}). Each phase ran "
        "its own npp-robot (this robot, in real time, "
        f"{out['control_period_ms']:g} ms period, from the s0 of episode {FIRST_TRIAL_EPISODE:,d}) and its own "
        "npp-deploy (through the gate, no override, robot_model_fingerprint empty: the gate reads the robot's "
        "description).",
        "",
        "| phase | npp-robot publishes | on_model_mismatch | what happened |",
        "|---|---|---|---|",
    ]
    said = {"robot": "its true description", "nominal": "the nominal description"}
    for phase in ("gate", "warn", "stop"):
        r = o[phase]
        mismatch = "-" if phase == "gate" else r["on_model_mismatch"]
        lines.append(f"| {phase} | {said[r['publish_description']]} | {mismatch} | {phase_words(phase, r)} |")
    warn, stopped = o["warn"], o["stop"]
    lines.append("")
    if "episode" in warn:
        e = warn["episode"]
        upright = (f"; upright robot / in process: {e['robot_upright']} / {e['in_process_upright']}"
                   if e["robot_upright"] is not None else "")  # fmt: skip
        lines.append(
            f"- The warn phase's episode ({out['horizon']} steps, npp-deploy commanding throughout): return robot "
            f"{e['robot_return']:.1f}, in process on the same robot {e['in_process_return']:.1f}, fresh commands "
            f"{e['fresh_command_share']:.1%}, replay mismatches {e['replay_mismatches']}{upright}."
        )
    if warn.get("warned"):
        lines.append(f"- The WARN status: `{warn['status']}`; its error: `{warn['error']}`.")
    if stopped.get("status"):
        lines.append(f"- The stop phase's status while inactive: `{stopped['status']}`.")
    lines += [
        "- Times are from npp-deploy's activate answer to the status (/diagnostics, published every second and at "
        "each transition) or the command reaching npp-trial; control steps are the robot's steps by then. The "
        "monitor's own finding is the time of npp-deploy's first log line saying so.",
        "- return robot: the efforts the robot reported, replayed on this robot's model from s0 (replay mismatches: "
        "joint states the replay does not reproduce bit for bit).",
    ]
    return "\n".join(lines) + "\n"
