"""Each trajectory's checksum in the run file (``trajectories.sha256``): the SHA-256 of its numbers as the file
stores them, and, for a trajectory of an older file whose checksum saw a -0.0 that SQLite stores as 0.0, the search
for its signed zeros that verifies it all the same.
"""

from __future__ import annotations

import hashlib

import numpy as np

from npp_ros.policy.dataset import FloatArray, Trajectory


def _digest_arrays(trajectory: Trajectory) -> tuple[FloatArray, ...]:
    arrays = (trajectory.states, trajectory.actions, trajectory.values)
    return arrays if trajectory.gains is None else (*arrays, trajectory.gains)


def trajectory_digest(trajectory: Trajectory) -> str:
    """SHA-256 of the trajectory's numbers as the file stores them; a trajectory without gains has the digest older
    files recorded.

    SQLite keeps a REAL -0.0 as +0.0, so the digest is of each value plus 0.0 (which turns -0.0 into +0.0 and
    leaves every other finite number as it is): what is digested is exactly what is read back. Values are finite
    (Trajectory.validated), so no NaN payload reaches the file."""
    h = hashlib.sha256()
    for arr in _digest_arrays(trajectory):
        h.update((np.ascontiguousarray(arr, dtype="<f8") + 0.0).tobytes())
    return h.hexdigest()


# Files written before the digest was of stored values digested a -0.0 as itself. A trajectory of such a file whose
# digest fails is searched for the zeros that were negative: each one alone, and each pair up to this many zeros.
SIGNED_ZERO_PAIRS_UP_TO = 200


class SignedZeroChecksum(UserWarning):
    """A trajectory of an older file verified once its signed zeros were found (said, then read as stored)."""


def signed_zeros_behind(trajectory: Trajectory, digest: str) -> int | None:
    """How many of the trajectory's zeros, stored as +0.0, were -0.0 when an older writer took ``digest`` (1 or 2);
    None when no such reading of them gives ``digest`` (the trajectory is damaged)."""
    flat = np.concatenate([np.ascontiguousarray(a, dtype="<f8").ravel() + 0.0 for a in _digest_arrays(trajectory)])
    zeros = np.flatnonzero(flat == 0.0)

    def matches(*where: int) -> bool:
        flipped = flat.copy()
        flipped[list(where)] = -0.0
        return hashlib.sha256(flipped.tobytes()).hexdigest() == digest

    if any(matches(int(i)) for i in zeros):
        return 1
    if len(zeros) <= SIGNED_ZERO_PAIRS_UP_TO:
        for a in range(len(zeros)):
            if any(matches(int(zeros[a]), int(b)) for b in zeros[a + 1 :]):
                return 2
    return None
