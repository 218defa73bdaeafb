"""A robot identified from its own motion through real MuJoCo, and the certified policy checked at it.

Short recordings (a few seconds) keep these fast: the measurement over the pendulum's set at 10 s each is
scripts/identify_robots.py's (results/identification).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from npp_ros.cli.identify import main as npp_identify
from npp_ros.cli.learn import main as learn
from npp_ros.identification.check import check_before_move, clopper_pearson_lower, successes_at
from npp_ros.identification.excitation import multisine
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import Recording, record_motion
from npp_ros.run.evaluation import policy_rollouts
from npp_ros.run.read import read_run
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot, ScaleRange, UncertaintySet

PENDULUM = get_task("pendulum_swingup")
HANGING = np.array([math.pi, 0.0])


def pump(state: np.ndarray) -> np.ndarray:
    """Energy in with the velocity's sign, below the torque limit so that the excitation is never clipped away."""
    return np.array([0.6 * np.sign(state[1])])


def pendulum_robot(mass: float, gear: float, damping: float, delay: int) -> Robot:
    return Robot((("mass", "pole", mass), ("gear", "torque", gear), ("damping", "hinge", damping)), delay, 1e-3, 3)


def pendulum_recording(robot: Robot, seconds: float = 4.0) -> Recording:
    plant = PENDULUM.make_plant(0)
    excitation = multisine(plant, seconds)
    return record_motion(plant, robot, pump, HANGING, excitation.steps, excitation.apply)


def combination(found, label: str) -> tuple[float, float, float]:
    (c,) = [c for c in found.combinations if c.label == label]
    return c.value, c.low, c.high


@pytest.fixture(scope="module")
def corner():
    """The set's corner the prototype used: mass x1.2, gear x0.8, damping x1.5, one step late."""
    return identify(PENDULUM, pendulum_recording(pendulum_robot(1.2, 0.8, 1.5, 1)))


def test_the_corner_robot_is_identified_with_its_delay_and_what_its_motion_cannot_tell(corner) -> None:
    assert corner.delay == 1
    scores = {d.delay: d.score for d in corner.delays}
    assert set(scores) == {0, 1, 2, 3} and all(scores[1] < scores[d] - 1.0 for d in (0, 2, 3))  # clearly apart
    for label, true in (("gear[torque] / mass[pole]", 0.8 / 1.2), ("damping[hinge] / mass[pole]", 1.5 / 1.2)):
        value, low, high = combination(corner, label)
        assert abs(value / true - 1) < 0.03 and low <= true <= high, (label, value, low, high)
    (why,) = corner.unidentifiable  # mass, gear and damping scaled together: the same motion
    assert "mass[pole] x c, gear[torque] x c, damping[hinge] x c" in why and "scaled by c" in why
    assert corner.singular_values[-1] < 1e-5 * corner.singular_values[0] < corner.singular_values[1]
    # at the set's corner: the estimate may lie just beyond it, the intervals reach into it
    assert corner.verdict in ("inside", "near the edge") and corner.reaches
    record = json.loads(json.dumps(corner.record()))
    assert record["delay"] == 1 and len(record["combinations"]) == 2


def test_the_region_holds_the_estimate_and_the_corners_of_the_intervals(corner) -> None:
    region = corner.region()
    assert len(region) == 1 + 4 and region[0] == corner.estimate
    ratios = {(round(f["gear"] / f["mass"], 6), round(f["damping"] / f["mass"], 6))
              for f in ({p: v for p, _, v in robot.scales} for robot in region[1:])}  # fmt: skip
    gear, damping = (combination(corner, f"{p} / mass[pole]") for p in ("gear[torque]", "damping[hinge]"))
    assert ratios == {(round(g, 6), round(d, 6)) for g in gear[1:] for d in damping[1:]}
    assert all(robot.action_delay == 1 for robot in region)


