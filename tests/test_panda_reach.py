"""The 7-joint Panda reaching task (examples/panda_reach): the model as shipped, the target in the state that
nothing moves, the warm start that holds the arm up, the offset's Hessian that lets iLQR converge, and
several success bands, each refusal naming its key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from npp_ros.deployment.commands import gravity_hold, safe_command
from npp_ros.deployment.joints import JointLayout, NoTarget
from npp_ros.deployment.robot_model import mjcf_fingerprint, model_mjcf
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.cost import TermCost
from npp_ros.tasks.task_file.loader import FilePlant, GravityHold, TaskFileError, target_origin

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "panda_reach"
ARM_JOINTS = 7


@pytest.fixture
def panda_dir(tmp_path: Path) -> Path:
    """A copy of the example to edit (the model stays where it is: the copy's file names it by path)."""
    text = (EXAMPLE / "task.toml").read_text().replace('model = "scene.xml"', f'model = "{EXAMPLE / "scene.xml"}"')
    (tmp_path / "task.toml").write_text(text)
    return tmp_path


def edited(task_dir: Path, old: str, new: str) -> str:
    path = task_dir / "task.toml"
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return str(path)


def test_the_panda_has_seven_torque_joints_and_a_target_in_its_state() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    assert (task.state_dim, task.action_dim) == (20, 7)
    plant = task.make_plant(0)
    assert plant.joint_names[:ARM_JOINTS] == [f"joint{i}" for i in range(1, 8)]
    assert plant.joint_names[ARM_JOINTS:] == ["target_x", "target_y", "target_z"]
    assert plant.action_high.tolist() == [80.0] * 5 + [12.0] * 2
    masses = plant.physics.model.body_mass
    assert [float(masses[plant.physics.model.body(f"link{i}").id]) for i in range(1, 8)] == [3, 3, 2, 2, 2, 1.5, 0.5]


def test_no_torque_moves_the_target() -> None:
    """The target's three slide joints are in no contact, held against gravity and driven by nothing."""
    task = get_task(str(EXAMPLE / "task.toml"))
    plant = task.make_plant(0)
    rng = np.random.default_rng(3)
    s0 = task.sample_initial_state(rng)
    plant.reset(s0)
    for _ in range(50):
        plant.step(rng.uniform(plant.action_low, plant.action_high))
    state = plant.state()
    assert np.array_equal(state[ARM_JOINTS:10], s0[ARM_JOINTS:10]) and not state[17:].any()


def test_the_gravity_warm_start_holds_the_arm_where_zero_torque_lets_it_fall() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    plant = task.make_plant(0)
    hold = GravityHold(plant.physics.model.ptr, plant.action_low, plant.action_high)
    s0 = task.sample_initial_state(np.random.default_rng(0))
    drift = {}
    for name, controller in (("hold", hold), ("zero", lambda _x: np.zeros(7))):
        plant.reset(s0)
        for _ in range(20):
            plant.step(controller(plant.raw_state()))
        drift[name] = float(np.max(np.abs(plant.state()[:ARM_JOINTS] - s0[:ARM_JOINTS])))
    assert drift["hold"] < 0.01 < 0.1 < drift["zero"], drift


def test_the_offset_hessian_has_the_offsets_rank_and_the_distances_gradient() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    definition = task.definition
    assert definition is not None and definition.cost_terms[0].hessian == "offset"
    model = FilePlant(definition).physics.model.ptr
    state = task.sample_initial_state(np.random.default_rng(1))[None, :]
    offset = TermCost(definition.cost_terms, model, definition.expert)
    scalar = TermCost(
        tuple(t.__class__(**{**t.__dict__, "hessian": "distance"}) for t in definition.cost_terms),
        model,
        definition.expert,
    )
    value, grad, hess = offset.state_terms(state)
    value_scalar, grad_scalar, hess_scalar = scalar.state_terms(state)
    assert value[0] == value_scalar[0] and np.allclose(grad, grad_scalar)
    arm = slice(0, ARM_JOINTS)
    assert np.linalg.matrix_rank(hess_scalar[0][arm, arm], tol=1e-9) == 1
    assert np.linalg.matrix_rank(hess[0][arm, arm], tol=1e-9) == 3


def test_the_expert_reaches_a_target_from_a_start_of_rho() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    assert task.success is not None
    s0 = task.sample_initial_state(np.random.default_rng(1))
    answer = task.make_expert(0, 150).trajectory(s0)
    assert task.success.met(answer.states)
    assert answer.gains is not None and answer.gains.shape == (150, 7, 20)


def test_two_success_bands_must_both_hold() -> None:
    """The hand near the target but moving fails the speed band; both bands are in the words."""
    task = get_task(str(EXAMPLE / "task.toml"))
    success = task.success
    assert success is not None and success.steps == 50
    assert "within [0, 0.02] m of each other and site hand moving at [0, 0.05] m/s" in success.describe()
    plant = task.make_plant(0)
    s0 = task.sample_initial_state(np.random.default_rng(2))
    plant.reset(s0)
    plant.physics.forward()
    hand = plant.physics.named.data.site_xpos["hand"].copy()
    still = s0.copy()
    still[ARM_JOINTS:10] = hand  # the target on the hand
    moving = still.copy()
    moving[10] = 0.5  # joint 1 turning at 0.5 rad/s sweeps the hand at more than 5 cm/s
    assert success.met(np.repeat(still[None], 50, axis=0))
    assert not success.met(np.repeat(moving[None], 50, axis=0))
    distance, speed = success.holds.bands  # type: ignore[attr-defined]
    assert speed.values(moving[None])[0] > 0.05 and distance.values(moving[None])[0] < 1e-9


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ('hessian = "offset"', 'hessian = "full"', "expert.terms[0].hessian: must be one of distance, offset"),
        ("margin = 0.3\n", 'margin = 0.3\nhessian = "offset"\n', "reward.terms[0].hessian: applies to a site_distance"),
        ("last_seconds = 0.5\n[[success]]", "last_seconds = 1.0\n[[success]]", "success[1].last_seconds: is 0.5 s"),
        ('speed = "hand"', 'speed = "elbow"', "success[1].speed: unknown site 'elbow'"),
        ('warm_start = "gravity"', 'warm_start = "hold"', "expert.warm_start: must be one of zero, gravity"),
    ],
)
def test_a_bad_key_is_refused_by_name(panda_dir: Path, old: str, new: str, expected: str) -> None:
    with pytest.raises(TaskFileError, match=expected.replace("[", r"\[").replace("]", r"\]")):
        get_task(edited(panda_dir, old, new))


