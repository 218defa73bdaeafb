"""The bench report: bench.json sections merged and bench.md written from them.

Kept apart from the measurements so that other measuring commands (the ROS loop bench) can put
their section into the same files without loading what the index bench measures with.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def write_report(folder: Path, name: str, result: dict[str, Any], text: str) -> tuple[Path, Path]:
    """``folder/name.json`` (the figures, for scripts) and ``folder/name.md`` (the tables, for people).

    Every benchmark writes its result this way, so each results folder holds both forms side by side.
    """
    folder.mkdir(parents=True, exist_ok=True)
    figures, tables = folder / f"{name}.json", folder / f"{name}.md"
    figures.write_text(json.dumps(result, indent=2) + "\n")
    tables.write_text(text)
    return figures, tables


def expert_label(t: dict[str, Any]) -> str:
    """A timed expert's task, and its iLQR code path unless it is the default one (mujoco.batch)."""
    return f"{t['task']} ({t['path']})" if t.get("path", "batch") != "batch" else t["task"]


def with_experts(result: dict[str, Any], experts: dict[str, Any]) -> None:
    """Puts an expert measurement into a bench result, its target rows replacing any earlier ones."""
    result["experts"] = experts
    rows = [row for row in result.get("targets", []) if not row["case"].startswith("iLQR expert")]
    for t in experts["tasks"]:
        if t["target_s"] is not None:
            rows.append({"case": f"iLQR expert {expert_label(t)}, H = {t['horizon']}, {t['requests']} requests",
                         "metric": "slowest request (s per trajectory)", "value": t["seconds"]["max_s"],
                         "unit": " s", "target": f"<= {t['target_s']:g} s", "met": t["met"]})  # fmt: skip
    result["targets"] = rows


