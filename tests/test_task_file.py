"""Tasks from a file: a MuJoCo model and a TOML task, checked key by key; a bad file is one line naming the key."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import HASH_MARK, TaskFileError, load_task_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm"
LEARN = [str(Path(sys.executable).parent / "npp-learn")]


@pytest.fixture
def task_dir(tmp_path: Path) -> Path:
    """A copy of the example's model and task file, to edit."""
    for name in ("arm.xml", "task.toml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    return tmp_path


def edited(task_dir: Path, old: str, new: str) -> Path:
    path = task_dir / "task.toml"
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return path


def test_the_example_file_defines_a_task(task_dir: Path) -> None:
    task = get_task(str(task_dir / "task.toml"))
    assert task.name.startswith(f"{(task_dir / 'task.toml').resolve()}{HASH_MARK}")
    assert (task.state_dim, task.action_dim, task.default_horizon, task.default_certify) == (4, 2, 200, "oracle")
    assert task.epsilon(None) == 20.0 and task.default_lipschitz_choice() == 200.0
    assert get_task(task.name) is task  # the published name loads the same task
    plant = task.make_plant(0)
    assert plant.task == task.name
    assert (plant.joint_names, plant.actuated_joint_names) == (["shoulder", "elbow"], ["shoulder", "elbow"])
    assert plant.model_sha256() == task.make_plant(3).model_sha256()
    for episode in range(20):
        s0 = task.initial_state(0, episode)
        assert -np.pi <= s0[0] <= np.pi and -2.0 <= s0[1] <= 2.0 and (s0[2:] == 0).all()
    plant.reset([4.0, 0.1, 0.0, 0.0])  # angles wrap in the stored state
    assert plant.state()[0] == pytest.approx(4.0 - 2 * np.pi)
    rewards = [plant.step([1.0, -1.0]) for _ in range(50)]
    assert all(0.0 <= r <= 1.1 for r in rewards)


def test_the_reward_is_the_files_tolerance_terms(task_dir: Path) -> None:
    from dm_control.utils.rewards import tolerance

    plant = get_task(str(task_dir / "task.toml")).make_plant(0)
    plant.reset([0.3, 0.4, 0.0, 0.0])
    reward = plant.step([0.5, -0.25])
    data = plant.physics.data
    distance = np.linalg.norm(data.site("fingertip").xpos - data.site("target").xpos)
    control = [float(tolerance(u, (0, 0), 1.0, "quadratic", 0.0)) for u in (0.5, -0.25)]
    expected = float(tolerance(distance, (0, 0.02), 0.3, "gaussian", 0.1)) + 0.05 * sum(control)
    assert reward == pytest.approx(expected, rel=1e-12)


def test_the_iLQR_expert_works_on_the_file_with_no_code(task_dir: Path) -> None:
    task = get_task(str(task_dir / "task.toml"))
    expert = task.make_expert(0, 200)
    s0 = np.array([2.45, 0.23, 0.0, 0.0])  # far from the target: 108 against 20 idle
    answer = expert.trajectory(s0)
    assert answer.states.shape == (200, 4) and answer.actions.shape == (200, 2)
    assert np.all(np.abs(answer.actions) <= 1.0)
    plant = task.make_plant(0)
    plant.reset(s0)
    replayed = sum(plant.step(u) for u in answer.actions)
    assert answer.expert_return == pytest.approx(replayed, rel=1e-12)
    plant.reset(s0)
    idle = sum(plant.step([0.0, 0.0]) for _ in range(200))
    assert answer.expert_return > idle + 50  # it reaches for the target


def test_a_changed_file_is_refused_naming_both_hashes(task_dir: Path) -> None:
    name = get_task(str(task_dir / "task.toml")).name
    edited(task_dir, "epsilon = 20.0", "epsilon = 25.0")
    with pytest.raises(TaskFileError) as caught:
        load_task_file(name)
    message = str(caught.value)
    old_hash = name.split(HASH_MARK)[1]
    assert "task file mismatch" in message and old_hash[:16] in message
    assert get_task(str(task_dir / "task.toml")).name.split(HASH_MARK)[1][:16] in message


BAD = [
    ('joints = ["shoulder", "elbow"]', 'joints = ["shoulder", "wrist"]', "state.joints: unknown joint 'wrist'"),
    ('model = "arm.xml"', 'model = "no_such_arm.xml"', "model: no model file at"),
    ('site_distance = ["fingertip", "target"]', "", "reward.terms[0]: the term is on nothing"),
    ("shoulder = { position = [-3.14159, 3.14159] }\nelbow = { position = [-2.0, 2.0] }", "", "rho: is empty"),
    ("elbow = { position = [-2.0, 2.0] }", "elbow = { position = [2.0, -2.0] }", "rho.elbow.position: is empty"),
    ('site_distance = ["fingertip", "target"]', 'site_distance = ["fingertip", "goal"]',
     "reward.terms[0].site_distance: unknown site 'goal'"),
    ("control_timestep = 0.01", "control_timestep = 0.015", "control_timestep: 0.015 s is not a whole multiple"),
    ('wrap = ["shoulder", "elbow"]', 'wrap = ["shoulder", "knee"]', "state.wrap: unknown joint 'knee'"),
    ("horizon = 200", "horizon = 200\nhorizn = 3", "horizn: unknown key"),
    ("horizon = 200", "horizon = [", "not valid TOML"),
    ('control = "elbow_motor"', 'control = "wrist_motor"', "reward.terms[2].control: unknown actuator 'wrist_motor'"),
]  # fmt: skip


@pytest.mark.parametrize(("old", "new", "expected"), BAD, ids=[b[2].split(":")[0] for b in BAD])
def test_a_bad_file_gets_one_line_naming_the_key(task_dir: Path, old: str, new: str, expected: str) -> None:
    path = edited(task_dir, old, new)
    with pytest.raises(TaskFileError) as caught:
        get_task(str(path))
    message = str(caught.value)
    assert expected in message and "\n" not in message and str(path) in message


@pytest.mark.parametrize(("old", "new", "expected"), BAD[:4], ids=[b[2].split(":")[0] for b in BAD[:4]])
def test_the_command_line_says_it_in_one_line(task_dir: Path, old: str, new: str, expected: str) -> None:
    path = edited(task_dir, old, new)
    run = subprocess.run([*LEARN, "--task", str(path)], capture_output=True, text=True, cwd=task_dir, timeout=120)
    assert run.returncode == 2
    errors = [line for line in run.stderr.splitlines() if "GLFW" not in line and "warnings.warn" not in line]
    assert "Traceback" not in run.stderr
    assert errors[-1].startswith("npp-learn: error: argument --task: task file") and expected in errors[-1]
