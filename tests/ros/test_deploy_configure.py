"""npp-deploy's configure in process: each failure reaches the operator with its reason, a bug named by its type."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from deploy_runs import FINGERPRINT, make_run, with_robots
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter

import npp_ros_graph.nodes.deploy.node as deploy_node
from npp_ros.cli.sign import main as npp_sign
from npp_ros.deployment.gate import GateRefusal
from npp_ros.deployment.signing import fingerprint, load_public_key
from npp_ros.run.read import read_run
from npp_ros.tasks.uncertainty import Robot


@pytest.fixture
def deploy(ros_context: None) -> Iterator[deploy_node.DeployNode]:
    node = deploy_node.DeployNode()
    node.set_parameters([Parameter("run_dir", value="/nowhere"), Parameter("robot_model_fingerprint", value="0" * 64)])
    try:
        yield node
    finally:
        node.destroy_node()


@pytest.mark.parametrize(
    ("raised", "said"),
    [
        (GateRefusal("the run file holds no certificate"), "configure refused: the run file holds no certificate"),
        (ValueError("setting an array element with a sequence"),
         "configure refused: ValueError: setting an array element with a sequence"),
        (KeyError("policy"), "configure refused: KeyError: 'policy'"),
    ],
)  # fmt: skip
def test_a_gate_refusal_is_its_reason_and_anything_else_from_the_gate_is_named_by_its_type(
    deploy: deploy_node.DeployNode, monkeypatch: pytest.MonkeyPatch, raised: Exception, said: str
) -> None:
    """The gate refuses with GateRefusal; a ValueError from inside it is a bug, not a refusal, and the operator
    sees its type rather than a message that reads like one of the gate's reasons."""

    def gate(*_args: object, **_kwargs: object) -> None:
        raise raised

    monkeypatch.setattr(deploy_node, "load_deployment", gate)
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert deploy.refusal == said, deploy.refusal


def test_a_bad_setting_is_refused_with_its_own_reason(deploy: deploy_node.DeployNode) -> None:
    """0 is within the parameter's range (>= 0), but no certificate can meet it: refused at configure."""
    (result,) = deploy.set_parameters([Parameter("max_epsilon", value=0.0)])
    assert result.successful, result.reason
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert deploy.refusal == "configure refused: max_epsilon must be > 0, got 0.0", deploy.refusal


def test_without_a_description_configure_waits_its_bound_and_says_what_it_saw(
    deploy: deploy_node.DeployNode, tmp_path: Path
) -> None:
    """No robot on the domain: configure waits description_timeout for the description, then refuses, naming how
    long it waited and how many publishers of the topic it saw."""
    run = make_run(tmp_path / "run")
    deploy.set_parameters([
        Parameter("run_dir", value=str(run)), Parameter("robot_model_fingerprint", value=""),
        Parameter("description_timeout", value=0.5),
    ])  # fmt: skip
    started = time.monotonic()
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert time.monotonic() - started >= 0.5
    assert "no robot description was received on /robot_description (waited 0.5 s" in deploy.refusal, deploy.refusal
    assert "no publisher of it seen" in deploy.refusal, deploy.refusal


def test_trusted_keys_refuse_a_run_signed_by_another_key_naming_it(
    deploy: deploy_node.DeployNode, tmp_path: Path
) -> None:
    """npp-deploy's trusted_keys: a run signed by another key is refused at configure, its signer named."""
    run = make_run(tmp_path / "run")
    for name in ("trusted", "other"):
        assert npp_sign(["keygen", str(tmp_path / name)]) == 0
    assert npp_sign(["run", str(run), "--key", str(tmp_path / "other.key")]) == 0
    signer = fingerprint(load_public_key(tmp_path / "other.pub"))
    deploy.set_parameters([
        Parameter("run_dir", value=str(run)), Parameter("robot_model_fingerprint", value=FINGERPRINT),
        Parameter("trusted_keys", value=str(tmp_path / "trusted.pub")),
    ])  # fmt: skip
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert f"the run is signed by {signer}, which this deployment does not trust" in deploy.refusal, deploy.refusal
    deploy.set_parameters([Parameter("trusted_keys", value=f"{tmp_path / 'trusted.pub'}, {tmp_path / 'other.pub'}")])
    assert deploy.on_configure(None) == TransitionCallbackReturn.SUCCESS  # type: ignore[arg-type]
    assert deploy.deployment is not None and deploy.deployment.signed.startswith(f"signed by {signer}")


