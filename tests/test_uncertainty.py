"""Model uncertainty in the core: the set a task declares, the robot each episode draws, that robot as the plant's
model, the privileged expert planning on it, and a run that records its robots and names its set."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from npp_ros.cli import learn
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.nominal_plan import REFERENCE, nominal_plan_returns, tracked_on_robot
from npp_ros.run.read import read_run
from npp_ros.run.records import RunFileError
from npp_ros.run.setup import NominalPlanExpert, PrivilegedExpert, build_config, build_loop
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, control_space, get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import (
    NOMINAL,
    SWINGUP_UNCERTAINTY,
    Robot,
    RobotEffects,
    ScaleRange,
    UncertaintySet,
    as_robot,
)

PENDULUM = "pendulum_swingup"
CARTPOLE = "cartpole_swingup"  # its reward is smooth: short episodes earn something
LIPSCHITZ = LipschitzConstant(50.0, "user")


@pytest.fixture(scope="module")
def pendulum_set() -> UncertaintySet:
    return SWINGUP_UNCERTAINTY.resolved(get_task(PENDULUM).make_plant(0).physics.model)


def test_a_set_names_every_element_it_scales_and_round_trips_through_its_record(pendulum_set: UncertaintySet) -> None:
    assert [(s.parameter, s.names) for s in pendulum_set.scales] == [
        ("mass", ("pole",)),
        ("gear", ("torque",)),
        ("damping", ("hinge",)),
    ]
    assert UncertaintySet.from_record(pendulum_set.record()) == pendulum_set
    assert "mass of pole x [0.8, 1.2]" in pendulum_set.describe()
    assert UncertaintySet().record() == "" and UncertaintySet.from_record("").empty


def test_bad_sets_are_refused_naming_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="unknown uncertain parameter 'stiffness'"):
        ScaleRange("stiffness", 0.5, 2.0)
    with pytest.raises(ValueError, match=r"0 < low <= high"):
        ScaleRange("mass", 1.2, 0.8)
    with pytest.raises(ValueError, match=r"body 'arm'.*its bodys: pole"):
        UncertaintySet((ScaleRange("mass", 0.8, 1.2, ("arm",)),)).resolved(
            get_task(PENDULUM).make_plant(0).physics.model
        )
    with pytest.raises(ValueError, match="action_delay"):
        UncertaintySet(action_delay=-1)


def test_each_episode_draws_its_own_robot_from_the_seed_and_episode_only(pendulum_set: UncertaintySet) -> None:
    first = [pendulum_set.draw(3, k) for k in range(50)]
    assert first == [pendulum_set.draw(3, k) for k in range(50)]  # reproducible, in any order
    assert pendulum_set.draw(3, 7) != pendulum_set.draw(4, 7)
    for robot in first:
        assert pendulum_set.contains(robot) == []
        assert Robot.from_record(robot.record()) == robot
    delays = {robot.action_delay for robot in first}
    assert delays == {0, 1}
    masses = np.array([dict(((p, n), f) for p, n, f in robot.scales)["mass", "pole"] for robot in first])
    assert 0.8 <= masses.min() < 0.9 and 1.1 < masses.max() <= 1.2
    outside = Robot((("mass", "pole", 1.3),), action_delay=2)
    assert pendulum_set.contains(outside) == [
        "mass of pole: x1.3 lies outside [0.8, 1.2]",
        "action delay 2 exceeds 1",
    ]


def test_widening_scales_the_distance_from_the_nominal_model(pendulum_set: UncertaintySet) -> None:
    half = pendulum_set.widened(0.5)
    assert [(s.low, s.high) for s in half.scales] == [(0.9, 1.1), (0.9, 1.1), (0.75, 1.25)]
    assert pendulum_set.widened(0).empty


def test_a_robot_is_the_plants_model_inside_the_block_and_nominal_after_it(pendulum_set: UncertaintySet) -> None:
    plant = get_task(PENDULUM).make_plant(0)
    twin = plant.clone()  # shares the model: sees the robot too
    fingerprint, model = plant.model_sha256(), plant.physics.model
    mass, inertia, gear = model.body_mass.copy(), model.body_inertia.copy(), model.actuator_gear[:, 0].copy()
    robot = Robot((("mass", "pole", 1.2), ("gear", "torque", 0.8), ("damping", "hinge", 1.5)))
    with as_robot(plant, robot):
        assert model.body_mass[1] == pytest.approx(1.2 * mass[1])
        assert np.allclose(model.body_inertia[1], 1.2 * inertia[1])
        assert twin.physics.model.actuator_gear[0, 0] == pytest.approx(0.8 * gear[0])
        assert plant.model_sha256() != fingerprint
    assert plant.model_sha256() == fingerprint and np.array_equal(model.body_mass, mass)


def test_a_heavier_weaker_robot_swings_differently_under_the_same_commands() -> None:
    plant = get_task(PENDULUM).make_plant(0)
    pump = lambda x: np.array([1.0 if x[1] >= 0 else -1.0])  # noqa: E731  # a bang-bang energy pump
    s0 = np.array([0.3, 0.0])
    nominal = rollout(plant, pump, s0, 60)
    heavy = rollout(plant, pump, s0, 60, Robot((("mass", "pole", 1.2), ("gear", "torque", 0.8))))
    again = rollout(plant, pump, s0, 60)
    assert np.array_equal(nominal.states, again.states)  # the plant is nominal again
    assert np.abs(heavy.states[-1] - nominal.states[-1]).max() > 1e-2


def test_a_delayed_robot_applies_each_command_one_step_late_and_noise_is_read_not_stepped() -> None:
    effects = RobotEffects(Robot(action_delay=1), 1)
    applied = [effects.command(np.array([u])) for u in (1.0, 2.0, 3.0)]
    assert [float(a[0]) for a in applied] == [0.0, 1.0, 2.0]
    noisy = RobotEffects(Robot(state_noise=0.1, noise_seed=5), 1)
    again = RobotEffects(Robot(state_noise=0.1, noise_seed=5), 1)
    state = np.zeros(2)
    read = noisy.observe(state)
    assert np.array_equal(read, again.observe(state)) and not np.array_equal(read, state)
    assert np.array_equal(state, np.zeros(2))
    assert RobotEffects(NOMINAL, 1).observe(state) is state


def test_the_privileged_expert_plans_on_the_episodes_robot(pendulum_set: UncertaintySet) -> None:
    """Its answer's actions, replayed on the robot's model, give its states; on the nominal model they do not."""
    task = get_task(PENDULUM)
    expert = task.make_expert(0, 80, ExpertOptions(max_iterations=5))
    robot = Robot((("mass", "pole", 1.2), ("gear", "torque", 0.8), ("damping", "hinge", 1.5)))
    s0 = task.initial_state(0, 0)
    answer = PrivilegedExpert(expert).trajectory(s0, robot=robot)
    plant = task.make_plant(0)
    actions = iter(answer.actions)
    replayed = rollout(plant, lambda _x: next(actions), s0, len(answer.actions), Robot(robot.scales)).states
    assert np.allclose(replayed, answer.states, atol=1e-8)
    actions = iter(answer.actions)
    on_nominal = rollout(plant, lambda _x: next(actions), s0, len(answer.actions)).states
    assert not np.allclose(on_nominal, answer.states, atol=1e-3)
    assert expert.plant.model_sha256() == plant.model_sha256()  # the expert's model is nominal again


def test_the_nominal_expert_plans_on_the_nominal_model_and_its_answer_is_that_plan_run_on_the_robot() -> None:
    """On the nominal robot the tracked plan is the plan itself; on another, the answer is a true rollout there
    (its actions replayed on that robot give its states and its return) and differs from the plan."""
    task = get_task(PENDULUM)
    expert = task.make_expert(0, 80, ExpertOptions(max_iterations=5))
    config = build_config(PENDULUM, 0, LIPSCHITZ, 130.0, horizon=80, uncertainty=1.0, expert_model="nominal")
    oracle = build_loop(config, expert).oracle
    assert isinstance(oracle, NominalPlanExpert)
    s0 = task.initial_state(0, 0)
    plan = expert.trajectory(s0)
    same = oracle.trajectory(s0, robot=NOMINAL)
    assert np.array_equal(same.states, plan.states) and np.array_equal(same.actions, plan.actions)
    assert same.expert_return == plan.expert_return
    robot = Robot((("mass", "pole", 1.2), ("gear", "torque", 0.8), ("damping", "hinge", 1.5)), action_delay=1)
    answer = oracle.trajectory(s0, robot=robot)
    assert not np.allclose(answer.states, plan.states, atol=1e-3)
    assert answer.gains is not None and plan.gains is not None and np.array_equal(answer.gains, plan.gains)
    plant = task.make_plant(0)
    actions = iter(answer.actions)
    replayed = rollout(plant, lambda _x: next(actions), s0, len(answer.actions), Robot(robot.scales))
    assert np.array_equal(replayed.states, answer.states)  # no delay: an answer runs on the robot's physics only
    assert replayed.total_return == pytest.approx(answer.expert_return, abs=1e-9)
    assert expert.plant.model_sha256() == plant.model_sha256()  # the expert never saw the robot


def test_a_nominal_expert_run_records_it_names_it_in_its_certificate_and_cannot_resume_as_another(
    tmp_path: Path,
) -> None:
    from npp_ros.certificate.authoring import over_robots

    task = get_task(PENDULUM)
    expert = task.make_expert(0, 60, ExpertOptions(max_iterations=3))
    nominal = build_config(PENDULUM, 0, LIPSCHITZ, 130.0, horizon=60, uncertainty=1.0, expert_model="nominal")
    privileged = replace(nominal, expert_model="robot")
    loop = build_loop(nominal, expert, store_path=tmp_path / "run.sqlite")
    loop.run(2)
    assert loop.store is not None
    loop.store.close()
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert store.metadata.expert_model == "nominal"
    run = read_run(tmp_path)
    assert run.expert_model == "nominal" and run.robots == UncertaintySet.from_record(nominal.uncertainty)
    with pytest.raises(RunFileError, match="expert_model: file has 'nominal'"):
        build_loop(privileged, expert, store_path=tmp_path / "run.sqlite")
    statement = over_robots("P_(s0~rho)[V - R <= 130] >= 0.9.", "mass x", REFERENCE["nominal"])
    assert "planning on the task's nominal model, its plan run on each episode's robot" in statement
    with pytest.raises(ValueError, match="expert model must be one of robot, nominal"):
        build_config(PENDULUM, 0, LIPSCHITZ, 130.0, uncertainty=1.0, expert_model="teacher")
    with pytest.raises(ValueError, match="expert model nominal needs a set of robots"):
        build_config(PENDULUM, 0, LIPSCHITZ, 130.0, expert_model="nominal")


def test_a_held_out_check_against_the_nominal_expert_runs_its_plans_on_the_drawn_robots() -> None:
    task = get_task(PENDULUM)
    horizon = 150  # long enough to reach the top from s0 0 on the model
    expert = task.make_expert(0, horizon, ExpertOptions(max_iterations=3))
    plant = task.make_plant(0)
    states = np.array([task.initial_state(0, k) for k in range(2)])
    robots = [Robot((("gear", "torque", 0.8),)), Robot((("damping", "hinge", 1.5),))]
    nominal = nominal_plan_returns(expert, plant, states, horizon, robots)
    privileged = task.expert_returns(expert, plant, states, horizon, robots=robots)
    on_model = task.expert_returns(expert, plant, states, horizon)
    space = control_space(plant)
    for k, s0 in enumerate(states):
        tracked = tracked_on_robot(plant, expert.trajectory(s0, horizon), s0, robots[k], space, window=True)
        assert nominal[k] == tracked.expert_return
    # the weaker motor: a plan for the model earns less on it than a plan made for it, which earns less than on
    # the model itself
    assert nominal[0] < privileged[0] < on_model[0]


def test_a_run_under_uncertainty_records_its_set_and_each_episodes_robot_and_resumes_them(tmp_path: Path) -> None:
    task = get_task(PENDULUM)
    expert = task.make_expert(0, 60, ExpertOptions(max_iterations=3))
    config = build_config(PENDULUM, 0, LipschitzConstant(50.0, "user"), 130.0, horizon=60, uncertainty=1.0)
    exact = build_config(PENDULUM, 0, LipschitzConstant(50.0, "user"), 130.0, horizon=60)
    assert config.uncertainty and not exact.uncertainty
    loop = build_loop(config, expert, store_path=tmp_path / "run.sqlite")
    loop.run(3)
    robots = UncertaintySet.from_record(config.uncertainty)
    assert [row.robot for row in loop.rows] == [robots.draw(0, k).record() for k in range(3)]
    assert [row.initial_state for row in loop.rows] == [tuple(task.initial_state(0, k)) for k in range(3)]
    assert loop.store is not None
    loop.store.close()
    resumed = build_loop(config, expert, store_path=tmp_path / "run.sqlite")
    assert [row.robot for row in resumed.rows] == [row.robot for row in loop.rows]
    assert resumed.store is not None
    resumed.store.close()
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert json.loads(str(store.metadata.uncertainty))["action_delay"] == 1
    with pytest.raises(RunFileError, match="uncertainty: file has"):  # the same folder, the exact model: another run
        build_loop(exact, expert, store_path=tmp_path / "run.sqlite")


def test_tasks_that_cannot_draw_a_robot_are_refused_saying_why() -> None:
    with pytest.raises(ValueError, match="declares nothing uncertain"):
        build_config("lqr_2_1", 0, LipschitzConstant(50.0, "user"), 50.0, uncertainty=1.0)
    with pytest.raises(ValueError, match="finite and >= 0"):
        build_config(PENDULUM, 0, LipschitzConstant(50.0, "user"), 130.0, uncertainty=-1.0)


def test_npp_learn_names_the_set_in_its_certificate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A tiny epsilon-free run cannot certify in a test's time; the certificate's words are checked on the author."""
    from npp_ros.certificate.authoring import over_robots, robot_assumptions
    from npp_ros.certificate.certifier import CertificationSpec

    text = over_robots("With probability at least 0.9, P_(s0~rho)[V - R <= 130] >= 0.9 for the policy.", "mass x")
    assert "P_((s0, theta)~rho x Theta)[V - R <= 130]" in text and "Theta, the robots this covers: mass x" in text
    spec = CertificationSpec("i", 130.0, 0.9, 0.1, LipschitzConstant(50.0, "user"), None, certify="rollout")
    assert any("NOT checked" in item for item in robot_assumptions(spec, "mass x"))
    code = learn.main(
        [
            "--task",
            PENDULUM,
            "--seed",
            "0",
            "--uncertainty",
            "1",
            "--max-episodes",
            "2",
            "--horizon",
            "40",
            "--evaluate",
            "0",
            "--run-dir",
            str(tmp_path),
        ],
    )
    assert code == 1  # not certified in 2 episodes
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert all(row.robot for row in store.episodes())


