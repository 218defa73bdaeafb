"""What a trajectory's checksum covers is exactly what the file gives back: any finite arrays, signed zeros and
subnormals included, are stored, read and verified; a file from before that, whose checksum saw a -0.0 the file
keeps as 0.0, verifies (and says so) instead of reading as damaged; real damage still fails."""

from __future__ import annotations

import hashlib
import sqlite3
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from npp_ros.policy.dataset import Trajectory
from npp_ros.run.records import RunFileError
from npp_ros.run.seal import write_seal
from npp_ros.run.store import RunStore
from npp_ros.run.trajectory_checksum import SignedZeroChecksum, trajectory_digest
from tests.test_storage import META, row

FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64) | st.sampled_from([0.0, -0.0, 5e-324, -5e-324])


@st.composite
def trajectories(draw: st.DrawFn) -> Trajectory:
    steps = draw(st.integers(1, 6))
    states = draw(arrays(np.float64, (steps, META.state_dim), elements=FINITE))
    actions = draw(arrays(np.float64, (steps, META.action_dim), elements=FINITE))
    values = draw(arrays(np.float64, (steps,), elements=FINITE))
    gains = draw(st.none() | arrays(np.float64, (steps, META.action_dim, META.state_dim), elements=FINITE))
    return Trajectory(states, actions, values, gains=gains)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(stored=st.lists(trajectories(), min_size=1, max_size=3))
def test_any_finite_arrays_read_back_bit_for_bit_or_as_the_values_their_digest_is_of(
    stored: list[Trajectory], tmp_path_factory: pytest.TempPathFactory
) -> None:
    path = tmp_path_factory.mktemp("exact") / "run.sqlite"
    with RunStore.create(path, META) as store:
        for k, traj in enumerate(stored):
            store.record_episode(row(k, k, 0), traj)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no file written now needs the signed-zero reading
        with RunStore.open(path) as store:
            data = store.load_dataset()
    for k, traj in enumerate(stored):
        back = data.trajectory(k)
        pairs = [(traj.states, back.states), (traj.actions, back.actions), (traj.values, back.values)]
        if traj.gains is not None:
            pairs.append((traj.gains, back.gains))
        for written, read in pairs:
            # Bit for bit, but for the sign of a zero, which SQLite does not keep (the digest is of +0.0).
            assert (np.asarray(written) + 0.0).tobytes() == np.asarray(read).tobytes()
        assert trajectory_digest(back) == trajectory_digest(traj)


def old_digest(traj: Trajectory) -> str:
    """The checksum a writer from before took: the arrays' bytes as they were in memory, -0.0 included."""
    h = hashlib.sha256()
    for arr in (traj.states, traj.actions, traj.values, traj.gains):
        if arr is not None:
            h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
    return h.hexdigest()


def written_by_an_older_writer(path: Path, traj: Trajectory) -> None:
    with RunStore.create(path, META) as store:
        store.record_episode(row(0, 0, 0), traj)
    with sqlite3.connect(path) as conn:  # as it was: the checksum of the array in memory; the seal then taken over it
        conn.execute("UPDATE trajectories SET sha256 = ? WHERE id = 0", (old_digest(traj),))
        write_seal(conn)


def gained(gains: np.ndarray) -> Trajectory:
    rng = np.random.default_rng(3)
    steps = gains.shape[0]
    return Trajectory(rng.normal(size=(steps, 4)), rng.normal(size=(steps, 1)), rng.normal(size=steps), gains=gains)


@pytest.mark.parametrize("negative", [1, 2])
def test_an_older_file_whose_checksum_saw_a_negative_zero_gain_verifies_and_says_so(
    tmp_path: Path, negative: int
) -> None:
    """The case of two outside runs that could not be read: a feedback gain of -0.0 among ordinary zeros."""
    gains = np.random.default_rng(1).normal(size=(40, 1, 4))
    gains[5:25, 0, 1] = 0.0  # an actuator at its limit: zero gains
    gains[12, 0, 1] = -0.0
    if negative == 2:
        gains[30, 0, 2] = -0.0
    traj = gained(gains)
    assert old_digest(traj) != trajectory_digest(traj)
    written_by_an_older_writer(tmp_path / "run.sqlite", traj)
    with RunStore.open(tmp_path / "run.sqlite") as store:
        with pytest.warns(SignedZeroChecksum, match=f"trajectory 0's checksum was taken before {negative} of its -0.0"):
            data = store.load_dataset()
    np.testing.assert_array_equal(data.trajectory(0).gains, gains)


def test_an_older_file_with_a_changed_number_beside_its_zeros_is_still_damage(tmp_path: Path) -> None:
    gains = np.zeros((30, 1, 4))
    gains[3, 0, 0] = -0.0
    traj = gained(gains)
    written_by_an_older_writer(tmp_path / "run.sqlite", traj)
    with sqlite3.connect(tmp_path / "run.sqlite") as conn:
        conn.execute("UPDATE points SET s_0 = s_0 + 1e-12 WHERE trajectory = 0 AND step = 4")
        write_seal(conn)
    with RunStore.open(tmp_path / "run.sqlite") as store:
        with pytest.raises(RunFileError, match="trajectory 0 fails its SHA-256 check"):
            store.load_dataset()
