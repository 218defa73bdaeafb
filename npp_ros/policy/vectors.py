"""The one check that a state or an action is usable: a flat vector of the expected length, all finite,
and small enough that distances to it can be computed.

Every entry point that receives a vector from outside (a service request, a topic, a reset) calls
:func:`finite_vector`, and the policy's queries call :func:`bounded`, so the rule and its wording
live in one place.

Why a magnitude limit: the bounds use |s - s_i|, a sum of squares. Past about 1.3e154 a square
overflows to inf, every distance is inf, every candidate scores -inf, and the greedy policy would
answer with the action of index 0 and V_lb = -inf: a wrong answer, not a refusal. Entries up to
MAX_MAGNITUDE keep every square below 1e301, so sums over any realistic dimension stay finite.
"""

from __future__ import annotations

import hashlib

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import DatasetError, FloatArray

SHOWN_ENTRIES = 5  # non-finite entries named in a message; more would drown the reason
MAX_MAGNITUDE = 1e150  # |entry| above this: distances to it overflow (see the module docstring)


class VectorError(DatasetError):
    """A state or action of the wrong length or with non-finite entries; the message says which."""


def finite_vector(values: ArrayLike, size: int, what: str = "state", layout: str = "") -> FloatArray:
    """``values`` as a float64 vector of ``size`` finite entries, or a VectorError naming the problem.

    ``what`` names the vector in the message ("state", "effort"); ``layout`` says what its entries
    are (e.g. "qpos then qvel of 2 joints of lqr_2_1"), so a caller knows what to send instead.
    """
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise VectorError(f"{what} is not a numeric vector: {exc}") from None
    detail = f" ({layout})" if layout else ""
    if arr.size == 0:
        raise VectorError(f"{what} is empty; expected {size} entries{detail}")
    if arr.ndim != 1:
        raise VectorError(f"{what} must be a flat vector of {size} entries{detail}, got shape {arr.shape}")
    if arr.size != size:
        raise VectorError(f"{what} has {arr.size} entries, expected {size}{detail}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        which = ", ".join(f"{what}[{i}] = {arr[i]}" for i in bad[:SHOWN_ENTRIES])
        raise VectorError(f"{what} must be finite: {which}")
    return bounded(arr, what)


def bounded(arr: FloatArray, what: str = "state") -> FloatArray:
    """``arr`` (finite, any shape) if every entry is within +-MAX_MAGNITUDE, else a VectorError naming them.

    A 2-D array is a batch: entries are named [row, column].
    """
    big = np.argwhere(np.abs(arr) > MAX_MAGNITUDE)
    if len(big):
        which = ", ".join(f"{what}[{', '.join(map(str, ix))}] = {arr[tuple(ix)]:g}" for ix in big[:SHOWN_ENTRIES])
        raise VectorError(
            f"{what} is too large to compare with the data: {which}; entries must be within "
            f"+-{MAX_MAGNITUDE:g} (beyond that the squared distances overflow and no bound can be computed)"
        )
    return arr


def state_digest(state: ArrayLike) -> str:
    """A short name for a state, the same in every process: the first 12 hex digits of the SHA-256 of its
    float64 bytes (logs name the states an expert computed from, so that repeats can be found)."""
    return hashlib.sha256(np.ascontiguousarray(state, dtype="<f8").tobytes()).hexdigest()[:12]