# ----------------------------------------------------------------------------- task files
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pendulum" / "task.toml"


def task_file_with(tmp_path: Path, table: str) -> Path:
    """The pendulum example's file with its [uncertainty] table replaced by ``table``, beside its model."""
    text = EXAMPLE.read_text().split("\n[uncertainty]")[0] + "\n" + table
    (tmp_path / "pendulum.xml").write_text((EXAMPLE.parent / "pendulum.xml").read_text())
    path = tmp_path / "task.toml"
    path.write_text(text)
    return path


def test_the_pendulum_example_declares_the_swing_ups_set() -> None:
    from npp_ros.tasks.task_file.loader import load_task_file

    task = load_task_file(str(EXAMPLE))
    assert task.uncertainty.describe().startswith("mass of pole x [0.8, 1.2]; gear of torque x [0.8, 1.2]")
    assert task.uncertainty.action_delay == 1


def test_a_task_files_named_elements_and_bad_keys(tmp_path: Path) -> None:
    from npp_ros.tasks.task_file.loader import load_task_file
    from npp_ros.tasks.task_file.reader import TaskFileError

    table = '[uncertainty]\ngear = { range = [0.9, 1.1], names = ["torque"] }\nstate_noise = 0.01\n'
    task = load_task_file(str(task_file_with(tmp_path, table)))
    assert [(s.parameter, s.names, s.low) for s in task.uncertainty.scales] == [("gear", ("torque",), 0.9)]
    assert task.uncertainty.state_noise == 0.01
    for bad, problem in [
        ("stiffness = [1, 2]", "uncertainty.stiffness: unknown key"),
        ("mass = [1.2, 0.8]", "uncertainty.mass: is empty"),
        ("mass = [0, 1.2]", "uncertainty.mass: a scale must be > 0"),
        ("action_delay = 0.5", "uncertainty.action_delay: must be a whole number"),
        ('mass = { range = [0.8, 1.2], names = ["arm"] }', "uncertainty: mass names body 'arm'"),
        ("gear = { names = [] }", "uncertainty.gear: a table needs range"),
    ]:
        with pytest.raises(TaskFileError, match=re.escape(problem)):
            load_task_file(str(task_file_with(tmp_path, f"[uncertainty]\n{bad}\n")))