def test_a_robot_outside_the_set_is_named_by_its_parameter_and_range() -> None:
    found = identify(PENDULUM, pendulum_recording(pendulum_robot(1.0, 0.6, 1.0, 0)))
    value, low, high = combination(found, "gear[torque] / mass[pole]")
    assert abs(value / 0.6 - 1) < 0.03 and low <= 0.6 <= high < 0.8 / 1.2 and found.delay == 0  # the set's least
    assert found.verdict == "outside" and not found.reaches
    assert any("gear[torque] / mass[pole]" in reason for reason in found.reasons)
    assert "outside" in found.summary() and "[0.8, 1.2]" in found.summary()


def test_a_late_robot_is_outside_by_its_delay() -> None:
    found = identify(PENDULUM, pendulum_recording(pendulum_robot(1.0, 1.0, 1.0, 2), seconds=3.0))
    assert found.delay == 2 and found.verdict == "outside"
    assert found.reasons == ("action delay 2 exceeds the set's 0..1 control steps",)


def test_masses_are_told_apart_where_springs_do_not_scale_with_them() -> None:
    """lqr_2_1's joints have springs, which no scale moves: every mass and the gear are then identifiable."""
    task = get_task("lqr_2_1")
    plant = task.make_plant(0)
    robots = UncertaintySet((ScaleRange("mass", 0.8, 1.2), ScaleRange("gear", 0.8, 1.2)))
    hidden = Robot((("mass", "body_0", 1.1), ("mass", "body_1", 0.9), ("gear", "motor_0", 1.15)), 0, 1e-3, 5)
    excitation = multisine(plant, 3.0, amplitude=5.0)
    recording = record_motion(plant, hidden, lambda x: np.zeros(1), [1.0, -0.5, 0.0, 0.0], excitation.steps,
                              excitation.apply)  # fmt: skip
    found = identify(task, recording, robots, max_delay=1)
    assert found.unidentifiable == () and found.delay == 0 and found.inside
    values = {c.label: c for c in found.combinations}
    for label, true in (("mass[body_0]", 1.1), ("mass[body_1]", 0.9), ("gear[motor_0]", 1.15)):
        assert abs(values[label].value / true - 1) < 0.02 and values[label].low <= true <= values[label].high


def test_streams_are_aligned_as_a_robot_applies_its_commands() -> None:
    """A command counts for the step after the last state before it; none yet: zero; a late one holds the last."""
    state_times = np.array([0.0, 0.02, 0.04, 0.06, 0.08])
    states = np.arange(10.0).reshape(5, 2)
    command_times = np.array([0.005, 0.025, 0.065, 0.066])  # answers to states 0 and 1, none to 2, two to 3
    commands = np.array([[1.0], [2.0], [4.0], [5.0]])
    recording = Recording.from_streams(state_times, states, command_times, commands, stamps=state_times + 10)
    np.testing.assert_array_equal(recording.commands[:, 0], [1.0, 2.0, 2.0, 5.0, 5.0])
    np.testing.assert_array_equal(recording.times, state_times + 10)
    early = Recording.from_streams(state_times, states, command_times + 0.03, commands)
    np.testing.assert_array_equal(early.commands[:, 0], [0.0, 1.0, 2.0, 2.0, 5.0])


def test_the_excitation_is_bounded_short_and_within_the_limits() -> None:
    plant = PENDULUM.make_plant(0)
    excitation = multisine(plant, 2.0, fraction=0.2, seed=4)
    assert excitation.steps == 100 and math.isclose(np.abs(excitation.signal).max(), 0.2)
    assert abs(excitation.signal[0, 0]) < 1e-12 and abs(excitation.signal[-1, 0]) < 1e-12  # faded in and out
    assert abs(excitation.signal.mean()) < 0.02 and not excitation.at(100).any() and not excitation.at(-1).any()
    sent = np.array([excitation.apply(t, [0.95]) for t in range(100)])
    assert sent.max() <= 1.0 and sent.min() >= 0.75 and (sent == 1.0).any()  # clipped at the actuator's limit
    np.testing.assert_array_equal(multisine(plant, 2.0, fraction=0.2, seed=4).signal, excitation.signal)
    with pytest.raises(ValueError, match="no limits"):
        multisine(get_task("lqr_2_1").make_plant(0), 2.0)


