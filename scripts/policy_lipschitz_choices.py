"""The policy's L each run chose from its data (``--policy-lipschitz select``), read back from the run files.

For each run folder: at each choice point (4, 8, 16, ... trajectories), how many held-out starts the choice was
scored on and, per candidate (the claim's L times 1, 10, 100, 1e3, 1e8), how many of its rollouts met the task's
success criterion and their mean return; the chosen one in bold.

    .venv/bin/python scripts/policy_lipschitz_choices.py runs/panda/select-s0 runs/panda/select-s1 \\
        --out results/policy-lipschitz/panda-select/choices.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

from npp_ros.run.policy_lipschitz import LADDER
from npp_ros.run.read import read_run


def table(folders: list[Path]) -> str:
    factors = " | ".join(f"x{factor:g}" for factor in LADDER)
    lines = [
        f"| run | claim's L | trajectories | starts | {factors} |",
        "|---|---|---|---|" + "---|" * len(LADDER),
    ]
    for folder in folders:
        run = read_run(folder)
        claim = run.spec.lipschitz.value
        for point, choice in sorted(run.lipschitz_choices.items()):
            cells = []
            for score in choice.scores:
                cell = f"{score.successes} met, {score.mean_return:.1f}"
                cells.append(f"**{cell}**" if score.lipschitz == choice.value else cell)
            lines.append(f"| {folder.name} | {claim:.4g} | {point} | {choice.starts} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders made with --policy-lipschitz select")
    parser.add_argument("--out", type=Path, required=True, help="the markdown file to write")
    args = parser.parse_args()
    title = "# The policy's L chosen at each choice point\n\n"
    how = (
        "Per candidate: rollouts from the held-out starts that met the task's success criterion, and their mean "
        "return; the chosen candidate in bold (most successes, then the higher mean return, then the smaller L).\n\n"
    )
    command = "`.venv/bin/python scripts/policy_lipschitz_choices.py " + " ".join(str(r) for r in args.runs)
    text = title + command + f" --out {args.out}`\n\n" + how + table(args.runs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
