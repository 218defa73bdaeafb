"""Measure the pendulum iLQR expert: seconds per request, where they go, and the slope of its value.

Usage: .venv/bin/python scripts/pendulum_expert_report.py [--requests 12] [--grid 64] [--bisect 12]
(``--grid 0`` skips part 3.)

1. ``--requests`` 1000-step requests from s0 ~ rho (seeded), timed one at a time with
   :func:`npp_ros.trajopt.expert.time_trajectories` at the expert's default budget.
2. Slopes: max |W_x| of the surrogate cost-to-go (the backward pass), and the data-based slope
   |Q_i - Q_j| / |s_i - s_j| of the true values over those trajectories (an under-estimate), with
   both value conventions (return-to-go, and H-step windows).
3. The expert's return Q_0(s0) on a grid of s0 angles; the largest jump between neighbours is
   bisected: a jump that keeps its size as the two s0 close in is a discontinuity of the
   expert's value, so no finite L bounds its slope there.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from npp_ros.policy.dataset import Dataset
from npp_ros.policy.lipschitz import estimate_global
from npp_ros.tasks.builtin.pendulum import PAPER_LIPSCHITZ, PendulumExpert, sample_initial_state
from npp_ros.trajopt.expert import ExpertSolution, replay_rewards, time_trajectories, window_values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=12)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--bisect", type=int, default=12)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args()

    expert = PendulumExpert(seed=0, values="return-to-go")  # Q_0 is the same in both modes; no continuation to time
    rng = np.random.default_rng(args.seed)
    starts = [sample_initial_state(rng) for _ in range(args.requests)]
    solutions: list[ExpertSolution] = []
    cpu: list[float] = []

    def solve(s0: np.ndarray) -> None:
        tick = time.process_time()
        solutions.append(expert.solve(s0))
        cpu.append(time.process_time() - tick)

    seconds = time_trajectories(solve, starts)
    print(f"time budget {expert.time_budget} s, max_iterations {expert.max_iterations}, H = {expert.horizon}")
    print("seconds per request:", " ".join(f"{s:.2f}" for s in seconds))
    q25, q50, q75 = np.percentile(seconds, [25, 50, 75])
    print(f"median {q50:.2f} s, IQR {q25:.2f}-{q75:.2f} s, min {seconds.min():.2f} s, max {seconds.max():.2f} s")
    print(f"CPU seconds per request (this process only): median {np.median(cpu):.2f}, max {max(cpu):.2f}")
    print(f"load average at the end: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    phases = {k: sum(s.optimization.timings[k] for s in solutions) for k in solutions[0].optimization.timings}
    total = sum(seconds)
    share = ", ".join(f"{k} {v:.2f} s ({100 * v / total:.0f}%)" for k, v in phases.items())
    print(f"phases over all requests ({total:.2f} s): {share}; replay and rest {total - sum(phases.values()):.2f} s")
    print("iterations:", [s.optimization.iterations for s in solutions])
    print("stop reasons:", sorted({s.optimization.stop_reason for s in solutions}))
    print("returns Q_0:", [int(s.expert_return) for s in solutions])
    slopes = [s.optimization.max_value_slope for s in solutions]
    print(f"max |W_x| (surrogate cost-to-go) per request: max {max(slopes):.1f}, median {np.median(slopes):.1f}")

    data, windowed = Dataset(2, 1), Dataset(2, 1)
    for s0, s in zip(starts, solutions, strict=True):
        data.append(s.trajectory)
        _, rewards = replay_rewards(expert.plant, s0, s.trajectory.actions, expert.warm_start, expert.horizon - 1)
        windowed.append_arrays(s.trajectory.states, s.trajectory.actions, window_values(rewards, expert.horizon))
    for name, d in (("return-to-go", data), ("window", windowed)):
        print(f"data slope of the true Q ({name} values) over {len(d)} points: {estimate_global(d):.4g}")
    print(f"paper L = {PAPER_LIPSCHITZ:g}")
    if args.grid < 2:
        return

    grid = np.linspace(-math.pi, math.pi, args.grid, endpoint=False)
    returns = np.array([expert.solve([a, 0.0]).expert_return for a in grid])
    jumps = np.abs(np.diff(returns))
    i = int(np.argmax(jumps))
    lo, hi = float(grid[i]), float(grid[i + 1])
    q_lo, q_hi = float(returns[i]), float(returns[i + 1])
    print(f"grid of {args.grid} s0 angles: returns {returns.min():.0f}-{returns.max():.0f}; largest neighbour jump")
    print(f"  {q_hi - q_lo:+.0f} between {lo:.6f} and {hi:.6f} rad (slope {abs(q_hi - q_lo) / (hi - lo):.0f})")
    for _ in range(args.bisect):
        mid = 0.5 * (lo + hi)
        q_mid = expert.solve([mid, 0.0]).expert_return
        if abs(q_mid - q_lo) >= abs(q_hi - q_mid):
            hi, q_hi = mid, q_mid
        else:
            lo, q_lo = mid, q_mid
        jump = abs(q_hi - q_lo)
        print(f"  bisect: |dQ_0| = {jump:.0f} over {hi - lo:.3e} rad -> slope {jump / (hi - lo):.3g}")


if __name__ == "__main__":
    main()