def expert_markdown(experts: dict[str, Any]) -> list[str]:
    lines = ["## iLQR experts (seconds per H-step trajectory, s0 ~ rho)", ""]
    lines += [f"Command: `{experts['command']}`, {experts['date']}; load average at start "
              f"{experts['load_average_start']}, at end {experts['load_average_end']}.", ""]  # fmt: skip
    lines += ["| task | H | requests | median s | quartiles | min - max | CPU s (median) | iterations | stop reasons "
              "| succeeded | target | met |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for t in experts["tasks"]:
        w, c = t["seconds"], t["cpu_seconds"]
        iterations = [r["iterations"] for r in t["detail"]]
        reasons = ", ".join(sorted({r["stop_reason"] for r in t["detail"]}))
        kept = sum(r["kept_warm_start"] for r in t["detail"])
        reasons += f"; warm start kept {kept}x" if kept else ""
        target = "-" if t["target_s"] is None else f"slowest <= {t['target_s']:g} s"
        met = "-" if t["met"] is None else ("yes" if t["met"] else "**no**")
        lines.append(
            f"| {expert_label(t)} | {t['horizon']} | {t['requests']} | {w['median_s']:.2f} | {w['q25_s']:.2f} - "
            f"{w['q75_s']:.2f} | {w['min_s']:.2f} - {w['max_s']:.2f} | {c['median_s']:.2f} | "
            f"{int(np.median(iterations))} ({min(iterations)} - {max(iterations)}) | {reasons} | "
            f"{t['succeeded']}/{t['requests']} | {target} | {met} |"
        )
    lines += ["", "Where the time goes (sum over the requests, share of their wall time):", ""]
    lines += ["| task | derivatives | backward pass | line search | first rollout | rest of iLQR "
              "| warm start and replays | derivatives by |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for t in experts["tasks"]:
        cells = " | ".join(f"{t['phases_s'][k]:.2f}s ({100 * t['phase_shares'][k]:.0f}%)" for k in
                           ("derivatives", "backward", "line_search", "rollout", "optimizer_other",
                            "warm_start_and_replays"))  # fmt: skip
        lines.append(f"| {expert_label(t)} | {cells} | {t['derivatives_by']} |")
    lines += [""]
    for t in experts["tasks"]:
        o = t["options"]
        stop = o.get("stop", "time")  # files from before the stop was recorded: the budget stopped iLQR
        budget = "a guard of" if stop == "iterations" else "a budget of"
        planner = f"; {o['planner']}" if o.get("planner") else ""  # a task file's planner keys
        lines.append(f"- {expert_label(t)}: default expert (stop = {stop}: at most {o['max_iterations']} iterations, "
                     f"{budget} {o['time_budget_s']:g} s per request; {o['values']} values{planner}); succeeded = "
                     f"{t['success_rule']}.")  # fmt: skip
    lines += [
        "",
        "A request is what the expert node answers: the warm-start controller's rollout, iLQR, and the replays of "
        "the actions on the plant for the true rewards (warm start and replays). Line search = the closed-loop "
        "rollouts of the candidate steps.",
        "",
    ]
    return lines


# ----------------------------------------------------------------------------- report
def fmt_us(t: dict[str, Any]) -> str:
    return f"{t['median_us']:.1f} ±{100 * t['spread']:.0f}%"


def markdown(result: dict[str, Any]) -> str:
    m = result["machine"]
    lines = [
        "# npp-bench",
        "",
        f"Command: `{result['command']}`  ",
        f"Date: {result['date']}  ",
        f"Machine: {m['cpu']}, {m['cores']} cores ({m['usable_cores']} usable), {m['system']}; Python {m['python']}, "
        f"numpy {m['numpy']}, numba {m['numba']}, scipy {m['scipy']}, pykdtree {m['pykdtree']}; {m['threads']}.  ",
        f"Load average at start: {m['load_average_start']}, at end: {result.get('load_average_end')}.  ",
    ]
    if "all_exact" in result:  # a folder first written by `--only experts` has no index figures
        lines += [
            f"All exact: **{result['all_exact']}** (same index and same value as brute force on every checked query).",
            "",
            "Times are microseconds per query: median over repeats, ± the half-range (max - min) / 2 as a "
            "fraction of the median.",
        ]
    lines += [
        "",
        "## Targets",
        "",
        "| case | metric | value | target | met |",
        "|---|---|---|---|---|",
    ]
    for row in result["targets"]:
        unit = row.get("unit", "x")  # the index and ROS rows are ratios
        lines.append(f"| {row['case']} | {row['metric']} | {row['value']:.2f}{unit} | {row['target']} | "
                     f"{'yes' if row['met'] else '**no**'} |")  # fmt: skip
    if "cases" not in result:  # only `--only experts` or `--only throughput` has written to this folder
        experts = expert_markdown(result["experts"]) if result.get("experts") else []
        throughput = throughput_markdown(result["expert_throughput"]) if result.get("expert_throughput") else []
        return "\n".join([*lines, "", *experts, *throughput])
    lines += ["", "## Index vs 1-NN trees (same points, same queries)", ""]
    lines += [
        "| case | points | L | mode | V_lb | V_ub | pykdtree 1-NN | cKDTree 1-NN | V_lb / 1-NN | both / 1-NN |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in result["cases"]:
        t = case["timings"]
        for mode in ("batch", "single"):
            py = fmt_us(t[f"pykdtree_{mode}"]) if f"pykdtree_{mode}" in t else "-"
            lines.append(
                f"| {case['name']} | {case['points']:,d} | {case['lipschitz']:.4g} ({case['lipschitz_source']}) | "
                f"{mode} | "
                f"{fmt_us(t[f'index_lower_{mode}'])} | {fmt_us(t[f'index_upper_{mode}'])} | {py} | "
                f"{fmt_us(t[f'ckdtree_{mode}'])} | {case['ratios'][f'lower_vs_1nn_{mode}']:.2f}x | "
                f"{case['ratios'][f'both_vs_1nn_{mode}']:.2f}x |"
            )
    lines += ["", "Build times (s) and what the compressed trees keep:", ""]
    lines += ["| case | index build | pykdtree | cKDTree | kept for V_lb | kept for V_ub | exact (queries checked) |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for case in result["cases"]:
        b, c, e = case["build_s"], case["compression"], case["exact"]
        lines.append(
            f"| {case['name']} | {b['index']:.2f} | {b.get('pykdtree', float('nan')):.2f} | {b['ckdtree']:.2f} | "
            f"{c['kept_lower']:,d} ({100 * c['kept_lower_fraction']:.1f}%) | "
            f"{c['kept_upper']:,d} ({100 * c['kept_upper_fraction']:.1f}%) | {e['exact']} ({e['queries']}) |"
        )
    lines += ["", "## Brute force vs index (V_lb, batch)", ""]
    lines += [
        "| case | points | brute force | index | speed-up | exact (queries checked) |",
        "|---|---|---|---|---|---|",
    ]
    for row in result["scaling"]:
        lines.append(f"| {row['case']} | {row['points']:,d} | {fmt_us(row['brute'])} | {fmt_us(row['index'])} | "
                     f"{row['speedup']:.0f}x | {row['exact']['exact']} ({row['exact']['queries']}) |")  # fmt: skip
    ties = result["ties"]
    lines += ["", f"Tie case (integer grid, L = 1): {ties['queries']} queries, {ties['tied_queries_lower']} with tied "
              f"maximisers; exact: {ties['exact']}.", ""]  # fmt: skip
    cc = result.get("compile")
    if cc:
        lines += [
            "## First call (numba compile or cache load)",
            "",
            f"Cold cache: import {cc['cold_import_s']:.2f}s, first build + queries {cc['cold_first_query_s']:.2f}s. "
            f"Warm cache: import {cc['warm_import_s']:.2f}s, first build + queries {cc['warm_first_query_s']:.2f}s.",
            "",
        ]
    if result.get("compression_runs"):
        lines += ["## Compression of stored runs (every point checked against the whole dataset)", ""]
        lines += [
            "| run | task | L | points | kept for V_lb | kept for V_ub | kept for either |",
            "|---|---|---|---|---|---|---|",
        ]
        for row in result["compression_runs"]:
            lines.append(
                f"| {row['run']} | {row['task']} | {row['lipschitz']:.4g} ({row['lipschitz_source']}) | "
                f"{row['points']:,d} | {row['kept_lower']:,d} ({100 * row['kept_lower_fraction']:.1f}%) | "
                f"{row['kept_upper']:,d} ({100 * row['kept_upper_fraction']:.1f}%) | "
                f"{row['kept_either']:,d} ({100 * row['kept_either_fraction']:.1f}%) |"
            )
        lines.append("")
    ros = result.get("ros")
    if ros:
        lines += ["## ROS loop (sim <-> policy lockstep vs a bare ROS ping-pong of the same message types)", ""]
        if ros.get("command"):  # measured on its own, after the figures above
            lines += [f"Command: `{ros['command']}`, {ros['date']}; load average at start "
                      f"{ros['load_average_start']}, at end {ros['load_average_end']}.", ""]  # fmt: skip
        if ros.get("error"):
            lines += [f"Failed: {ros['error']}", ""]
        lines += ["| task | points | graph steps/s | ping-pong steps/s | ratio | target | met |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for c in ros.get("cases", []):
            graph = ", ".join(f"{r:.0f}" for r in c["graph_steps_per_s"])
            pingpong = ", ".join(f"{r:.0f}" for r in c["pingpong_steps_per_s"])
            lines.append(
                f"| {c['task']} | {c['points']:,d} | {c['graph_median']:.0f} ({graph}) | "
                f"{c['pingpong_median']:.0f} ({pingpong}) | "
                f"{c['ratio']:.2f} | >= {c['target']:.2f} | {'yes' if c['met'] else '**no**'} |"
            )
        lines += [
            "",
            "Graph: this process plays the sim in lockstep with the policy node (npp_ros_graph/nodes/policy.py), "
            "stepping the plant's exact linear model with each answer, both sides sealing and checking every "
            "state and action as a run does (the policy node on the ROS 2 EventsExecutor). Ping-pong: the same "
            "driver against a plain ROS 2 node (SingleThreadedExecutor) that answers at once, in its own process, "
            "same message types and QoS, no seals.",
            "",
        ]
    if result.get("experts"):
        lines += expert_markdown(result["experts"])
    if result.get("expert_throughput"):
        lines += throughput_markdown(result["expert_throughput"])
    return "\n".join(lines) + "\n"


def with_ros(result: dict[str, Any], ros: dict[str, Any]) -> None:
    """Puts a ROS loop measurement into a bench result, its target rows replacing any earlier ones."""
    result["ros"] = ros
    rows = [row for row in result.get("targets", []) if not row["case"].startswith("ROS loop")]
    for c in ros.get("cases", []):
        rows.append({"case": f"ROS loop {c['task']}, {c['points']:,d} points",
                     "metric": "graph / bare ping-pong steps/s", "value": c["ratio"],
                     "target": f">= {c['target']:g}x", "met": c["met"]})  # fmt: skip
    result["targets"] = rows


def throughput_markdown(section: dict[str, Any]) -> list[str]:
    lines = ["## Expert throughput (requests per second through the expert pool, same s0 at every worker count)", ""]
    lines += [f"Command: `{section['command']}`, {section['date']}; {section['usable_cores']} usable cores; "
              f"load average at start {section['load_average_start']}, at end {section['load_average_end']}.",
              ""]  # fmt: skip
    lines += ["| task | H | requests | workers x threads | wall s | requests/s | speed-up | cores used | answered "
              "| stop reasons |", "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for t in section["tasks"]:
        for run in t["runs"]:
            reasons = ", ".join(f"{reason} {n}" for reason, n in run["stop_reasons"].items())
            lines.append(
                f"| {t['task']} | {t['horizon']} | {t['requests']} | {run['workers']} x {run['threads_per_worker']} | "
                f"{run['seconds']:.1f} | "
                f"{run['requests_per_s']:.3f} | {run['speedup']:.2f}x | {run['cores_used']:.2f} | "
                f"{run['answered']}/{t['requests']} | {reasons} |"
            )
    lines.append("")
    for t in section["tasks"]:
        if not t["compared_requests"]:
            lines.append(f"- {t['task']}: no answers compared: the time budget cut every s0 at some worker count.")
            continue
        same = "the same bit for bit" if t["answers_equal"] else "**not** the same"
        lines.append(f"- {t['task']}: answers at every worker count {same} on the {t['compared_requests']} of "
                     f"{t['requests']} s0 that no time budget cut at any count.")  # fmt: skip
    lines += [
        "",
        "Wall time from the first request to the last answer, all requests asked at once; each pool's start and "
        "one short warm-up request per worker excluded. Cores used: the requests' CPU seconds in the workers over "
        "that wall time (below the worker count where other jobs share the cores). Threads: each worker's iLQR "
        "derivative threads (by default the cores over the workers). 'time budget' names an answer "
        "the optimizer's wall-clock budget cut, which depends on the machine's speed and load.",
        "",
    ]
    return lines
