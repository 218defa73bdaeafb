"""The per-robot map as a figure: one panel per axis (the policy's and the expert's success per bin, with counts),
and the draws themselves over the two identifiable ratios (else the first two parameters), failed ones marked."""

from __future__ import annotations

import math
from pathlib import Path

from npp_ros.run.per_robot.success_map import SuccessMap, value_on


def write_figure(success: SuccessMap, path: str | Path) -> Path:
    """Draws ``success`` to ``path`` (PNG, or any format matplotlib knows by the suffix) without a display."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tables = success.tables
    ratios = [t.axis for t in tables if t.axis.ratio]
    plain = [t.axis for t in tables if not t.axis.ratio and not t.axis.discrete]
    pair = ratios[:2] if len(ratios) >= 2 else plain[:2]
    panels = len(tables) + (1 if len(pair) == 2 and success.points else 0)
    columns = min(3, panels)
    rows = math.ceil(panels / columns)
    fig, grid = plt.subplots(rows, columns, figsize=(5 * columns, 3.6 * rows), squeeze=False)
    cells = [ax for row in grid for ax in row]
    for ax, part in zip(cells, tables, strict=False):
        labels = part.axis.labels()
        where = range(len(labels))
        for shift, who, tallies, colour in ((-0.2, "policy", part.policy, "tab:blue"),
                                            (0.2, "expert", part.expert, "tab:orange")):  # fmt: skip
            if not any(t.judged for t in tallies):
                continue
            heights = [t.rate if t.judged else 0.0 for t in tallies]
            ax.bar([k + shift for k in where], heights, width=0.38, color=colour, label=who)
            for k, t in ((k, t) for k, t in zip(where, tallies, strict=True) if t.judged):
                ax.text(k + shift, 0.02, f"{t.succeeded}/{t.judged}", ha="center", va="bottom", fontsize=7, rotation=90)
        ax.set_xticks(list(where), labels, fontsize=7, rotation=20)
        ax.set_ylim(0, 1.2)
        ax.set_title(part.axis.name, fontsize=9)
        ax.set_ylabel("success")
        ax.legend(fontsize=7, loc="upper center", ncol=2, frameon=False)
    if panels > len(tables):
        ax = cells[len(tables)]
        who = 1 if success.policy.judged else 2
        for met, marker, colour, label in ((True, "o", "tab:green", "met"), (False, "x", "tab:red", "failed")):
            xs = [value_on(pair[0], p[0]) for p in success.points if p[who] is met]
            ys = [value_on(pair[1], p[0]) for p in success.points if p[who] is met]
            ax.scatter(xs, ys, marker=marker, color=colour, s=12, label=label, alpha=0.7)
        ax.set_xlabel(pair[0].name, fontsize=8)
        ax.set_ylabel(pair[1].name, fontsize=8)
        ax.set_title(f"each draw: the {'policy' if who == 1 else 'expert'}", fontsize=9)
        ax.legend(fontsize=7)
    for ax in cells[panels:]:
        ax.set_visible(False)
    fig.suptitle(success.source, fontsize=10)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
