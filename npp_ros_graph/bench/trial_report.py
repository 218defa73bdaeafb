"""npp-trial's report on a certified run's episodes: the summary over them (returns, the gaps in process - robot
against epsilon, fresh commands, replay mismatches, upright and success counts) and trial.md; and report_head, the
head every trial.md opens with (the ``--outside`` report's too, bench/trial_outside.py).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from npp_ros_graph.bench.trial_judge import TrialEpisode

MODEL = "the task's model"  # what the robot is when the run names no set or --robots nominal asks for it


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
    if rows and rows[0].robot_success is not None:
        out["robot_success"] = int(sum(bool(r.robot_success) for r in rows))
        out["in_process_success"] = int(sum(bool(r.in_process_success) for r in rows))
    return out


def report_head(out: dict[str, Any], title: str, run_ends: str) -> list[str]:
    """A report's title, its command (date, load) and its run and certificate, the run's line ending ``run_ends``."""
    c = out["certificate"]
    return [
        f"# npp-trial: {title}",
        "",
        f"Command: `{out['command']}` ({out['date']}; load average {out['load_average_start'][0]:.2f} at the start, "
        f"{out['load_average_end'][0]:.2f} at the end; {os.cpu_count()} cores).",
        "",
        f"Run: {out['run']} ({out['task']} seed {out['seed']}, H {out['horizon']}); certificate: epsilon "
        f"{c['epsilon']:g}, p {c['p']:g}, delta {c['delta']:g}, certify={c['certify']}, rule={c['rule']}, "
        f"{c['policy_trajectories']} trajectories in the policy, acting {out.get('policy', 'open-loop')}{run_ends}",
        "",
    ]


def markdown(out: dict[str, Any]) -> str:
    s = out["summary"]
    lines = [
        *report_head(
            out,
            "the certified policy on the real-time robot",
            ". npp-deploy loaded it through its gate (no override); npp-robot ran each episode in real time "
            f"({out['control_period_ms']:g} ms period) from a fresh s0, on {out.get('robots', MODEL)}.",
        ),
        "| episodes | return robot / in process (median) | gap in process - robot: median / p90 / max "
        "| within epsilon of in process | fresh commands (median, min) | replay mismatches "
        "| upright robot / in process | success robot / in process |",
        "|---|---|---|---|---|---|---|---|",
        f"| {s['episodes']} | {s['robot_return_median']:.1f} / {s['in_process_return_median']:.1f} | "
        f"{s['gap_median']:.2f} / {s['gap_p90']:.2f} / {s['gap_max']:.2f} | {s['within_epsilon_of_in_process']:.0%} | "
        f"{s['fresh_command_share_median']:.1%}, {s['fresh_command_share_min']:.1%} | {s['replay_mismatches']} | "
        + (f"{s['robot_upright']} / {s['in_process_upright']} |" if "robot_upright" in s else "- |")
        + (f" {s['robot_success']} / {s['in_process_success']} |" if "robot_success" in s else " - |"),
        "",
        "- return robot: the efforts the robot reported, replayed on the model from s0 (replay mismatches: joint "
        "states the replay does not reproduce bit for bit; 0 means the robot moved exactly as the model does).",
        "- fresh commands: steps whose command was the policy's answer to the state just before; the others ran "
        "on a held command (the answer missed its control period).",
        "- upright: the pole within 8 degrees of upright over the last half of the horizon.",
        "- success: the task's own success criterion on the episode's states (a task that states one).",
    ]
    return "\n".join(lines) + "\n"