def test_a_held_out_check_of_a_claim_over_robots_draws_both_and_rolls_each_out_on_its_robot() -> None:
    from npp_ros.policy.dataset import Dataset
    from npp_ros.run.held_out import HELD_OUT_EPISODES, check_policy, held_out_robots
    from npp_ros.run.setup import policy_for

    config = build_config(CARTPOLE, 0, LipschitzConstant(50.0, "user"), 130.0, horizon=40, uncertainty=1.0)
    robots = held_out_robots(config.uncertainty, 0, 3)
    assert held_out_robots("", 0, 3) is None
    assert robots == [UncertaintySet.from_record(config.uncertainty).draw(0, HELD_OUT_EPISODES + k) for k in range(3)]
    task = get_task(CARTPOLE)
    expert = task.make_expert(0, 40, ExpertOptions(max_iterations=3))
    data = Dataset(4, 1)
    data.append(expert.trajectory(task.initial_state(0, 0), 40))
    policy = policy_for(data, config.spec, CARTPOLE, 0)
    states = np.array([task.initial_state(5, k) for k in range(3)])
    kwargs = {"epsilon": 130.0, "p": 0.9, "delta": 0.1, "against_expert": True}
    on_robots = check_policy(policy, task, task.make_plant(0), expert, states, 40, robots=robots, **kwargs)
    nominal = check_policy(policy, task, task.make_plant(0), expert, states, 40, **kwargs)
    assert on_robots.states == nominal.states == 3
    assert on_robots.gap_max != nominal.gap_max  # other robots, other returns
    assert expert.plant.model_sha256() == task.make_plant(0).model_sha256()


