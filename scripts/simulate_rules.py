"""The stopping rules on simulated runs: checks and expert calls to a certificate, and false certificates.

Usage: .venv/bin/python scripts/simulate_rules.py [--repetitions 1000] [--max-checks 20000] [--seed 11]
       [--out results/rules]

No plant and no expert: a policy that holds j joined trajectories passes each check with
probability q_j, and the rules' own certifiers (npp_ros.certificate.certifier and
npp_ros.certificate.mixture, through npp_ros.certificate.mixture.simulate_run) decide from the
outcomes, holding data back exactly as the loop does. p = 0.9, delta = 0.1.

- Learning curves: q_j = c - (c - 0.5) exp(-j / tau), for a plateau c and a pace tau, and
  q_j = 1 - 0.5 exp(-j / 40); "q = 1 at once" is a policy that passes every check from its first
  trajectory on. The tau 80 curves learn slowly, as the pendulum swing-up's oracle-mode runs did
  (224-351 trajectories joined when they certified). In "rollout" mode only failed checks ask the
  expert; in "oracle" mode every check does, and (both rules) the data of passed checks join only
  when the policy is no longer frozen.
- Constant q (every policy the same): every certificate is false when q <= p.

Writes OUT/simulation.md and OUT/simulation.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from npp_ros.certificate.certifier import CertificationSpec
from npp_ros.certificate.mixture import simulate_run
from npp_ros.policy.lipschitz import LipschitzConstant

RULES = ("sequential", "mixture")


def plateau(ceiling: float, pace: float) -> Callable[[int], float]:
    return lambda joined: ceiling - (ceiling - 0.5) * math.exp(-joined / pace)


CURVES: dict[str, Callable[[int], float]] = {
    "q_j = 1 - 0.5 exp(-j / 40)": lambda joined: 1 - 0.5 * math.exp(-joined / 40),
    "plateau 0.99, tau 8": plateau(0.99, 8),
    "plateau 0.98, tau 5": plateau(0.98, 5),
    "plateau 0.97, tau 8": plateau(0.97, 8),
    "plateau 0.95, tau 8": plateau(0.95, 8),
    "plateau 0.98, tau 80": plateau(0.98, 80),
    "plateau 0.97, tau 80": plateau(0.97, 80),
    "plateau 0.96, tau 80": plateau(0.96, 80),
    "q = 1 at once": lambda joined: 1.0,
}


def spec(rule: str) -> CertificationSpec:
    return CertificationSpec("i", 1.0, 0.9, 0.1, LipschitzConstant(1.0, "user"), rule=rule)  # type: ignore[arg-type]


def learning_rows(repetitions: int, max_checks: int, seed: int) -> list[dict[str, object]]:
    rows = []
    for mode in ("rollout", "oracle"):
        for name, curve in CURVES.items():
            for rule in RULES:
                rng = np.random.default_rng([seed, len(rows)])
                runs = [simulate_run(spec(rule), curve, rng, max_checks, mode == "oracle") for _ in range(repetitions)]
                checks = np.array([r.checks for r in runs])
                certified = [r for r in runs if r.certified]
                certified_q = float(np.mean([r.certified_rate for r in certified])) if certified else math.nan
                rows.append({
                    "mode": mode, "curve": name, "rule": rule,
                    "checks_mean": float(checks.mean()), "checks_p90": float(np.percentile(checks, 90)),
                    "expert_calls_mean": float(np.mean([r.expert_calls for r in runs])),
                    "failures_mean": float(np.mean([r.failures for r in runs])),
                    "uncertified": 1 - len(certified) / repetitions,
                    "certified_q_mean": certified_q,
                    "false": sum(r.certified_rate < 0.9 for r in certified) / repetitions,
                })  # fmt: skip
                print(f"{mode} {name} {rule}: {rows[-1]['checks_mean']:.0f} checks", file=sys.stderr, flush=True)
    return rows


def false_rows(repetitions: int, seed: int, episodes: int = 5000) -> list[dict[str, object]]:
    rows = []
    for q in (0.85, 0.89, 0.9):
        for rule in RULES:
            rng = np.random.default_rng([seed, 1000 + len(rows)])
            runs = [simulate_run(spec(rule), lambda joined, q=q: q, rng, episodes) for _ in range(repetitions)]
            false = sum(r.certified for r in runs) / repetitions
            rows.append({"q": q, "rule": rule, "episodes": episodes, "false": false})
    return rows


def table(rows: list[dict[str, object]], max_checks: int) -> str:
    lines = [
        "| mode | success rate of the policy over j joined trajectories | rule | checks (mean / 90th pct) "
        "| expert calls (mean) | failed checks (mean) | uncertified | certified q (mean) | false certificates |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p90 = f"{r['checks_p90']:,.0f}" if r["checks_p90"] < max_checks else f"budget ({max_checks:,})"
        lines.append(
            f"| {r['mode']} | {r['curve']} | {r['rule']} | {r['checks_mean']:,.0f} / {p90} "
            f"| {r['expert_calls_mean']:,.0f} | {r['failures_mean']:,.0f} | {r['uncertified']:.1%} "
            f"| {r['certified_q_mean']:.3f} | {r['false']:.1%} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repetitions", type=int, default=1000, help="simulated runs per cell")
    ap.add_argument("--max-checks", type=int, default=20000, help="a run's budget of checks (episodes)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", type=Path, default=Path("results/rules"))
    args = ap.parse_args()
    started = time.perf_counter()
    learning = learning_rows(args.repetitions, args.max_checks, args.seed)
    false = false_rows(2 * args.repetitions, args.seed)
    command = f"scripts/simulate_rules.py {' '.join(sys.argv[1:])}".strip()
    false_lines = ["| q of every policy | rule | false certificates within 5,000 episodes |", "|---|---|---|"]
    false_lines += [f"| {r['q']} | {r['rule']} | {r['false']:.2%} |" for r in false]
    text = (
        f"Simulated runs, p = 0.9, delta = 0.1, {args.repetitions:,} runs a row (`{command}`, "
        f"{time.perf_counter() - started:.0f} s):\n\n{table(learning, args.max_checks)}\n\n"
        f"Every policy at the same q ({2 * args.repetitions:,} runs a row; every certificate is false):\n\n"
        + "\n".join(false_lines)
        + "\n"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "simulation.md").write_text(text)
    (args.out / "simulation.json").write_text(json.dumps({"learning": learning, "constant_q": false}, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
