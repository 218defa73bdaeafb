"""How often the sequential and the paper's stopping rules certify a policy below p: the table in docs/concepts.md.

Usage: .venv/bin/python scripts/stopping_rules.py [--repetitions 2000] [--seed 7]
Prints a Markdown table to stdout, no figure: at the defaults (about 25 s) exactly the one under "When to
stop: the stopping rules" in docs/concepts.md. Policies pass each check with probability q < p = 0.9 and
are replaced after every failure (as new data replaces the policy in a run), for up to 1,000 episodes;
delta = 0.1. The mixture rule has its own certifier and is simulated by scripts/simulate_rules.py
(results/rules/simulation.md).
"""

from __future__ import annotations

import argparse

from npp_ros.certificate.certifier import STOPPING_RULES, CertificationSpec, false_certificate_rate
from npp_ros.policy.lipschitz import LipschitzConstant

RULES = tuple(rule for rule in STOPPING_RULES if rule != "mixture")  # the rules the core's Certifier runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repetitions", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    print("| q per policy | " + " | ".join(f"false certificates, {rule} rule" for rule in RULES) + " |")
    print("|---|" + "---|" * len(RULES))
    lipschitz = LipschitzConstant(1.0, "user")  # condition (i) does not use L
    for q in (0.85, 0.8, 0.7):
        rates = [
            false_certificate_rate(
                CertificationSpec("i", 1.0, 0.9, 0.1, lipschitz, rule=rule), q, args.repetitions, args.seed
            )
            for rule in RULES
        ]
        print(f"| {q} | " + " | ".join(f"{rate:.1%}" for rate in rates) + " |")


if __name__ == "__main__":
    main()
