"""Figure 4 and Figure 5 of the paper, drawn from the experiment's run records (PNG, Agg)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FuncFormatter, SymmetricalLogLocator
from scipy.stats import gaussian_kde

from npp_ros.certificate.certifier import QUANTITY
from npp_ros.experiment import RunRecord

POLICY_COLOR = "tab:blue"
EXPERT_COLOR = "tab:orange"
CERT_COLOR = "tab:purple"


def _pooled_by_checkpoint(records: Sequence[RunRecord], attr: str) -> tuple[np.ndarray, list[np.ndarray]]:
    checkpoints = sorted({row.checkpoint for record in records for row in record.evaluations})
    pooled = [
        np.array([getattr(row, attr) for record in records for row in record.evaluations if row.checkpoint == c])
        for c in checkpoints
    ]
    return np.array(checkpoints), pooled


def label_gap_axis(ax: plt.Axes) -> None:
    """Plain-number ticks on the symlog gap axis, at 1-2-3-5 steps where its decades alone leave fewer than 3.

    Gaps within one decade (all between 130 and 900, say) would otherwise show no tick at all.
    """
    lo, hi = ax.get_ylim()
    if sum(lo <= tick <= hi for tick in ax.get_yticks()) < 3:
        ax.yaxis.set_major_locator(SymmetricalLogLocator(base=10, linthresh=1.0, subs=(1.0, 2.0, 3.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _pos: f"{value:g}"))


def training_curves(records: Sequence[RunRecord], path: Path) -> Path:
    """Figure 4: returns (median, 95% band), |D|, oracle calls and the gap each episode checked at s0."""
    arm = records[0].arm
    epsilon = records[0].epsilon
    fig, axes = plt.subplots(1, 4, figsize=(19, 4.2))
    ax = axes[0]
    for attr, color, label in (("policy_return", POLICY_COLOR, "policy"), ("expert_return", EXPERT_COLOR, "expert")):
        x, pooled = _pooled_by_checkpoint(records, attr)
        if not len(x):
            continue
        med = [np.median(v) for v in pooled]
        lo = [np.quantile(v, 0.025) for v in pooled]
        hi = [np.quantile(v, 0.975) for v in pooled]
        ax.plot(x, med, marker="o", ms=3, color=color, label=f"{label} (median)")
        ax.fill_between(x, lo, hi, color=color, alpha=0.2, label=f"{label} (2.5-97.5%)")
    ax.set_title(f"return from s0 ~ rho (N = {_n(records)} per seed and checkpoint)")
    ax.set_xlabel("episode")
    ax.legend(fontsize=8)
    for record in records:
        episodes = np.arange(1, len(record.episodes) + 1)
        axes[1].plot(episodes, [row.dataset_size for row in record.episodes], label=f"seed {record.seed}")
        axes[2].plot(episodes, [row.oracle_calls for row in record.episodes], label=f"seed {record.seed}")
        gaps = np.array([row.checked_gap for row in record.episodes], dtype=np.float64)
        axes[3].plot(episodes, np.where(np.isfinite(gaps), gaps, np.nan), lw=0.8, label=f"seed {record.seed}")
        if record.certified_episode is not None:
            axes[3].axvline(record.certified_episode, color=CERT_COLOR, ls="--", lw=1)
    axes[1].set_title("dataset size |D|")
    axes[2].set_title("oracle calls")
    axes[3].axhline(epsilon, color="k", ls=":", label=f"epsilon = {epsilon:g}")
    axes[3].set_yscale("symlog", linthresh=1.0)  # a negative gap (crossed bounds) proves L too small
    label_gap_axis(axes[3])
    axes[3].set_title(f"checked gap {QUANTITY[arm.certify]} (dashed: certified)")
    for ax in axes[1:]:
        ax.set_xlabel("episode")
        ax.legend(fontsize=8)
    fig.suptitle(
        f"{arm.label}: L = {records[0].lipschitz.value:.0f} ({records[0].lipschitz.source}), {len(records)} seeds"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _n(records: Sequence[RunRecord]) -> int:
    rows = records[0].evaluations
    return sum(1 for row in rows if row.checkpoint == rows[0].checkpoint) if rows else 0


def gap_distributions(records: Sequence[RunRecord], path: Path, stages: int = 4) -> Path:
    """Figure 5: density of V^pi(s0) - V*(s0) at several stages, pooled over seeds.

    V* here is the measured H-step return of the optimal controller from the same s0.
    """
    arm = records[0].arm
    epsilon = records[0].epsilon
    common = sorted(set.intersection(*({row.checkpoint for row in r.evaluations} for r in records)))
    chosen = [common[i] for i in np.unique(np.linspace(0, len(common) - 1, min(stages - 1, len(common))).astype(int))]
    groups: list[tuple[str, np.ndarray]] = []
    for c in chosen:
        values = [-row.gap_to_optimal for r in records for row in r.evaluations if row.checkpoint == c]
        groups.append((f"episode {c}", np.array(values)))
    if any(_last(r) != chosen[-1] for r in records):
        finals = [-row.gap_to_optimal for r in records for row in r.evaluations if row.checkpoint == _last(r)]
        groups.append(("final (certified or budget)", np.array(finals)))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(groups)))
    lo = min(float(v.min()) for _, v in groups)
    grid = np.linspace(min(lo, -epsilon) * 1.05, max(0.0, max(float(v.max()) for _, v in groups)) + 5, 400)
    for (label, values), color in zip(groups, colors, strict=True):
        if np.ptp(values) > 1e-9 and len(values) > 2:
            ax.plot(grid, gaussian_kde(values)(grid), color=color, label=f"{label} (n = {len(values)})")
        else:
            ax.axvline(float(values.mean()), color=color, label=f"{label} (all {values.mean():.1f})")
    ax.axvline(-epsilon, color="k", ls=":", label=f"-epsilon = {-epsilon:g}")
    ax.set_xlabel("V^pi(s0) - V*(s0)   (V*: measured return of the optimal controller)")
    ax.set_ylabel("density (KDE)")
    ax.set_title(f"{arm.label}: suboptimality over training")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _last(record: RunRecord) -> int:
    return max(row.checkpoint for row in record.evaluations)
