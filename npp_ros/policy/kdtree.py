"""Exact fast search for max_i (v_i - L|s - s_i|): a kd-tree whose nodes carry their best value.

V_lb(s) = max_i Q_i - L|s - s_i| is this search with v = Q; V_ub(s) = min_j Q_j + L|s - s_j| is
minus the same search with v = -Q (round-to-nearest is symmetric, so -fl(-Q - x) == fl(Q + x) bit
for bit). No 1-NN library supports the per-point offset, hence this module.

Exactness, bit for bit, against the brute force of :mod:`npp_ros.policy.bounds`:

* every point score is computed with the same operations in the same order as the brute force:
  ``acc = sum_k (q_k - p_k)^2`` accumulated coordinate by coordinate, ``v - L * sqrt(acc)``;
  numba compiles without ``fastmath`` and LLVM does not contract the products into FMAs (a test
  checks the machine code);
* a node's bound uses the distance to its bounding box computed by the same sequence. IEEE
  rounding is monotone in every argument, so the computed bound is >= the computed score of
  every point inside the node, with no slack needed; nodes are pruned only when their bound is
  strictly below the best score (or equal with only larger indices inside), so ties still go to
  the smallest index.

The tree also splits on the value, v / L, as an extra coordinate: where values vary faster than
positions (low dimensions, large value ranges) that keeps each node's best value tight.

The index follows a growing dataset with a logarithmic method: the newest points are searched by
brute force (the tail); once the tail holds ``tail_limit`` points it becomes a segment with its own
tree, and segments of similar size merge, so each point is rebuilt O(log N) times and a query
visits O(log N) trees that share one running best.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from npp_ros.policy.dataset import Dataset, FloatArray

IntArray = NDArray[np.int64]

LEAF_SIZE = 16
"""Points per leaf: small leaves prune more, large ones amortise the node overhead."""
TAIL_LIMIT = 2048
"""The newest points stay in the brute-force tail until there are this many."""
DOMINANCE_BUDGET = 8
"""Leaves a dominance check may visit before it keeps the point (bounds the compression cost)."""
_DOMINANCE_SAMPLE = 256  # new points checked first; if none is dominated, the rest are not checked
_PROVISIONAL_TREE = 4096  # dominance checks over more new points than this search a tree built for them
_STACK = 256  # depth-first stack; a median-split tree over < 2^63 points is < 64 levels deep


# --------------------------------------------------------------------------- build
@njit(cache=True)
def _select(perm: IntArray, key: FloatArray, lo: int, hi: int, k: int) -> None:  # pragma: no cover - compiled
    """Quickselect on perm[lo:hi] by key[perm]: the k-th smallest lands at k (3-way, duplicates safe)."""
    while hi - lo > 1:
        a, b, c = key[perm[lo]], key[perm[(lo + hi) // 2]], key[perm[hi - 1]]
        if a > b:
            a, b = b, a
        pivot = b if b <= c else (c if c >= a else a)
        lt, i, gt = lo, lo, hi
        while i < gt:
            x = key[perm[i]]
            if x < pivot:
                perm[lt], perm[i] = perm[i], perm[lt]
                lt += 1
                i += 1
            elif x > pivot:
                gt -= 1
                perm[gt], perm[i] = perm[i], perm[gt]
            else:
                i += 1
        if k < lt:
            hi = lt
        elif k >= gt:
            lo = gt
        else:
            return


@njit(cache=True)
def _build(points, values, order, leaf_size, value_scale):  # pragma: no cover - compiled
    """Median-split kd-tree over (points, values * value_scale); returns the permutation and node arrays.

    Children of node c are child[c] and child[c] + 1; child = -1 marks a leaf. node_v is the
    largest value in the node, node_min the smallest ``order`` (dataset index) in it.
    """
    m, n = points.shape
    perm = np.arange(m)
    half = max(1, (leaf_size + 1) // 2)
    max_nodes = 2 * (m // half + 1) + 1
    box_lo = np.empty((max_nodes, n))
    box_hi = np.empty((max_nodes, n))
    node_v = np.empty(max_nodes)
    node_min = np.empty(max_nodes, dtype=np.int64)
    start = np.empty(max_nodes, dtype=np.int64)
    end = np.empty(max_nodes, dtype=np.int64)
    child = np.empty(max_nodes, dtype=np.int64)
    key = np.empty(m)
    st_node = np.empty(_STACK, dtype=np.int64)
    st_lo = np.empty(_STACK, dtype=np.int64)
    st_hi = np.empty(_STACK, dtype=np.int64)
    count = 1
    top = 1
    st_node[0], st_lo[0], st_hi[0] = 0, 0, m
    while top > 0:
        top -= 1
        node, lo, hi = st_node[top], st_lo[top], st_hi[top]
        start[node], end[node], child[node] = lo, hi, -1
        vmax, vmin, imin = -np.inf, np.inf, np.iinfo(np.int64).max
        for k in range(n):
            box_lo[node, k] = np.inf
            box_hi[node, k] = -np.inf
        for j in range(lo, hi):
            p = perm[j]
            for k in range(n):
                x = points[p, k]
                if x < box_lo[node, k]:
                    box_lo[node, k] = x
                if x > box_hi[node, k]:
                    box_hi[node, k] = x
            v = values[p]
            vmax = max(vmax, v)
            vmin = min(vmin, v)
            imin = min(imin, order[p])
        node_v[node], node_min[node] = vmax, imin
        if hi - lo <= leaf_size:
            continue
        dim, spread = -1, 0.0
        for k in range(n):
            w = box_hi[node, k] - box_lo[node, k]
            if w > spread:
                dim, spread = k, w
        if (vmax - vmin) * value_scale > spread:
            dim = n
        if dim < 0:
            continue  # every point identical: one leaf
        for j in range(lo, hi):
            p = perm[j]
            key[p] = points[p, dim] if dim < n else values[p]
        mid = (lo + hi) // 2
        _select(perm, key, lo, hi, mid)
        left = count
        count += 2
        child[node] = left
        st_node[top], st_lo[top], st_hi[top] = left + 1, mid, hi
        st_node[top + 1], st_lo[top + 1], st_hi[top + 1] = left, lo, mid
        top += 2
    return (
        perm,
        box_lo[:count],
        box_hi[:count],
        node_v[:count],
        node_min[:count],
        start[:count],
        end[:count],
        child[:count],
    )


# --------------------------------------------------------------------------- search
@njit(cache=True, inline="always")
def _box_bound(q, box_lo, box_hi, node_v, c, lipschitz):  # pragma: no cover - compiled
    """node_v[c] - L * (distance from q to the box of c), with the point-score operation order."""
    acc = 0.0
    for k in range(q.shape[0]):
        x = q[k]
        lo = box_lo[c, k]
        if x < lo:
            d = lo - x
            acc += d * d
        else:
            hi = box_hi[c, k]
            if x > hi:
                d = x - hi
                acc += d * d
    return node_v[c] - lipschitz * np.sqrt(acc)


@njit(cache=True, inline="always")
def _scan_range(q, lipschitz, sign, data_states, data_values, a, b, best, bi):  # pragma: no cover - compiled
    """Brute force over dataset rows [a, b) on top of a running best (best, bi); ties to the smallest index."""
    for i in range(a, b):
        v = sign * data_values[i]
        if v < best:
            continue
        acc = 0.0
        for k in range(q.shape[0]):
            d = q[k] - data_states[i, k]
            acc += d * d
        s = v - lipschitz * np.sqrt(acc)
        if bi < 0 or s > best or (s == best and i < bi):
            best, bi = s, i
    return best, bi


@njit(cache=True)
def _search(
    queries, lipschitz, sign, data_states, data_values, tail_start,
    pts, vals, order, box_lo, box_hi, node_v, node_min, start, end, child,
    roots, seg_r2, seg_a, seg_b, out_val, out_idx,
):  # fmt: skip  # pragma: no cover - compiled
    """max_i (sign * Q_i - L|q - s_i|) for every query, ties to the smallest dataset index.

    Tail [tail_start, N) by brute force; each segment by its tree when |q|^2 <= seg_r2 (its
    compressed points are safe there), else by brute force over its dataset range [a, b).
    """
    n_queries, n = queries.shape
    total = data_values.shape[0]
    st_node = np.empty(_STACK, dtype=np.int64)
    st_bound = np.empty(_STACK)
    for b in range(n_queries):
        q = queries[b]
        best, bi = -np.inf, -1
        best, bi = _scan_range(q, lipschitz, sign, data_states, data_values, tail_start, total, best, bi)
        r2 = 0.0
        for k in range(n):
            r2 += q[k] * q[k]
        for g in range(roots.shape[0]):
            if r2 > seg_r2[g]:
                best, bi = _scan_range(q, lipschitz, sign, data_states, data_values, seg_a[g], seg_b[g], best, bi)
                continue
            st_node[0] = roots[g]
            st_bound[0] = _box_bound(q, box_lo, box_hi, node_v, roots[g], lipschitz)
            top = 1
            while top > 0:
                top -= 1
                c = st_node[top]
                bound = st_bound[top]
                if bi >= 0 and (bound < best or (bound == best and node_min[c] > bi)):
                    continue
                left = child[c]
                if left < 0:
                    for p in range(start[c], end[c]):
                        v = vals[p]
                        if v < best:
                            continue
                        acc = 0.0
                        for k in range(n):
                            d = q[k] - pts[p, k]
                            acc += d * d
                        s = v - lipschitz * np.sqrt(acc)
                        i = order[p]
                        if bi < 0 or s > best or (s == best and i < bi):
                            best, bi = s, i
                    continue
                # a child whose best value is already below the running best cannot win: no distance needed
                b1 = _box_bound(q, box_lo, box_hi, node_v, left, lipschitz) if node_v[left] >= best else -np.inf
                r = left + 1
                b2 = _box_bound(q, box_lo, box_hi, node_v, r, lipschitz) if node_v[r] >= best else -np.inf
                if b1 >= b2:  # the more promising child is popped first
                    if b2 >= best:
                        st_node[top], st_bound[top] = r, b2
                        top += 1
                    if b1 >= best:
                        st_node[top], st_bound[top] = left, b1
                        top += 1
                else:
                    if b1 >= best:
                        st_node[top], st_bound[top] = left, b1
                        top += 1
                    if b2 >= best:
                        st_node[top], st_bound[top] = r, b2
                        top += 1
        out_val[b] = best
        out_idx[b] = bi


@njit(cache=True)
def _exceeds(
    queries, thresholds, lipschitz, sign, data_states, data_values, tail_start,
    pts, vals, order, box_lo, box_hi, node_v, start, end, child, roots, leaf_budget, out,
):  # fmt: skip  # pragma: no cover - compiled
    """out[b] = whether some point is found scoring strictly above thresholds[b] at queries[b].

    For dominance checks: a dominator, if any, is usually close, so the search visits the most
    promising leaves first and gives up after ``leaf_budget`` leaves (False: the point is kept,
    which is always safe). That bounds the cost where nothing dominates (a true Lipschitz L).
    """
    n_queries, n = queries.shape
    total = data_values.shape[0]
    st_node = np.empty(_STACK, dtype=np.int64)
    for b in range(n_queries):
        q = queries[b]
        thr = thresholds[b]
        found = False
        for i in range(tail_start, total):
            v = sign * data_values[i]
            if v <= thr:
                continue
            acc = 0.0
            for k in range(n):
                d = q[k] - data_states[i, k]
                acc += d * d
            if v - lipschitz * np.sqrt(acc) > thr:
                found = True
                break
        g = 0
        leaves = 0
        while not found and g < roots.shape[0] and leaves < leaf_budget:
            st_node[0] = roots[g]
            top = 1
            while top > 0 and not found and leaves < leaf_budget:
                top -= 1
                c = st_node[top]
                left = child[c]
                if left >= 0:
                    b1 = _box_bound(q, box_lo, box_hi, node_v, left, lipschitz)
                    b2 = _box_bound(q, box_lo, box_hi, node_v, left + 1, lipschitz)
                    first, second = (left, left + 1) if b1 >= b2 else (left + 1, left)
                    if min(b1, b2) > thr:
                        st_node[top] = second
                        top += 1
                    if max(b1, b2) > thr:
                        st_node[top] = first
                        top += 1
                    continue
                leaves += 1
                for p in range(start[c], end[c]):
                    v = vals[p]
                    if v <= thr:
                        continue
                    acc = 0.0
                    for k in range(n):
                        d = q[k] - pts[p, k]
                        acc += d * d
                    if v - lipschitz * np.sqrt(acc) > thr:
                        found = True
                        break
            g += 1
        out[b] = found


# --------------------------------------------------------------------------- python side
_UNIT_ROUNDOFF = 2.0**-53


@dataclass
class _Tree:
    """One kd-tree over some dataset points, values already signed (Q or -Q)."""

    pts: FloatArray
    vals: FloatArray
    order: IntArray  # dataset index of each tree point
    box_lo: FloatArray
    box_hi: FloatArray
    node_v: FloatArray
    node_min: IntArray
    start: IntArray
    end: IntArray
    child: IntArray

    @classmethod
    def build(cls, states: FloatArray, signed: FloatArray, order: IntArray, value_scale: float, leaf: int) -> _Tree:
        perm, *nodes = _build(states, signed, order, leaf, value_scale)
        return cls(np.ascontiguousarray(states[perm]), np.ascontiguousarray(signed[perm]), order[perm], *nodes)

    @property
    def size(self) -> int:
        return int(self.order.shape[0])


@dataclass
class _Segment:
    """Dataset points [a, b) with their trees for V_lb (sign +1) and V_ub (sign -1).

    A tree may hold only the points its bound cannot do without (compression); that is exact for
    queries with |q|^2 <= r2, and the search falls back to brute force over [a, b) beyond.
    """

    a: int
    b: int
    r2: float
    trees: dict[float, _Tree]

    @property
    def size(self) -> int:
        return self.b - self.a


class _Forest:
    """The trees of one sign laid end to end, so one compiled call searches them all.

    Buffers grow by doubling and segments only change at the end (merges replace the newest
    ones), so appending a segment costs its own size, not the forest's.
    """

    _FIELDS = ("pts", "vals", "order", "box_lo", "box_hi", "node_v", "node_min", "start", "end", "child")
    _POINT_FIELDS = frozenset({"pts", "vals", "order"})

    def __init__(self, sign: float, state_dim: int) -> None:
        self.sign = sign
        n = state_dim
        self._buf: dict[str, np.ndarray] = {
            "pts": np.empty((0, n)), "vals": np.empty(0), "order": np.empty(0, dtype=np.int64),
            "box_lo": np.empty((0, n)), "box_hi": np.empty((0, n)), "node_v": np.empty(0),
            "node_min": np.empty(0, dtype=np.int64), "start": np.empty(0, dtype=np.int64),
            "end": np.empty(0, dtype=np.int64), "child": np.empty(0, dtype=np.int64),
        }  # fmt: skip
        self._offsets: list[tuple[int, int]] = []  # (first point, first node) of each segment
        self._segments: list[_Segment] = []
        self.points = self.nodes = 0
        self._refresh()

    def truncate(self, count: int) -> None:
        """Keep the first ``count`` segments."""
        if count < len(self._offsets):
            self.points, self.nodes = self._offsets[count]
            del self._offsets[count:]
            del self._segments[count:]
            self._refresh()

    def append(self, segment: _Segment) -> None:
        tree = segment.trees[self.sign]
        p0, n0 = self.points, self.nodes
        p1, n1 = p0 + tree.size, n0 + tree.node_v.shape[0]
        for name in self._FIELDS:
            buf = self._buf[name]
            need = p1 if name in self._POINT_FIELDS else n1
            if buf.shape[0] < need:
                grown = np.empty((max(need, 2 * buf.shape[0]), *buf.shape[1:]), dtype=buf.dtype)
                grown[: p0 if name in self._POINT_FIELDS else n0] = buf[: p0 if name in self._POINT_FIELDS else n0]
                self._buf[name] = buf = grown
            lo, hi = (p0, p1) if name in self._POINT_FIELDS else (n0, n1)
            values = getattr(tree, name)
            if name in ("start", "end"):
                values = values + p0
            elif name == "child":
                values = np.where(values >= 0, values + n0, -1)
            buf[lo:hi] = values
        self._offsets.append((p0, n0))
        self._segments.append(segment)
        self.points, self.nodes = p1, n1
        self._refresh()

    def _refresh(self) -> None:
        for name in self._FIELDS:
            setattr(self, name, self._buf[name][: self.points if name in self._POINT_FIELDS else self.nodes])
        self.roots = np.array([n0 for _, n0 in self._offsets], dtype=np.int64)
        self.r2 = np.array([seg.r2 for seg in self._segments], dtype=np.float64)
        self.a = np.array([seg.a for seg in self._segments], dtype=np.int64)
        self.b = np.array([seg.b for seg in self._segments], dtype=np.int64)


@dataclass(frozen=True)
class IndexStats:
    """What the index holds; kept_* count the points each bound's search still visits (tail included)."""

    points: int
    indexed: int
    tail: int
    segments: int
    kept_lower: int
    kept_upper: int


