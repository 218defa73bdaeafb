"""A task file's energy cost term: MuJoCo's mechanical energy less a pose's, for underactuated swing-ups."""

from __future__ import annotations

import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest

from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import TaskFileError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def acrobot_file(folder: Path, append: str = "", replace: tuple[str, str] = ("", "")) -> Path:
    """A copy of the acrobot example, ``append`` added at its end and ``replace`` made in its text."""
    shutil.copy(EXAMPLES / "acrobot" / "acrobot.xml", folder / "acrobot.xml")
    text = (EXAMPLES / "acrobot" / "task.toml").read_text().replace(*replace)
    (folder / "task.toml").write_text(text + append)
    return folder / "task.toml"


def energy_by_mujoco(model: mujoco.MjModel, x: np.ndarray) -> float:
    """MuJoCo's own energy after a full forward pass with its energy flag on."""
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = x[:2], x[2:]
    mujoco.mj_forward(model, data)
    return float(data.energy.sum())


def test_the_energy_term_penalises_the_energy_beyond_the_poses_and_its_gradient_is_the_costs(tmp_path: Path) -> None:
    """The example's term (weight 0.2, margin 1 J) costs 0.5 w ((E(x) - E(upright at rest)) / margin)^2 with E
    as MuJoCo computes it, and the gradient iLQR gets is the cost's own slope (central differences of the cost)."""
    task = get_task(str(acrobot_file(tmp_path)))
    cost = task.make_expert(0, 20).optimizer.cost
    (energy,) = (t for t in cost.state_terms_list if t.quantity == "energy")
    assert (energy.weight, energy.margin, energy.bounds) == (0.2, 1.0, (0.0, 0.0))
    alone = type(cost)((energy,), cost.model, {"velocity_weight": 0.0, "control_weight": 0.0})
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "acrobot.xml"))
    upright = energy_by_mujoco(model, np.zeros(4))
    states = np.array([[0.3, -0.2, 1.0, 0.5], [2.9, 0.4, -2.0, 3.0], [-1.5, 2.5, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    value, grad, hess = alone.state_terms(states)
    expected = [0.5 * 0.2 * (energy_by_mujoco(model, x) - upright) ** 2 for x in states]
    assert np.allclose(value, expected, rtol=1e-9, atol=1e-9)
    assert value[-1] == 0.0 and not grad[-1].any()
    step = 1e-5
    for k, x in enumerate(states):
        slope = [(alone.state_values((x + d)[None])[0] - alone.state_values((x - d)[None])[0]) / (2 * step)
                 for d in np.eye(4) * step]  # fmt: skip
        assert np.allclose(grad[k], slope, rtol=1e-5, atol=1e-6), (k, grad[k], slope)
        assert np.allclose(hess[k], hess[k].T) and np.linalg.eigvalsh(hess[k]).min() >= -1e-12


@pytest.mark.parametrize(
    ("append", "replace", "expected"),
    [
        (
            "",
            ('site_distance = ["tip", "target"]\nbounds = [0.0, 0.2]', "energy = { shoulder = 0.0 }"),
            "reward.terms[0].energy: an energy term is the expert's cost only: write it in [[expert.terms]]",
        ),
        (
            "[[expert.terms]]\nenergy = { wrist = 0.0 }\n",
            ("", ""),
            "expert.terms[3].energy: unknown joint 'wrist' (the model's: elbow, shoulder)",
        ),
        (
            '[[expert.terms]]\nenergy = { shoulder = 0.0 }\nsigmoid = "linear"\n',
            ("", ""),
            "expert.terms[3].sigmoid: unknown key",
        ),
        ("[[expert.terms]]\nenergy = 3.0\n", ("", ""), "expert.terms[3].energy: must be a table"),
    ],
)
def test_a_bad_energy_term_is_refused_in_one_line_naming_its_key(
    tmp_path: Path, append: str, replace: tuple[str, str], expected: str
) -> None:
    with pytest.raises(TaskFileError) as caught:
        get_task(str(acrobot_file(tmp_path, append, replace)))
    message = str(caught.value)
    assert "\n" not in message and expected in message, message