# ----------------------------------------------------------------------------- the success claim
def test_the_success_claim_certifies_a_policy_that_holds_the_pendulum_with_one_expert_call(tmp_path: Path) -> None:
    """Starts near upright on robots from the swing-ups' set: the feedback policy of one answer holds every one, so
    the streak certifies P[success] >= p and the expert is asked only where the data must grow (once: no data)."""
    text = EXAMPLE.read_text()
    text = text.replace("hinge = { position = [-3.14159, 3.14159] }", "hinge = { position = [-0.05, 0.05] }")
    text = text.replace("horizon = 1000 ", "horizon = 100  ").replace("last_seconds = 1.0", "last_seconds = 0.5")
    (tmp_path / "pendulum.xml").write_text((EXAMPLE.parent / "pendulum.xml").read_text())
    (tmp_path / "task.toml").write_text(text)
    name = str(tmp_path / "task.toml")
    task = get_task(name)
    expert = task.make_expert(0, 100)
    config = build_config(
        name, 0, LipschitzConstant(50.0, "user"), 130.0, horizon=100, certify="success", policy="feedback",
        uncertainty=1.0,
    )  # fmt: skip
    loop = build_loop(config, expert)
    result = loop.run(60)
    assert result.certificate is not None
    assert result.oracle_calls == 1 and result.episodes == 1 + config.spec.streak_required(1)
    assert all(row.policy_success for row in result.rows[1:])
    statement = result.certificate.statement
    assert "P_((s0, theta)~rho x Theta)[the policy's rollout from s0 meets the task's success criterion] >= 0.9" in (
        statement
    )
    assert "the pole within 8 degrees of upright" in statement and "claims nothing about" in statement
    assert result.certificate.proven
    assert not any("L bounds" in item for item in result.certificate.assumptions)
    from npp_ros.run.held_out import check_success, held_out_robots

    states = np.array([task.initial_state(9, k) for k in range(10)])
    robots = held_out_robots(config.uncertainty, 0, 10)
    held_out = check_success(loop.policy, task, task.make_plant(0), states, 100, p=0.9, delta=0.1, robots=robots)
    assert held_out.states == 10 and held_out.succeeded == 10 and not held_out.rejected