def test_the_shipped_model_names_its_source_and_licence() -> None:
    """robosuite's Panda as published, its visual meshes left out (they change no physics), its MIT licence."""
    licence = (EXAMPLE / "panda" / "LICENSE").read_text()
    assert licence.startswith("MIT License")
    assert sorted(p.name for p in (EXAMPLE / "panda" / "meshes").iterdir()) == sorted(f"link{i}.stl" for i in range(8))
    assert sum(p.stat().st_size for p in (EXAMPLE / "panda").rglob("*")) < 1_500_000


def test_the_target_is_declared_and_said_in_the_stored_state() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    assert task.make_plant(0).target_joints == ("target_x", "target_y", "target_z")
    assert task.stored_state.endswith("target_x, target_y, target_z the target, at rest")
    assert target_origin(task.make_plant(0)).tolist() == [0.0, 0.0, 0.0]


def scene_copy(task_dir: Path, old: str, new: str) -> None:
    """The example's scene, edited, beside the task file (its meshes by a link to the example's)."""
    (task_dir / "panda").symlink_to(EXAMPLE / "panda")
    text = (EXAMPLE / "scene.xml").read_text()
    assert old in text, old
    (task_dir / "scene.xml").write_text(text.replace(old, new, 1))
    edited(task_dir, f'model = "{EXAMPLE / "scene.xml"}"', 'model = "scene.xml"')


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ('target = ["target_x", "target_y", "target_z"]', 'target = ["target_x", "target_y"]', "must name three"),
        ('target = ["target_x", "target_y", "target_z"]', 'target = ["joint1", "target_y", "target_z"]',
         "joint 'joint1' is not a slide"),
        ('target = ["target_x", "target_y", "target_z"]', 'target = ["target_y", "target_x", "target_z"]',
         "slides along [0.0, 1.0, 0.0], not the world's x axis"),
        ("target_x = { position = [0.35, 0.6] }", "target_x = { position = [0.35, 0.6], velocity = [0.0, 0.1] }",
         "rho.target_x.velocity: a target coordinate starts at rest"),
    ],
)  # fmt: skip
def test_a_bad_target_is_refused_by_name(panda_dir: Path, old: str, new: str, expected: str) -> None:
    with pytest.raises(TaskFileError, match=expected.replace("[", r"\[").replace("]", r"\]")):
        get_task(edited(panda_dir, old, new))


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ('<body name="target" gravcomp="1">', '<body name="target">', 'must set gravcomp="1"'),
        ('contype="0" conaffinity="0" rgba="1 0 0 0.5"', 'rgba="1 0 0 0.5"', "has a geom that collides"),
        ('<joint name="target_x" type="slide" axis="1 0 0"/>',
         '<joint name="target_x" type="slide" axis="1 0 0" stiffness="10" springref="0.3"/>',
         "random torques moved the target by up to"),
    ],
)  # fmt: skip
def test_a_target_something_moves_is_refused(panda_dir: Path, old: str, new: str, expected: str) -> None:
    scene_copy(panda_dir, old, new)
    with pytest.raises(TaskFileError, match=expected):
        get_task(str(panda_dir / "task.toml"))


