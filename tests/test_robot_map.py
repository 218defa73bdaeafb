"""Where in a set the policy and the expert fail: the per-parameter table, its identifiable ratios, its figure, and
the expert alone on draws of its own before a run (a real iLQR expert on a real MuJoCo pendulum)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from npp_ros.cli import robots as cli
from npp_ros.run.per_robot.expert_map import EXPERT_MAP_INDEX, expert_draw, expert_map
from npp_ros.run.per_robot.figure import write_figure
from npp_ros.run.per_robot.success_map import ratio_pairs, success_map
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import SWINGUP_UNCERTAINTY, Robot, UncertaintySet

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pendulum" / "task.toml"


@pytest.fixture(scope="module")
def pendulum_set() -> UncertaintySet:
    return SWINGUP_UNCERTAINTY.resolved(get_task("pendulum_swingup").make_plant(0).physics.model)


def robot(mass: float, gear: float, damping: float, delay: int = 0) -> Robot:
    return Robot((("mass", "pole", mass), ("gear", "torque", gear), ("damping", "hinge", damping)), delay)


def test_each_bin_counts_the_draws_that_fall_in_it(pendulum_set: UncertaintySet) -> None:
    """A corner (heavy, weak, damped, late) where the policy fails, and a nominal middle where it succeeds; the
    expert judged on the corner's draws only. The counts land in the bins of each axis, the worst bin is named."""
    corner, middle = robot(1.19, 0.81, 1.45, 1), robot(1.0, 1.0, 1.0, 0)
    draws = [(corner, False, False)] * 10 + [(middle, True, None)] * 30
    table = success_map(pendulum_set, draws, "made up", bodies=("pole",))
    by_name = {part.axis.name: part for part in table.tables}
    assert [t.text() for t in by_name["mass[pole]"].policy] == ["-", "-", "30/30 100%", "0/10   0%"]
    assert [t.judged for t in by_name["mass[pole]"].expert] == [0, 0, 0, 10]
    assert [(t.succeeded, t.judged) for t in by_name["delay"].policy] == [(30, 30), (0, 10)]
    assert (table.policy.succeeded, table.policy.judged, table.expert.judged) == (30, 40, 10)
    # gear/mass of the corner: 0.81 / 1.19 = 0.68, in the lowest bin of [0.8 / 1.2, 1.2 / 0.8]
    assert by_name["gear[torque]/mass[pole]"].policy[0].judged == 10
    assert by_name["damping[hinge]/mass[pole]"].policy[3].judged == 0  # 1.45 / 1.19 = 1.22: third bin
    text = table.table()
    assert "worst bin of the policy" in text and "0/10" in text.splitlines()[-1]
    assert json.loads(json.dumps(table.record()))["axes"][0]["bins"][2]["policy"] == [30, 30]


def test_ratios_are_tabled_for_one_body_only(pendulum_set: UncertaintySet) -> None:
    pairs, why = ratio_pairs(pendulum_set, ("pole",))
    assert pairs == [("gear[torque]", "mass[pole]"), ("damping[hinge]", "mass[pole]")] and "gravity" in why
    cartpole = SWINGUP_UNCERTAINTY.resolved(get_task("cartpole_swingup").make_plant(0).physics.model)
    pairs, why = ratio_pairs(cartpole, ("cart", "pole_1"))
    assert pairs == [] and "several bodies" in why
    assert ratio_pairs(pendulum_set, ("pole", "another"))[0] == []  # one body drawn of two: no ratio holds


def test_the_figure_is_written(pendulum_set: UncertaintySet, tmp_path: Path) -> None:
    draws = [(pendulum_set.draw(0, k), k % 3 != 0, k % 5 != 0 if k % 2 else None) for k in range(40)]
    path = write_figure(success_map(pendulum_set, draws, "forty draws", bodies=("pole",)), tmp_path / "map.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


def test_the_expert_alone_is_asked_on_draws_of_its_own(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Near upright at horizon 50 the privileged iLQR expert holds every drawn pendulum; the draws are a function
    of (seed, k) only, apart from the run's, and the command prints its progress on stderr."""
    text = EXAMPLE.read_text().replace(
        "hinge = { position = [-3.14159, 3.14159] }", "hinge = { position = [-0.05, 0.05] }"
    )
    text = text.replace("horizon = 1000 ", "horizon = 50   ").replace("last_seconds = 1.0", "last_seconds = 0.5")
    (tmp_path / "pendulum.xml").write_text((EXAMPLE.parent / "pendulum.xml").read_text())
    (tmp_path / "task.toml").write_text(text)
    name = str(tmp_path / "task.toml")
    heard: list[tuple[int, bool]] = []
    table = expert_map(name, 1.0, 3, horizon=50, progress=lambda k, n, r, met: heard.append((k, met)))
    assert heard == [(1, True), (2, True), (3, True)]
    assert (table.expert.succeeded, table.expert.judged, table.policy.judged) == (3, 3, 0)
    robots = UncertaintySet.from_record(
        SWINGUP_UNCERTAINTY.resolved(get_task(name).make_plant(0).physics.model).record()
    )
    first, s0 = expert_draw(name, robots, 0, 0)
    assert first == robots.draw(0, EXPERT_MAP_INDEX) and abs(s0[0]) <= 0.05
    assert cli.main(["expert", "--task", name, "--robots", "1", "--horizon", "50"]) == 0
    out, err = capsys.readouterr()
    assert "expert answer    1/1 | met" in err and "expert (answers)" in out and "policy (checks)" not in out
    assert cli.main(["expert", "--task", name, "--uncertainty", "0", "--robots", "1"]) == 2
    assert "exact model" in capsys.readouterr().err
