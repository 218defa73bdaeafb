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
        queries = query_markdown(result["queries"]) if result.get("queries") else []
        return "\n".join([*lines, "", *experts, *throughput, *queries])
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
    if result.get("queries"):
        lines += query_markdown(result["queries"])
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


# ----------------------------------------------------------------------------- query cost at an arm's scale
QUERY_CASE = "Query cost"  # the first words of this part's target rows


def with_queries(result: dict[str, Any], section: dict[str, Any]) -> None:
    """Puts a query-cost measurement into a bench result, its target rows replacing any earlier ones.

    One row per size: V_lb's one-call p99 at the run's L against the task's control period, the time a control
    loop has for its whole step.
    """
    result["queries"] = section
    rows = [row for row in result.get("targets", []) if not row["case"].startswith(QUERY_CASE)]
    period_ms = 1e3 * section["control_period_s"]
    for size in section["sizes"]:
        entry = size["lipschitz"][0]
        p99_ms = entry["single"]["lower"]["p99_us"] / 1e3
        rows.append({"case": f"{QUERY_CASE} {section['task']}, {size['points']:,d} points, L {entry['value']:.4g}",
                     "metric": "V_lb one query, p99 (ms)", "value": p99_ms, "unit": " ms",
                     "target": f"<= {period_ms:g} ms (the control period)", "met": p99_ms <= period_ms})  # fmt: skip
    result["targets"] = rows


def query_markdown(section: dict[str, Any]) -> list[str]:
    """The query-cost part of bench.md: where the points came from, one-call percentiles, batches, builds."""
    src, lip, q = section["points"], section["lipschitz"], section["queries"]
    lines = [f"## Query cost at an arm's scale ({section['task']}, {section['state_dim']}-entry state, "
             f"{section['moving_entries']} of them moving)", ""]  # fmt: skip
    lines += [f"Command: `{section['command']}`, {section['date']}; load average at start "
              f"{section['load_average_start']}, at end {section['load_average_end']}.", ""]  # fmt: skip
    run = ""
    if section.get("run"):
        run = f"{src['run_points']:,d} points of run {section['run']} ({src['run_trajectories']} expert answers), then "
    lines += [
        f"Points: {run}{src['rollout_points']:,d} states of {src['rollouts']:,d} rollouts of {src['horizon']} steps "
        f"from s0 ~ rho under {src['controller']}; values: {src['values']}. Generated in {src['seconds']:.0f} s "
        f"({src['steps_per_s']:.0f} plant steps/s, one core). Each size is the first N points.",
        "",
        f"Queries: every {q['stride']}th state of fresh rollouts (another seed's stream), each entry moved by "
        f"{q['jitter']:g} x the data's spread: {q['single']} timed one call at a time, {q['repeats']} times each "
        f"({q['single'] * q['repeats']:,d} calls per method), {q['batch']} in one batch ({q['repeats']} repeats), "
        f"{q['checked']} checked against brute force (V_lb and V_ub: same value bit for bit, same index).",
        "",
        f"L: {lip['value']:.4g} ({lip['source']}: {lip['detail']}), and {section['large_lipschitz']:g}, where "
        "distance outweighs any value difference and V_lb is (nearly) the nearest point's value. "
        f"Exact at every size and L: **{section['exact']}**.",
        "",
        "### One query per call (microseconds; what a control loop waits for)",
        "",
        "| points | L | query | p50 | p90 | p99 | max | mean | CPU p50 | CPU p99 | p50 / pykdtree | p99 / pykdtree |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for size in section["sizes"]:
        n = f"{size['points']:,d}"
        for entry in size["lipschitz"]:
            for bound in ("lower", "upper", "both"):
                t, r = entry["single"][bound], entry["ratios"][bound]
                label = {"lower": "V_lb", "upper": "V_ub", "both": "V_lb + V_ub"}[bound]
                lines.append(f"| {n} | {entry['value']:.4g} | {label} | {_latency_cells(t)} | "
                             f"{r['single_p50']:.2f}x | {r['single_p99']:.2f}x |")  # fmt: skip
        for tree, tree_label in (("pykdtree", "pykdtree 1-NN"), ("ckdtree", "cKDTree 1-NN")):
            if tree in size["trees"]:
                lines.append(f"| {n} | - | {tree_label} | {_latency_cells(size['trees'][tree]['single'])} | - | - |")
    lines += [
        "",
        "p50 / p90 / p99 / max / mean: wall time of one call (`perf_counter_ns` around it; the mean is what a batch "
        "costs per query); CPU: this thread's CPU time of the same calls, which leaves out the time another process "
        "held the core: where wall p99 is far above CPU p99, the tail is the machine's load, not the search.",
        "",
        "### Batched (microseconds per query, median over repeats ± the half-range)",
        "",
        "| points | L | V_lb | V_ub | V_lb + V_ub | pykdtree 1-NN | cKDTree 1-NN | V_lb / pykdtree | both / pykdtree |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for size in section["sizes"]:
        trees = size["trees"]
        py = fmt_us(trees["pykdtree"]["batch"]) if "pykdtree" in trees else "-"
        for entry in size["lipschitz"]:
            b, r = entry["batch"], entry["ratios"]
            lines.append(
                f"| {size['points']:,d} | {entry['value']:.4g} | {fmt_us(b['lower'])} | {fmt_us(b['upper'])} | "
                f"{fmt_us(b['both'])} | {py} | {fmt_us(trees['ckdtree']['batch'])} | {r['lower']['batch']:.2f}x | "
                f"{r['both']['batch']:.2f}x |"
            )
    lines += [
        "",
        "### Build (seconds), what the index keeps, exactness",
        "",
        "| points | L | index build | pykdtree | cKDTree | kept for V_lb | kept for V_ub | V_lb picks the 1-NN point "
        "| exact (queries checked) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for size in section["sizes"]:
        trees, n = size["trees"], size["points"]
        py = f"{trees['pykdtree']['build_s']:.2f}" if "pykdtree" in trees else "-"
        for entry in size["lipschitz"]:
            e = entry["exact"]
            lines.append(
                f"| {n:,d} | {entry['value']:.4g} | {entry['build_s']:.2f} | {py} | {trees['ckdtree']['build_s']:.2f} "
                f"| {entry['kept_lower']:,d} ({100 * entry['kept_lower'] / n:.1f}%) | {entry['kept_upper']:,d} "
                f"({100 * entry['kept_upper'] / n:.1f}%) | {entry['same_point_as_1nn']}/{e['queries']} | "
                f"{e['exact']} ({e['queries']}) |"
            )
    lines += [
        "",
        "Index build: the policy's own index (compression on) over the N points at once, both bounds' trees. "
        "V_lb picks the 1-NN point: checked queries whose V_lb maximiser is the point pykdtree calls nearest.",
        "",
    ]
    return lines


def _latency_cells(t: dict[str, Any]) -> str:
    keys = ("p50_us", "p90_us", "p99_us", "max_us", "mean_us", "cpu_p50_us", "cpu_p99_us")
    return " | ".join(f"{t[key]:.1f}" for key in keys)