def test_clopper_pearson_lower_bound() -> None:
    assert clopper_pearson_lower(0, 10, 0.05) == 0.0
    assert math.isclose(clopper_pearson_lower(10, 10, 0.05), 0.05 ** (1 / 10))
    from scipy.stats import binom

    bound = clopper_pearson_lower(37, 50, 0.05)
    assert math.isclose(binom.sf(36, 50, bound), 0.05, rel_tol=1e-6)  # P(X >= 37 | bound) = delta exactly


@pytest.fixture(scope="module")
def lqr_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("identify") / "run"
    argv = ["--task", "lqr_2_1", "--seed", "0", "--max-episodes", "2", "--evaluate", "0"]
    learn([*argv, "--run-dir", str(run_dir)])
    return run_dir


def test_the_check_before_moving_refuses_a_robot_its_policy_fails_on(lqr_run: Path) -> None:
    """lqr_2_1's success: settled near 0 at the end. A motor of a hundredth cannot settle it; the nominal one can."""
    run = read_run(lqr_run)
    nominal = Robot((("gear", "motor_0", 1.0),))
    weak = Robot((("gear", "motor_0", 0.01),))
    check = check_before_move(run, [nominal], n=6, p=0.5, delta_g=0.05)
    assert check.accepted and check.points[0].successes == 6
    assert math.isclose(check.worst.lower, 0.05 ** (1 / 6))
    both = check_before_move(run, [nominal, weak], n=6, p=0.5, delta_g=0.05)
    assert not both.accepted and both.worst.robot == weak and both.worst.successes == 0
    assert both.points[0].lower == pytest.approx(0.025 ** (1 / 6))  # each point at delta_g / 2
    assert "must not move" in both.summary()


