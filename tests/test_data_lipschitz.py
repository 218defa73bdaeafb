"""L = 'data' is not set by pairs of nearly equal states, nor by values the continuation past the horizon decides.

Window values Q_t sum the rewards t .. t + H - 1, the last t of them after the horizon, under the continuation
(zero torque for a task file). From upright, a fall under zero torque is chaotic: two upright states 1e-10 apart
can carry values that differ by 1, a quotient of 1e10 that says nothing about the slope a policy meets.
"""

from __future__ import annotations

import numpy as np

from npp_ros.certificate.choices import DATA_PAIR_FLOOR, DATA_WITHIN
from npp_ros.policy.dataset import Dataset, Trajectory
from npp_ros.policy.lipschitz import steepest_pair
from npp_ros.run.setup import data_slope

H = 40


def answers(late_jump: float = 0.0, twin_gap: float = 0.0) -> Dataset:
    """Two answers along a line, values with slope 2 in the state; the second ends upright (the twin of the
    first's last state, ``twin_gap`` apart) with its last quarter's values off by ``late_jump``."""
    data = Dataset(2, 1)
    for k in range(2):
        x = np.linspace(0.0, 3.0, H) + 0.01 * k
        states = np.stack([x, np.zeros(H)], axis=1)
        values = 2.0 * x
        if k == 1:
            states[-1] = data.trajectory(0).states[-1] + [twin_gap, 0.0] if twin_gap else states[-1]
            values[-H // 4 :] += late_jump
        data.append(Trajectory(states, np.zeros((H, 1)), values))
    return data


def test_pairs_closer_than_the_floor_do_not_count() -> None:
    data_late = answers(late_jump=0.8, twin_gap=1.8e-10)
    assert steepest_pair(data_late, floor_share=0.0).slope > 1e9  # the old rule: any pair
    pair = steepest_pair(data_late, floor_share=DATA_PAIR_FLOOR)
    assert pair is not None and pair.distance >= pair.floor > 0 and pair.slope < 100
    plain = steepest_pair(answers(), floor_share=DATA_PAIR_FLOOR)
    assert plain is not None and abs(plain.slope - 2.0) < 1e-6  # the values' own slope
    assert "answer" in plain.describe() and "apart" in plain.describe()


def test_continued_values_count_only_on_steps_mostly_within_the_horizon() -> None:
    data = answers(late_jump=50.0)
    everything = data_slope(data, continued=False)
    within = data_slope(data, continued=True)
    assert everything is not None and everything.slope > 100  # a late step's value, set after the horizon
    assert within is not None and abs(within.slope - 2.0) < 1e-6
    last = int((1 - DATA_WITHIN) * H)
    assert max(within.first[1], within.second[1]) <= last and within.points == 2 * (last + 1)