def test_the_success_claim_needs_a_criterion(tmp_path: Path) -> None:
    text = EXAMPLE.read_text()
    (tmp_path / "pendulum.xml").write_text((EXAMPLE.parent / "pendulum.xml").read_text())
    (tmp_path / "task.toml").write_text(text[: text.index("[success]")] + text[text.index("[uncertainty]") :])
    name = str(tmp_path / "task.toml")
    config = build_config(name, 0, LipschitzConstant(50.0, "user"), 50.0, horizon=50, certify="success")
    with pytest.raises(ValueError, match="certify=success judges the policy's own rollout"):
        build_loop(config, get_task(name).make_expert(0, 50))


def test_the_success_claims_progress_says_met_or_failed_not_a_gap_against_epsilon() -> None:
    from npp_ros.run.progress import checked_text

    assert checked_text(0.0, 130.0, "success") == "success       met"
    assert checked_text(1.0, 130.0, "success") == "success    FAILED"
    assert checked_text(12.5, 130.0, "oracle") == "checked    12.50 / eps 130"
    assert checked_text(float("inf"), 50.0, "rollout", "rollout") == "rollout      inf / eps 50"


def test_a_run_says_where_in_the_set_its_expert_failed() -> None:
    from npp_ros.tasks.uncertainty import where_expert_failed

    weak = Robot((("gear", "torque", 0.82), ("damping", "hinge", 1.4)), action_delay=1)
    strong = Robot((("gear", "torque", 1.15), ("damping", "hinge", 0.6)))
    assert where_expert_failed([weak, strong], [False, False]) == ""
    text = where_expert_failed([weak, strong], [True, False])
    assert text.startswith("the expert failed on 1 of 2 answers, on robots with gear of torque x[0.82, 0.82]")
    assert "(all answers x[0.82, 1.15])" in text and "damping of hinge x[1.40, 1.40]" in text and "delay 1" in text


def test_the_success_claims_statement_does_not_call_itself_relative_to_a_failing_expert() -> None:
    from npp_ros.certificate.authoring import MeasuredSuccess

    relative = MeasuredSuccess("upright", expert=(1, 10), policy=(9, 10))
    alone = MeasuredSuccess("upright", expert=(1, 10), policy=(9, 10), relative=False)
    assert "relative to its expert" in relative.sentence()
    assert "relative to its expert" not in alone.sentence() and "needs no expert" in alone.sentence()
