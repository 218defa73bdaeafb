"""Compression of dominated points: which stored triplets can never attain V_lb or V_ub.

Point i is dominated for V_lb when some j has Q_j - L|s_i - s_j| >= Q_i: by the triangle
inequality j then scores at least as well as i at every state. Mirrored for V_ub
(Q_j + L|s_i - s_j| <= Q_i). Leaving such points out of a search changes no bound, no gap and
no action, provided two floating-point details are handled, which :class:`BoundIndex` does:

* ties: with equality, i may still be the smallest-index maximiser, so only a strict margin counts;
* rounding: computed scores carry rounding errors that grow with |Q| and L|s - s_i|. A point is
  left out only when its dominator wins by more than 16 times the worst rounding error for
  queries within a ball around the data (:func:`npp_ros.policy.kdtree.dominance_threshold`); queries
  outside that ball search the uncompressed points by brute force.

So the index returns the same values and the same indices as the brute force over the full
dataset, bit for bit. The dataset, and with it the stored expert data, is never modified.

The policy's index compresses as data arrives (new points are checked against everything held);
:func:`compression_report` checks every point against the whole dataset at once, which finds
more, since old points can be dominated by later data.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from npp_ros.policy.dataset import Dataset
from npp_ros.policy.kdtree import BoundIndex


@dataclass(frozen=True)
class CompressionReport:
    """Points a search still needs, per bound, out of ``points``."""

    points: int
    kept_lower: int
    kept_upper: int
    kept_either: int  # needed by at least one bound: what a single shared search would keep

    def fraction(self, kept: int) -> float:
        return kept / self.points if self.points else 1.0

    def as_dict(self) -> dict[str, float]:
        out: dict[str, float] = dict(asdict(self))
        for name in ("kept_lower", "kept_upper", "kept_either"):
            out[f"{name}_fraction"] = self.fraction(int(out[name]))
        return out


def _masks(index: BoundIndex) -> tuple[np.ndarray, np.ndarray]:
    size = len(index.dataset)
    lower, upper = np.zeros(size, dtype=bool), np.zeros(size, dtype=bool)
    for segment in index.segments:
        lower[segment.trees[1.0].order] = True
        upper[segment.trees[-1.0].order] = True
    lower[index.tail_start :] = True
    upper[index.tail_start :] = True
    return lower, upper


def kept_masks(dataset: Dataset, lipschitz: float) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (lower, upper): True where no other point safely dominates the point."""
    index = BoundIndex(dataset, lipschitz, compress=True, tail_limit=max(1, len(dataset)))
    index.sync()
    return _masks(index)


def _report(size: int, lower: np.ndarray, upper: np.ndarray) -> CompressionReport:
    return CompressionReport(size, int(lower.sum()), int(upper.sum()), int((lower | upper).sum()))


def compression_report(dataset: Dataset, lipschitz: float) -> CompressionReport:
    """Check every point against the whole dataset; count what each bound still needs."""
    return _report(len(dataset), *kept_masks(dataset, lipschitz))


def index_report(index: BoundIndex) -> CompressionReport:
    """What a live index (compressing as data arrived) actually searches."""
    index.sync()
    return _report(len(index.dataset), *_masks(index))