def test_the_gravity_safe_effort_holds_the_arm_before_any_target() -> None:
    """npp-deploy's safe command with safe_effort gravity: the torques that hold the measured pose, computed from a
    joint state of the arm's own joints before any target was given; zero effort lets the same arm fall."""
    task = get_task(str(EXAMPLE / "task.toml"))
    plant = task.make_plant(0)
    layout = JointLayout.of_plant(plant)
    s0 = task.sample_initial_state(np.random.default_rng(5))
    names = [f"joint{i}" for i in range(1, 8)]
    with pytest.raises(NoTarget) as waiting:
        layout.state(names, s0[:ARM_JOINTS].tolist(), s0[10:17].tolist())
    held = safe_command("effort", layout, waiting.value.raw, gravity_hold(plant))
    assert not np.array_equal(held, np.zeros(7))
    drift = {}
    for name, command in (("gravity", held), ("zero", safe_command("effort", layout, waiting.value.raw))):
        plant.reset(s0)
        for _ in range(20):
            plant.step(layout.action(command))
        drift[name] = float(np.max(np.abs(plant.state()[:ARM_JOINTS] - s0[:ARM_JOINTS])))
    assert drift["gravity"] < 0.01 < 0.1 < drift["zero"], drift


def test_the_arms_description_compiles_alone_to_the_tasks_fingerprint() -> None:
    """What npp-robot publishes on /robot_description: its include inlined and its mesh files by absolute path, so
    the text compiles away from the example's folder and gives the fingerprint the run recorded."""
    plant = get_task(str(EXAMPLE / "task.toml")).make_plant(0)
    text = model_mjcf(plant)
    assert text is not None and "<include" not in text and "meshdir" not in text
    assert f'file="{EXAMPLE.resolve() / "panda" / "meshes" / "link1.stl"}"' in text
    assert mjcf_fingerprint(plant, text) == plant.model_sha256()
