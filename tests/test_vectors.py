"""finite_vector: the one rule for states and actions from outside, and its wording."""

from __future__ import annotations

import math

import numpy as np
import pytest

from npp_ros.dataset import DatasetError
from npp_ros.vectors import VectorError, finite_vector


def test_a_good_vector_comes_back_as_float64() -> None:
    out = finite_vector([1, 2, 3, 4], 4)
    assert out.dtype == np.float64 and out.tolist() == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ([], "state is empty; expected 4 entries (qpos then qvel)"),
        ([0.0, 1.0, 2.0], "state has 3 entries, expected 4 (qpos then qvel)"),
        ([[0.0, 1.0], [2.0, 3.0]], "state must be a flat vector of 4 entries (qpos then qvel), got shape (2, 2)"),
        ([0.0, math.nan, math.inf, 1.0], "state must be finite: state[1] = nan, state[2] = inf"),
        (["a", 1.0, 2.0, 3.0], "state is not a numeric vector"),
    ],
)
def test_a_bad_vector_is_refused_with_the_reason(values: object, message: str) -> None:
    with pytest.raises(VectorError) as info:
        finite_vector(values, 4, "state", "qpos then qvel")  # type: ignore[arg-type]
    assert message in str(info.value)
    assert isinstance(info.value, DatasetError) and isinstance(info.value, ValueError)
