"""npp-run: starts sim, expert, policy and supervisor as four processes and follows the run.

Shows live progress from the /npp/gap topic, prints the certificate, and stops all four
cleanly when the run is certified, when it runs out of episodes, on Ctrl-C, or when a node
dies (saying which, with its log). The run folder holds run.sqlite (dataset and episode log),
gaps.csv, episodes.csv and logs/<node>.log. Started again on the same folder, the supervisor
resumes the run.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from npp_interfaces.msg import Certificate, GapReport
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from npp_ros_graph.common import CERTIFICATE, GAP, LATCHED_QOS, REPORT_QOS
from npp_ros_graph.dashboard import start_dashboard
from npp_ros_graph.monitor import certificate_line, gap_line
from npp_ros_graph.record import start_recorder


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--task", default="lqr_2_1", help="lqr_2_1 or lqr_6_2")
    ap.add_argument("--seed", type=int, default=0, help="task seed")
    ap.add_argument("--horizon", type=int, default=1000, help="episode length")
    ap.add_argument("--epsilon", type=float, default=0.0, help="target gap > 0; 0: the paper's (50 / 300)")
    ap.add_argument("--lipschitz", default="analytic", help="'analytic', 'paper' (not a bound) or a number")
    ap.add_argument("--max-episodes", type=int, default=1000, help="episode budget")
    ap.add_argument("--run-dir", type=Path, default=None, help="run folder; default runs/graph-TASK-seedSEED")
    ap.add_argument("--no-rollouts", action="store_true", help="skip the policy's episodes (gap checks only)")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the four nodes (default: inherited)")
    ap.add_argument("--record", action="store_true", help="also record every /npp topic into RUN_DIR/bag (npp-record)")
    ap.add_argument(
        "--dashboard", type=int, nargs="?", const=8765, default=None, metavar="PORT",
        help="also serve the live dashboard on 127.0.0.1:PORT (npp-dashboard; default port 8765)",
    )  # fmt: skip
    return ap


class Follower(Node):
    def __init__(self) -> None:
        super().__init__("npp_run")
        self.last: GapReport | None = None
        self.certificate: Certificate | None = None
        self.create_subscription(GapReport, GAP, self.on_gap, REPORT_QOS)
        self.create_subscription(Certificate, CERTIFICATE, self.on_certificate, LATCHED_QOS)
        self.tty = sys.stderr.isatty()
        self._printed = 0.0

    def on_gap(self, msg: GapReport) -> None:
        self.last = msg
        now = time.monotonic()
        text = gap_line(msg)
        if self.tty:
            sys.stderr.write("\r" + text.ljust(110))
            sys.stderr.flush()
        elif now - self._printed > 2.0:
            print(text, file=sys.stderr, flush=True)
            self._printed = now

    def on_certificate(self, msg: Certificate) -> None:
        self.certificate = msg


def restore_default_sigint() -> None:
    """In each child: started from a background job, it would inherit an ignored SIGINT and never stop."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def stop_all(procs: dict[str, subprocess.Popen]) -> None:
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + 15
    for name, proc in procs.items():
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            print(f"npp-run: {name} did not stop on SIGINT; killing it", file=sys.stderr)
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    run_dir = (args.run_dir or Path("runs") / f"graph-{args.task}-seed{args.seed}").resolve()
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID") if k in env})
    params = {
        "sim": {"task": args.task, "seed": args.seed, "horizon": args.horizon},
        "expert": {},
        "policy": {},
        "supervisor": {
            "epsilon": float(args.epsilon), "lipschitz": str(args.lipschitz), "max_episodes": args.max_episodes,
            "run_dir": str(run_dir), "rollouts": not args.no_rollouts,
        },
    }  # fmt: skip
    procs: dict[str, subprocess.Popen] = {}
    extras: dict[str, subprocess.Popen] = {}  # started first and stopped last, so that they see the whole run
    if args.dashboard is not None:  # first: a port in use stops npp-run before anything else started
        extras["dashboard"] = procs["dashboard"] = start_dashboard(run_dir, env, args.dashboard)
    if args.record:
        extras["record"] = procs["record"] = start_recorder(run_dir, env)
    for name, values in params.items():
        cmd = [sys.executable, "-m", f"npp_ros_graph.{name}_node", "--ros-args"]
        for key, value in values.items():
            text = (
                str(value).lower() if isinstance(value, bool) else repr(value) if isinstance(value, str) else str(value)
            )
            cmd += ["-p", f"{key}:={text}"]
        log = (run_dir / "logs" / f"{name}.log").open("a")
        procs[name] = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=restore_default_sigint
        )
    print(f"npp-run: started sim, expert, policy, supervisor (logs in {run_dir / 'logs'})", file=sys.stderr)

    rclpy.init(args=["npp-run"])
    follower = Follower()
    executor = SingleThreadedExecutor()
    executor.add_node(follower)
    code = 0
    budget_reached_at: float | None = None
    try:
        while follower.certificate is None:
            executor.spin_once(timeout_sec=0.1)
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            if dead:
                for name, rc in dead.items():
                    print(
                        f"\nnpp-run: npp-{name} exited with code {rc}; see {run_dir / 'logs' / (name + '.log')}",
                        file=sys.stderr,
                    )
                code = 1
                break
            if follower.last is not None and follower.last.episode + 1 >= args.max_episodes:
                budget_reached_at = budget_reached_at or time.monotonic()
                if time.monotonic() - budget_reached_at > 5.0:
                    print(f"\nnpp-run: NOT CERTIFIED within {args.max_episodes} episodes", file=sys.stderr)
                    code = 1
                    break
    except (KeyboardInterrupt, ExternalShutdownException):
        print("\nnpp-run: interrupted; stopping the nodes (the run resumes from its folder)", file=sys.stderr)
        code = 130
    finally:
        if follower.certificate is not None:
            print(("\n" if follower.tty else "") + certificate_line(follower.certificate))
            print(f"run folder: {run_dir}")
        follower.destroy_node()
        rclpy.try_shutdown()
        stop_all({name: proc for name, proc in procs.items() if name not in extras})
        stop_all(extras)
    return code


if __name__ == "__main__":
    sys.exit(main())
