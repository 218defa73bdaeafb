"""Deploying a task whose state holds a target, without ROS: the robot's joints and a given point as one state
(npp_ros.deployment.joints), the box a target must lie in, what npp-deploy's status says while it waits for a
target or after one was refused, and the certified point-mass reach (tests/fixtures/point_reach) reaching a
target the run never drew, its transitions inside what the model monitor explains."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from deploy_runs import REACH, SEED, make_reach_run

from npp_ros.deployment.gate import Acceptance, load_deployment
from npp_ros.deployment.joints import JointLayout, NoTarget, RobotStateError, TargetRefused, stored_state
from npp_ros.deployment.model_monitor import ModelMonitor
from npp_ros.deployment.state import DeploymentState, Level
from npp_ros.run.setup import plant_fingerprint
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import ScaleRange, UncertaintySet

ROBOT = ["mass_x", "mass_y"]  # what a robot reports; the fixture's target sits at (0.2, 0.1, 0) with its joints at 0
BOX = "x [0.1, 0.3], y [0, 0.2], z [0, 0] m"


@pytest.fixture(scope="module")
def reach_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_reach_run(tmp_path_factory.mktemp("reach") / "run")


def reach_layout() -> JointLayout:
    return JointLayout.of_plant(get_task(REACH).make_plant(SEED))


def test_the_state_is_the_robots_joints_and_the_given_point_at_rest() -> None:
    layout = reach_layout()
    assert layout.measured == tuple(ROBOT) and layout.target is not None and layout.target.describe() == BOX
    with pytest.raises(NoTarget, match="no target given yet: the state holds the target's joints target_x"):
        layout.state(["mass_y", "mass_x"], [0.2, 0.1], [0.4, 0.3])
    with pytest.raises(RobotStateError, match=r"lacks the task's joints mass_y \(it names: mass_x\)") as refused:
        layout.state(["mass_x"], [0.1], [0.3])  # a bad state is refused as before, not taken for a wait
    assert not isinstance(refused.value, NoTarget)
    np.testing.assert_allclose(layout.aim([0.25, 0.15, 0.0]), [0.05, 0.05, 0.0])
    state = layout.state(["mass_y", "mass_x"], [0.2, 0.1], [0.4, 0.3])
    np.testing.assert_allclose(state, [0.1, 0.2, 0.05, 0.05, 0.0, 0.3, 0.4, 0.0, 0.0, 0.0])
    # A message that names the target's joints too is not heard on them: the target is the point given.
    named = layout.state(["target_x", "mass_x", "mass_y"], [9.0, 0.1, 0.2], [9.0, 0.3, 0.4])
    np.testing.assert_array_equal(named, state)
    # The point given is where the model puts the target for that state: the point less the target's origin.
    plant = get_task(REACH).make_plant(SEED)
    plant.reset(state)
    np.testing.assert_allclose(plant.physics.named.data.site_xpos["target"], [0.25, 0.15, 0.0], atol=1e-12)


def test_a_target_outside_the_box_is_refused_naming_it_and_the_one_before_is_kept() -> None:
    layout = reach_layout()
    with pytest.raises(TargetRefused) as refused:
        layout.aim([0.35, 0.1, 0.0])
    assert str(refused.value) == (
        f"target (0.35, 0.1, 0) lies outside the box {BOX} that rho draws targets from: the certificate covers "
        "those targets only"
    )
    assert layout.aimed is None  # none before it: still none
    layout.aim([0.1, 0.0, 0.0])  # the box's corner is inside
    outside, not_finite = "lies outside the box", "is not a finite point"
    for point, says in (([0.2, 0.1, 0.01], outside), ([0.2, -0.05, 0.0], outside), ([np.nan, 0.1, 0.0], not_finite),
                        ([0.2, 0.1], not_finite)):  # fmt: skip
        with pytest.raises(TargetRefused, match=says):
            layout.aim(point)
        np.testing.assert_allclose(layout.aimed, [-0.1, -0.1, 0.0])  # type: ignore[arg-type]
    with pytest.raises(TargetRefused, match="holds no target"):
        JointLayout.of_plant(get_task("lqr_2_1").make_plant(0)).aim([0.0, 0.0, 0.0])


def test_a_reset_start_gives_the_target_it_holds() -> None:
    layout = reach_layout()
    start = get_task(REACH).initial_state(SEED, 3)
    layout.aim_as(start)
    np.testing.assert_array_equal(layout.state(ROBOT, start[:2], start[5:7]), start)


def test_the_status_waits_for_a_target_and_warns_while_one_is_refused() -> None:
    state = DeploymentState()
    state.configured("ab" * 32, "here")
    state.awaits_target("/npp_deploy/target")
    state.became("inactive")
    assert state.values()["target"] == "none received on /npp_deploy/target"
    state.activated()
    waiting = state.status({})
    assert (waiting.doing, waiting.level, waiting.error) == (
        "active: waiting for a target on /npp_deploy/target", Level.OK, ""
    )  # fmt: skip
    state.arrived(1.0)  # joint states come; none can be acted on, and the watchdog sends the safe command
    stale = state.watchdog_expired(0.3, 0.1, "safe command [0.0, 0.0] sent")
    assert stale.startswith("no target received on /npp_deploy/target in the 300 ms since activation")
    assert state.status({}, watchdog_expired=True).doing == "active: waiting for a target on /npp_deploy/target"
    refused = state.target_refused("target (1, 0, 0) lies outside the box")
    assert refused == "target refused: target (1, 0, 0) lies outside the box; there is still no target"
    status = state.status({}, watchdog_expired=True)
    assert (status.doing, status.level, status.error) == (
        "active: waiting for a target on /npp_deploy/target", Level.WARN, refused
    )  # fmt: skip
    state.target_taken("(0.2, 0.1, 0) in world")
    state.answered(1e-4, 1.1, resumed=True)
    assert (state.status({}).doing, state.status({}).level) == ("active: commanding the robot", Level.OK)
    assert state.values()["target"] == "(0.2, 0.1, 0) in world" and "target refused" not in state.values()
    state.target_refused("target (0.2, 0.1, 0) is in frame 'map', not 'world'")
    status = state.status({})
    assert (status.level, status.doing) == (
        Level.WARN, "active: commanding the robot towards the target kept; the last target given was refused"
    )  # fmt: skip
    assert status.error.endswith("; the target kept is (0.2, 0.1, 0) in world"), status.error
    state.stop_commanding()
    state.became("inactive")
    assert state.status({}).level == Level.WARN  # said while inactive too, until a target is taken
    state.released()
    assert "target" not in state.values() and state.status({}).level == Level.OK


def test_the_certified_reach_reaches_a_target_it_never_drew_and_its_transitions_stay_explained(reach_run) -> None:
    """Through the gate, the policy drives the model from joint states and a given point, as npp-deploy does; the
    model monitor (on a set around the model) predicts each transition with the target's entries where they are."""
    plant = get_task(REACH).make_plant(SEED)
    deployment = load_deployment(reach_run, Acceptance(model_fingerprint=plant_fingerprint(REACH, SEED)))
    assert deployment.certificate is not None and deployment.certificate.proven
    layout = JointLayout.of_plant(deployment.plant)
    robots = UncertaintySet((ScaleRange("mass", 0.8, 1.2), ScaleRange("damping", 0.8, 1.2)))
    monitor = ModelMonitor.of_plant(deployment.plant, robots)
    goal = np.array([0.27, 0.03, 0.0])
    layout.aim(goal)
    plant.reset(np.concatenate([[-0.04, 0.05], layout.aimed, np.zeros(5)]))  # type: ignore[list-item]
    for _ in range(2 * get_task(REACH).default_horizon):
        raw = plant.raw_state()
        state = layout.state(ROBOT, raw[:2], raw[5:7])
        action = deployment.policy.act(stored_state(deployment.plant, state))
        monitor.observe(state, action)
        plant.step(action)
    miss = float(np.linalg.norm(plant.raw_state()[:2] - goal[:2]))
    assert miss < 0.02, miss  # the task's success band
    assert monitor.checked > 100 and monitor.exceeded == 0, monitor.summary()
    print(f"\nthe mass ended {miss * 1e3:.2f} mm from the target; {monitor.summary()}")