class BoundIndex:
    """Exact V_lb / V_ub search over a live :class:`Dataset` (see the module docstring).

    With ``compress`` the trees leave out points another point dominates with a safe margin (see
    :func:`dominance_threshold`); values and indices stay exactly those of the brute force over the
    full dataset. The dataset itself is never modified.
    """

    def __init__(
        self,
        dataset: Dataset,
        lipschitz: float,
        *,
        compress: bool = True,
        leaf_size: int = LEAF_SIZE,
        tail_limit: int = TAIL_LIMIT,
        value_weight: float = 1.0,
        dominance_budget: int = DOMINANCE_BUDGET,
    ) -> None:
        if not math.isfinite(lipschitz) or lipschitz <= 0:
            raise ValueError(f"the Lipschitz constant must be finite and > 0, got {lipschitz!r}")
        if leaf_size < 1 or tail_limit < 1:
            raise ValueError(f"leaf_size and tail_limit must be >= 1, got {leaf_size}, {tail_limit}")
        self.dataset = dataset
        self.lipschitz = float(lipschitz)
        self.compress = bool(compress)
        self.leaf_size = int(leaf_size)
        self.tail_limit = int(tail_limit)
        self.value_weight = float(value_weight)
        self.dominance_budget = int(dominance_budget)
        self.segments: list[_Segment] = []
        self._forests = {sign: _Forest(sign, dataset.state_dim) for sign in (1.0, -1.0)}

    # ------------------------------------------------------------------ maintenance
    @property
    def tail_start(self) -> int:
        return self.segments[-1].b if self.segments else 0

    def sync(self) -> None:
        """Index the tail once it holds ``tail_limit`` points; segments of similar size merge."""
        size = len(self.dataset)
        a = self.tail_start
        if size < a:
            raise RuntimeError("the dataset shrank under its index; datasets only grow")
        if size - a < self.tail_limit:
            return
        r2, kept = self._compress(a, size)
        segment = self._make_segment(a, size, r2, kept)
        while self.segments and self.segments[-1].size < 2 * segment.size:
            last = self.segments.pop()
            merged = {s: np.concatenate([last.trees[s].order, segment.trees[s].order]) for s in (1.0, -1.0)}
            segment = self._make_segment(last.a, segment.b, min(last.r2, segment.r2), merged)
        self.segments.append(segment)
        for forest in self._forests.values():
            forest.truncate(len(self.segments) - 1)
            forest.append(segment)

    def _make_segment(self, a: int, b: int, r2: float, kept: dict[float, IntArray]) -> _Segment:
        data, scale, leaf = self.dataset, self.value_weight / self.lipschitz, self.leaf_size
        trees = {}
        for sign, idx in kept.items():
            idx = np.sort(idx)
            trees[sign] = _Tree.build(data.states[idx], sign * data.values[idx], idx, scale, leaf)
        return _Segment(a, b, r2, trees)

    def _compress(self, a: int, b: int) -> tuple[float, dict[float, IntArray]]:
        """Safe ball and kept points of the new points [a, b): those no other point dominates."""
        everything = np.arange(a, b, dtype=np.int64)
        if not self.compress:
            return math.inf, {1.0: everything, -1.0: everything}
        data = self.dataset
        states, values = data.states[:b], data.values[:b]
        radius = math.sqrt(float(np.max(np.einsum("ij,ij->i", states, states)))) * (1 + 1e-9)
        ball = 4.0 * radius + 1.0
        threshold = dominance_threshold(float(np.max(np.abs(values))), self.lipschitz, ball + radius, data.state_dim)
        # A sample first: where it finds nothing dominated (typically a true Lipschitz L), checking every
        # point would cost a search each for nothing, so all are kept (always safe).
        sample = np.unique(np.linspace(a, b - 1, min(b - a, _DOMINANCE_SAMPLE)).astype(np.int64))
        kept = {}
        provisional: _Segment | None = None
        for sign in (1.0, -1.0):
            forest = self._forests[sign]
            if b - a > _DOMINANCE_SAMPLE and not self._dominated(forest, sample, threshold, a).any():
                kept[sign] = everything
                continue
            if b - a <= _PROVISIONAL_TREE:
                kept[sign] = everything[~self._dominated(forest, everything, threshold, a)]
                continue
            # many new points: search them through a provisional tree instead of a long brute-force tail
            if provisional is None:
                provisional = self._make_segment(a, b, math.inf, {1.0: everything, -1.0: everything})
            forest.append(provisional)
            try:
                kept[sign] = everything[~self._dominated(forest, everything, threshold, b)]
            finally:
                forest.truncate(len(self.segments))
        return ball * ball, kept

    def _dominated(self, f: _Forest, points: IntArray, threshold: float, tail: int) -> NDArray[np.bool_]:
        """Whether a point safely dominates each of ``points`` (within the search budget)."""
        data, sign = self.dataset, f.sign
        states, values = data.states, data.values
        out = np.empty(points.shape[0], dtype=np.bool_)
        _exceeds(
            np.ascontiguousarray(states[points]), sign * values[points] + threshold, self.lipschitz, sign,
            states, values, tail, f.pts, f.vals, f.order, f.box_lo, f.box_hi, f.node_v, f.start, f.end, f.child,
            f.roots, self.dominance_budget, out,
        )  # fmt: skip
        return out

    def stats(self) -> IndexStats:
        self.sync()
        tail = len(self.dataset) - self.tail_start
        kept = {sign: sum(s.trees[sign].size for s in self.segments) for sign in (1.0, -1.0)}
        return IndexStats(
            len(self.dataset), self.tail_start, tail, len(self.segments), kept[1.0] + tail, kept[-1.0] + tail
        )

    # ------------------------------------------------------------------ queries
    def search(self, queries: FloatArray, lower: bool) -> tuple[FloatArray, IntArray]:
        """(values, indices) of V_lb (lower) or V_ub at finite (B, n) queries; index -1 if empty."""
        self.sync()
        sign = 1.0 if lower else -1.0
        f = self._forests[sign]
        count = queries.shape[0]
        out_val = np.empty(count)
        out_idx = np.empty(count, dtype=np.int64)
        data = self.dataset
        _search(
            np.ascontiguousarray(queries, dtype=np.float64), self.lipschitz, sign, data.states, data.values,
            self.tail_start, f.pts, f.vals, f.order, f.box_lo, f.box_hi, f.node_v, f.node_min, f.start, f.end,
            f.child, f.roots, f.r2, f.a, f.b, out_val, out_idx,
        )  # fmt: skip
        return (out_val if lower else -out_val), out_idx


def dominance_threshold(value_bound: float, lipschitz: float, distance_bound: float, state_dim: int) -> float:
    """Margin T by which a point must out-score Q_i at s_i for i to be safely left out.

    Every computed score v - L|q - s| with |v| <= value_bound and |q - s| <= distance_bound is
    within E = (n + 4) u (value_bound + L distance_bound) of the exact one (u the unit roundoff).
    If j's computed score at s_i exceeds Q_i + T with T = 16 E, then exactly
    Q_j - L|s_i - s_j| - Q_i > 15 E, and by the triangle inequality j's computed score beats i's
    strictly at every query within the bounds: i can never be the argmax, not even on a tie.
    """
    return 16.0 * (state_dim + 4) * _UNIT_ROUNDOFF * (value_bound + lipschitz * distance_bound) * 1.01
