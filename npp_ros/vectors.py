"""The one check that a state or an action is usable: a flat vector of the expected length, all finite.

Every entry point that receives a vector from outside (a service request, a topic, a reset) calls
:func:`finite_vector`, so the rule and its wording live in one place.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.dataset import DatasetError, FloatArray

SHOWN_ENTRIES = 5  # non-finite entries named in a message; more would drown the reason


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
    return arr
