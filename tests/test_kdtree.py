"""The kd-tree index returns exactly the brute force's values and indices, ties and growth included."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.policy.kdtree import BoundIndex, _build, _exceeds, _search
from npp_ros.tasks.builtin.lqr import LQRExpert, sample_initial_state


def grid_or_normal(rng: np.random.Generator, count: int, dim: int, grid: bool) -> tuple[np.ndarray, np.ndarray]:
    if grid:  # coarse integers: exact ties in values and distances are everywhere
        return rng.integers(-3, 4, size=(count, dim)).astype(float), rng.integers(0, 5, size=count).astype(float)
    return rng.normal(size=(count, dim)), 3.0 * rng.normal(size=count)


def assert_same_as_brute_force(index: BoundIndex, reference: NonparametricPolicy, queries: np.ndarray) -> None:
    for lower in (True, False):
        value, idx = index.search(queries, lower)
        ref = reference.lower(queries) if lower else reference.upper(queries)
        np.testing.assert_array_equal(idx, ref.index)
        assert np.array_equal(value, ref.value)  # bit for bit, not approximately


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("compress", [False, True])
def test_growing_dataset_matches_brute_force_after_every_append(seed: int, compress: bool) -> None:
    rng = np.random.default_rng(seed)
    dim, grid = 1 + seed % 5, seed % 2 == 0
    data = Dataset(dim, 1)
    L = 1.0 if grid else float(rng.uniform(0.1, 10.0))
    index = BoundIndex(data, L, compress=compress, tail_limit=int(rng.integers(1, 300)), leaf_size=1 + seed % 17)
    reference = NonparametricPolicy(data, L, index=False)
    empty = index.search(np.zeros((2, dim)), True)
    assert np.all(empty[0] == -np.inf) and np.all(empty[1] == -1)
    for step in range(25):
        count = int(rng.integers(1, 200))
        states, values = grid_or_normal(rng, count, dim, grid)
        data.append_arrays(states * (1 + step % 3), np.zeros((count, 1)), values)
        # near the data, and some far away (beyond the compressed trees' safe ball: brute force there)
        queries, _ = grid_or_normal(rng, 40, dim, grid)
        queries[::7] *= 50.0
        assert_same_as_brute_force(index, reference, queries)
    stats = index.stats()
    assert stats.points == len(data) and stats.indexed + stats.tail == len(data)
    assert stats.segments <= 1 + int(np.log2(len(data)))


def test_ties_go_to_the_smallest_index_inside_the_trees() -> None:
    data = Dataset(2, 1)
    # Many exact duplicates with equal values: every query ties between copies.
    base = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    data.append_arrays(np.tile(base, (500, 1)), np.zeros((2000, 1)), np.ones(2000))
    index = BoundIndex(data, 1.0, tail_limit=8, leaf_size=4)
    _, idx = index.search(np.array([[0.0, 0.0], [1.0, 1.0], [0.5, 0.5], [3.0, -2.0]]), True)
    np.testing.assert_array_equal(idx, [0, 3, 0, 1])
    assert_same_as_brute_force(
        index, NonparametricPolicy(data, 1.0, index=False), np.random.default_rng(0).normal(size=(50, 2))
    )


def test_lqr_trajectories_and_nearby_queries_match_brute_force() -> None:
    expert = LQRExpert("lqr_2_1", 0)
    rng = np.random.default_rng(1)
    data = Dataset(4, 1)
    for _ in range(6):
        data.append(expert.trajectory(sample_initial_state("lqr_2_1", rng)))
    queries = expert.trajectory(sample_initial_state("lqr_2_1", rng)).states[::10]
    queries = np.concatenate([queries, queries + 1e-3 * rng.normal(size=queries.shape), data.states[::97]])
    for L in (50.0, expert.analytic_lipschitz().value):
        index = BoundIndex(data, L, tail_limit=512)
        assert_same_as_brute_force(index, NonparametricPolicy(data, L, index=False), queries)


def test_policy_uses_the_index_and_agrees_with_brute_force_single_and_batch() -> None:
    rng = np.random.default_rng(3)
    data = Dataset(3, 2)
    data.append_arrays(rng.normal(size=(5000, 3)), rng.normal(size=(5000, 2)), rng.normal(size=5000))
    fast, slow = NonparametricPolicy(data, 2.5), NonparametricPolicy(data, 2.5, index=False)
    assert fast.index is not None and slow.index is None
    queries = rng.normal(size=(64, 3))
    for name in ("v_lb", "v_ub", "gap", "greedy_index", "act"):
        batch = getattr(fast, name)(queries)
        np.testing.assert_array_equal(batch, getattr(slow, name)(queries))
        for k in (0, 17, 63):
            np.testing.assert_array_equal(getattr(fast, name)(queries[k]), batch[k])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    dim=st.integers(1, 6),
    size=st.integers(1, 400),
    grid=st.booleans(),
    lipschitz=st.sampled_from([0.25, 1.0, 3.0, 50.0]),
    leaf=st.integers(1, 20),
    compress=st.booleans(),
)
def test_randomised_datasets_match_brute_force(
    seed: int, dim: int, size: int, grid: bool, lipschitz: float, leaf: int, compress: bool
) -> None:
    rng = np.random.default_rng(seed)
    data = Dataset(dim, 1)
    states, values = grid_or_normal(rng, size, dim, grid)
    data.append_arrays(states, np.zeros((size, 1)), values)
    index = BoundIndex(data, lipschitz, compress=compress, tail_limit=1 + size // 3, leaf_size=leaf)
    queries = np.concatenate([grid_or_normal(rng, 30, dim, grid)[0], states[: min(size, 10)]])
    assert_same_as_brute_force(index, NonparametricPolicy(data, lipschitz, index=False), queries)


@pytest.mark.slow  # disassembles the compiled kernels
def test_kernels_contain_no_fused_multiply_add() -> None:
    """An FMA rounds once where the brute force rounds twice: it would break bit-for-bit equality."""
    data = Dataset(3, 1)
    data.append_arrays(np.random.default_rng(0).normal(size=(300, 3)), np.zeros((300, 1)), np.arange(300.0))
    index = BoundIndex(data, 1.0, tail_limit=50)
    index.search(np.zeros((1, 3)), True)
    for kernel in (_search, _exceeds, _build):
        assert kernel.signatures, kernel
        fresh = numba.njit(kernel.py_func)  # uncached, so its machine code can be inspected
        for signature in kernel.signatures:
            fresh.compile(signature)
            asm = fresh.inspect_asm(signature)
            assert "sqrt" in asm or kernel is _build
            assert not any(op in asm for op in ("vfmadd", "vfnmadd", "vfmsub", "vfnmsub")), kernel


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="Lipschitz"):
        BoundIndex(Dataset(1, 1), 0.0)
    with pytest.raises(ValueError, match="leaf_size"):
        BoundIndex(Dataset(1, 1), 1.0, leaf_size=0)