def test_npp_identify_reads_a_recording_and_prints_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], lqr_run: Path
) -> None:
    path = tmp_path / "robot.npz"
    pendulum_recording(pendulum_robot(1.0, 1.1, 0.8, 0), seconds=3.0).save(path)
    assert npp_identify([str(path), "--task", "pendulum_swingup", "--max-delay", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["identification"]
    assert out["delay"] == 0 and out["verdict"] == "inside"
    (gear,) = [c for c in out["combinations"] if c["label"] == "gear[torque] / mass[pole]"]
    assert abs(gear["value"] / 1.1 - 1) < 0.03
    assert npp_identify([str(path), "--task", "pendulum_swingup", "--check"]) == 2  # a check needs the run
    assert "--check needs --run" in capsys.readouterr().err
    assert npp_identify([str(path), "--run", str(lqr_run), "--check"]) == 2  # no set to place a robot in
    assert "certified on the exact model" in capsys.readouterr().err


def test_the_lockstep_rollouts_are_the_evaluations_one_at_a_time(lqr_run: Path) -> None:
    """The check's rollouts, all s0 of one robot at once, give the successes npp_ros.run.evaluation's rollouts give
    one robot per rollout, noise and delay included."""
    run = read_run(lqr_run)
    plant = run.task.make_plant(0)
    robot = Robot((("gear", "motor_0", 0.5), ("mass", "body_1", 1.2)), 1, 0.05, 0)
    states = np.array([run.task.sample_initial_state(np.random.default_rng(k)) for k in range(4)])
    met = successes_at(plant, run.policy, run.task.success, robot, states, 1000)
    drawn = [Robot(robot.scales, 1, 0.05, k) for k in range(4)]
    one_by_one = np.zeros(4)
    policy_rollouts(plant, run.policy, states, 1000, None, robots=drawn, met=one_by_one, criterion=run.task.success)
    np.testing.assert_array_equal(met, one_by_one == 1)
    assert 0 < met.sum() < 4  # some succeed, some do not: the comparison tells them apart


def test_a_window_of_motion_is_judged_outside_or_not_and_two_in_a_row_find_the_robot() -> None:
    """npp-deploy's window identification (npp_ros.identification.window): three seconds of a gear x0.6 robot's
    motion lie outside the pendulum's set, the nominal robot's do not; the window keeps its last seconds, is due once
    a second of motion, and finds the robot outside only when two windows in a row are."""
    from npp_ros.identification.window import MotionWindow, judge

    record = PENDULUM.uncertainty.record()
    verdicts = {}
    for name, robot in (("weak", pendulum_robot(1.0, 0.6, 1.0, 0)), ("nominal", pendulum_robot(1.0, 1.0, 1.0, 0))):
        motion = pendulum_recording(robot, 3.0)
        window = MotionWindow(seconds=3.0, every=1.0, in_a_row=2)
        due = None
        for t in range(len(motion)):
            window.add(float(motion.times[t]), motion.states[t], motion.commands[t])
            due = window.due() or due
        assert due is not None and window.due() is None  # once due, not again within the next second
        verdicts[name] = judge("pendulum_swingup", 0, record, *due)
        assert not window.found(verdicts[name])  # one window alone finds nothing
        assert window.found(verdicts[name]) == verdicts[name].outside
    assert verdicts["weak"].outside and "gear" in verdicts["weak"].said, verdicts["weak"]
    assert not verdicts["nominal"].outside, verdicts["nominal"]
    at_rest = np.tile(HANGING, (40, 1))  # no noise, no command: the motion tells nothing, and says no alarm
    assert not judge("pendulum_swingup", 0, record, np.arange(40) * 0.02, at_rest, np.zeros((40, 1))).outside
    late = pendulum_recording(Robot((), 2), 3.0)  # no noise: the nominal model two steps late reproduces it exactly
    found = judge("pendulum_swingup", 0, record, late.times, late.states, late.commands)
    assert found.outside and "delay 2" in found.said, found


def test_npp_deploy_runs_the_window_by_default_only_where_the_set_says_its_robots_read_exact_states() -> None:
    """monitor_window's default: the window where the set's reads are exact, none where the set declares noise (noise
    in the regressed states biases the fit, and robots of the set would be found outside); an asked value as asked."""
    from dataclasses import replace

    from npp_ros.identification.window import AUTO, WINDOW_S, window_seconds

    exact = PENDULUM.uncertainty
    assert exact.state_noise == 0 and window_seconds(AUTO, exact) == WINDOW_S
    noisy = replace(exact, state_noise=1e-3)
    assert window_seconds(AUTO, noisy) == 0.0
    assert window_seconds(3.0, noisy) == 3.0 and window_seconds(0.0, exact) == 0.0


def test_a_robot_come_to_rest_is_not_found_outside_for_a_delay_its_stillness_cannot_show() -> None:
    """A window of a robot of the set come to rest upright under the certified pendulum policy (2 s, 12 s into its
    motion; a robot drawn from the set, recorded with scripts/monitor_on_robot.py's starts): every delay reproduces
    its motion to rounding. The fit takes the smallest delay such a tie allows, never a delay outside the set
    picked by which rounding came out smallest (which found this robot outside)."""
    from npp_ros.identification.window import judge

    saved = np.load(Path(__file__).parent / "fixtures" / "pendulum_at_rest_window.npz")
    still = Recording(saved["times"], saved["states"], saved["commands"])
    found = identify("pendulum_swingup", still, PENDULUM.uncertainty)
    assert found.delay == 0 and found.verdict == "inside", found.summary()
    assert not judge("pendulum_swingup", 0, PENDULUM.uncertainty.record(), still.times, still.states,
                     still.commands).outside  # fmt: skip


def test_a_window_leaves_out_the_rows_whose_commands_went_out_late() -> None:
    """A command sent later than the window's least lag by more than late_after missed the step it answers: its row
    is left out, as a skipped state is; a robot clock offset shared by every row is no lateness."""
    from npp_ros.identification.window import MotionWindow

    window = MotionWindow(seconds=1.0, every=0.5, in_a_row=2, late_after=0.01)
    offset = 1000.0  # the robot's clock started elsewhere: every row shares it
    late = {20, 21, 35}
    for t in range(51):
        stamp = 0.02 * t
        window.add(stamp, np.array([stamp, 0.0]), np.array([0.1 * t]), offset + stamp + (0.015 if t in late else 0.002))
    due = window.due()
    assert due is not None and window.late == 3
    times, states, commands = due
    assert len(times) == 48 and not any(np.isclose(times, 0.02 * t).any() for t in late)
    assert np.array_equal(states[:, 0], times) and np.allclose(commands[:, 0], times * 5)