def test_a_trusted_key_that_cannot_be_read_is_configures_refusal_not_a_stopped_node(
    deploy: deploy_node.DeployNode, tmp_path: Path
) -> None:
    """A bad trusted_keys path is read at configure: the node stays up and configure says which file and why."""
    run = make_run(tmp_path / "run")
    deploy.set_parameters([
        Parameter("run_dir", value=str(run)), Parameter("robot_model_fingerprint", value=FINGERPRINT),
        Parameter("trusted_keys", value=str(tmp_path / "missing.pub")),
    ])  # fmt: skip
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert "cannot read the public key" in deploy.refusal and "missing.pub" in deploy.refusal, deploy.refusal
    deploy.set_parameters([Parameter("trusted_keys", value="")])
    assert deploy.on_configure(None) == TransitionCallbackReturn.SUCCESS  # type: ignore[arg-type]


@pytest.mark.long  # a run at H = 1000 and two configures that derive it again and roll it out: about 40 s
def test_identified_robot_checks_the_policy_at_that_robot_before_it_moves(
    deploy: deploy_node.DeployNode, tmp_path: Path
) -> None:
    """A run on a set of robots and an identification of the robot at hand (as npp-identify --json writes it): at the
    nominal robot the policy settles lqr_2_1 from every start and configure passes, saying so; at a robot whose
    motor gives a hundredth, it settles none and configure refuses, naming the robot and the bound."""
    run = with_robots(tmp_path / "run", horizon=1000)
    read = read_run(run)
    assert read.robots is not None

    def identified(robot: Robot, name: str) -> Path:
        record = {"identification": {
            "task": "lqr_2_1", "set": read.robots.describe(), "verdict": "inside", "delay": robot.action_delay,
            "combinations": [{"label": "gear of motor_0 / mass of body_1", "value": 1.0, "low": 0.99, "high": 1.01}],
            "region": [json.loads(robot.record())],
        }}  # fmt: skip
        (tmp_path / name).write_text(json.dumps(record))
        return tmp_path / name

    deploy.set_parameters([
        Parameter("run_dir", value=str(run)), Parameter("robot_model_fingerprint", value=FINGERPRINT),
        Parameter("identified_robot", value=str(identified(Robot(), "nominal.json"))),
        Parameter("robot_check_starts", value=6), Parameter("robot_min_success", value=0.5),
    ])  # fmt: skip
    assert deploy.on_configure(None) == TransitionCallbackReturn.SUCCESS, deploy.refusal  # type: ignore[arg-type]
    assert deploy.robot_check.startswith("the robot may move: the certified policy's success at the worst of 1 points")
    assert deploy.health().values["robot check"] == deploy.robot_check
    assert deploy.on_cleanup(None) == TransitionCallbackReturn.SUCCESS  # type: ignore[arg-type]
    weak = Robot((("gear", "motor_0", 0.01),))
    deploy.set_parameters([Parameter("identified_robot", value=str(identified(weak, "weak.json")))])
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert "the robot identified from its own motion (gear of motor_0 / mass of body_1 1 [0.99, 1.01]" in deploy.refusal
    assert "the robot must not move" in deploy.refusal and "0/6 at gear[motor_0] x0.010" in deploy.refusal
    deploy.set_parameters([Parameter("identified_robot", value=str(tmp_path / "nowhere.json"))])
    assert deploy.on_configure(None) == TransitionCallbackReturn.FAILURE  # type: ignore[arg-type]
    assert "cannot read the identified robot" in deploy.refusal, deploy.refusal
