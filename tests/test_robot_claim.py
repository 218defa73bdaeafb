"""The per-robot claim Q(q, p_r): with probability >= 1 - delta, P_theta[r(theta) >= p_r] >= q.

First in a world whose truth is known in closed form (each robot's success rate r(theta) is given, a check's
successes are Binomial(m, r(theta))), run through the claim's own rule: the claim is false in the worst such world
at most delta of the time, and true claims are made. Then on a real certified run of the pendulum (a task file that
starts near upright, horizon 100): the batched rollouts on a robot equal the one-at-a-time ones, a claim is made and
kept, a stopped claim goes on from its checks without drawing them again, and what cannot be claimed is refused.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.certifier import CertificationSpec
from npp_ros.certificate.mixture import certifier_for
from npp_ros.cli import robots as cli
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.per_robot.claim import (
    CLAIM_INDEX,
    ClaimSettings,
    binomial_tail,
    claim_file,
    claim_for_run,
    claim_robot,
    claim_starts,
    decide,
    pass_rate_upper,
    robot_check,
    rollouts_on_robot,
    threshold_for,
)
from npp_ros.run.read import Run, read_run
from npp_ros.run.setup import build_config, build_loop
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pendulum" / "task.toml"
HORIZON = 100


# ----------------------------------------------------------------------------- the pass threshold
def test_the_threshold_is_the_smallest_c_whose_binomial_tail_keeps_beta() -> None:
    c, beta = threshold_for(50, 0.8, 0.05)
    assert (c, round(beta, 3)) == (45, 0.048)
    assert binomial_tail(50, 0.8, c - 1) > 0.05  # one fewer would let a poor robot pass too often
    assert threshold_for(50, 0.9, 0.05)[0] == 49
    with pytest.raises(ValueError, match="use more starts per robot"):
        threshold_for(20, 0.9, 0.05)  # even 20 of 20 is met by a robot at 0.9 with probability 0.12
    settings = ClaimSettings(0.9, 0.8, 50, 45)
    assert settings.target == pytest.approx(0.9 + settings.beta * 0.1)


# ----------------------------------------------------------------------------- a world whose truth is known
def false_claim_rate(
    settings: ClaimSettings, share_good: float, bad_rate: float, repetitions: int, seed: int, max_checks: int = 200
) -> float:
    """How often the claim's rule certifies in a world where a share ``share_good`` of robots has r = 1 and the rest
    r = ``bad_rate`` (< p_r): P_theta[r >= p_r] = share_good, known. Each robot check draws theta, then
    X ~ Binomial(m, r(theta)); the rule sees only X, as on a real run."""
    rng = np.random.default_rng(seed)
    certified = 0
    for _ in range(repetitions):
        good = rng.random(max_checks) < share_good
        successes = np.where(good, settings.m, rng.binomial(settings.m, bad_rate, max_checks))
        certified += decide(settings, lambda i, s=successes: int(s[i]), max_checks).certified
    return certified / repetitions


@pytest.mark.parametrize("rule", ["mixture", "sequential"])
def test_a_false_claim_is_made_at_most_delta_of_the_time_in_the_worst_world(rule: str) -> None:
    """88% of robots succeed always, the others at just below p_r: the most a poor robot can pass (beta), so
    P(pass) is as high as a false claim Q(0.9, 0.8) allows. 1,000 repetitions; 3 standard errors of margin."""
    repetitions, delta = 1000, 0.1
    settings = ClaimSettings(0.9, 0.8, 50, 45, delta, rule)  # type: ignore[arg-type]
    margin = 3 * math.sqrt(delta * (1 - delta) / repetitions)
    rate = false_claim_rate(settings, share_good=0.88, bad_rate=0.8 - 1e-9, repetitions=repetitions, seed=3)
    assert rate + margin < delta, f"{rule}: {rate:.1%} false claims"


def test_without_beta_a_lenient_pass_makes_false_claims_and_with_it_none() -> None:
    """At c = 38 of 50 a robot at r just below 0.8 passes 81% of the time: the checks' pass rate then says little of
    the robots. Where only 70% of robots reach 0.8, P(pass) = 0.7 + 0.3 x 0.81 = 0.94: certifying P(pass) >= q alone
    claims Q(0.9, 0.8) almost always (falsely); certifying q + beta (1 - q) never does."""
    settings = ClaimSettings(0.9, 0.8, 50, 38, 0.1, "mixture")
    assert settings.beta > 0.8 and settings.target > 0.98
    rng = np.random.default_rng(5)
    naive_spec = CertificationSpec("i", 1.0, settings.q, settings.delta, LipschitzConstant(1.0, "user"),
                                   certify="success", rule="mixture")  # fmt: skip
    naive = ours = 0
    for _ in range(200):
        good = rng.random(400) < 0.7
        successes = np.where(good, 50, rng.binomial(50, 0.8 - 1e-9, 400))
        certifier = certifier_for(naive_spec)
        naive += any(certifier.observe(0.0, failed=not x >= settings.c).certified for x in successes)
        ours += decide(settings, lambda i, s=successes: int(s[i]), 400).certified
    assert naive / 200 > 0.5 and ours == 0


def test_a_true_claim_is_made_when_nearly_every_robot_succeeds() -> None:
    """98% of robots at r = 1, the rest at 0: P(pass) = 0.98 > 0.9048, and the rule certifies nearly always."""
    settings = ClaimSettings(0.9, 0.8, 50, 45)
    rate = false_claim_rate(settings, share_good=0.98, bad_rate=0.0, repetitions=200, seed=11)
    assert rate > 0.9


# ----------------------------------------------------------------------------- a real certified run
@pytest.fixture(scope="module")
def certified_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The pendulum near upright on the swing-ups' set, certified for success with one expert call."""
    folder = tmp_path_factory.mktemp("near-upright")
    text = EXAMPLE.read_text()
    text = text.replace("hinge = { position = [-3.14159, 3.14159] }", "hinge = { position = [-0.05, 0.05] }")
    text = text.replace("horizon = 1000 ", "horizon = 100  ").replace("last_seconds = 1.0", "last_seconds = 0.5")
    (folder / "pendulum.xml").write_text((EXAMPLE.parent / "pendulum.xml").read_text())
    (folder / "task.toml").write_text(text)
    name = str(folder / "task.toml")
    config = build_config(
        name, 0, LipschitzConstant(50.0, "user"), 130.0, horizon=HORIZON, certify="success", policy="feedback",
        uncertainty=1.0,
    )  # fmt: skip
    run = folder / "run"
    run.mkdir()
    loop = build_loop(config, get_task(name).make_expert(0, HORIZON), store_path=run / "run.sqlite")
    result = loop.run(60)
    assert result.certificate is not None
    assert loop.store is not None
    loop.store.close()
    return run


def fresh_copy(run: Path, tmp_path: Path) -> Path:
    target = tmp_path / "run"
    shutil.copytree(run, target)
    return target


def test_rollouts_on_one_robot_in_lockstep_equal_the_rollouts_one_at_a_time() -> None:
    """Four starts on a delayed, heavier, weaker pendulum, under a saturating feedback law: the same states bit for
    bit as npp_ros.tasks.rollout one start at a time (each start has its own delay queue; no reward is computed)."""
    task = get_task("pendulum_swingup")
    plant = task.make_plant(0)
    robot = Robot((("mass", "pole", 1.15), ("gear", "torque", 0.85), ("damping", "hinge", 1.4)), action_delay=1)
    gain = np.array([[-6.0, -1.5]])

    def controller(states: np.ndarray) -> np.ndarray:
        return np.clip(np.atleast_2d(states) @ gain.T, -1, 1)

    starts = claim_starts(task, 0, 3, 4)
    together = rollouts_on_robot(plant, controller, starts, 80, robot)
    for states, s0 in zip(together, starts, strict=True):
        assert np.array_equal(states, rollout(plant, lambda x: controller(x)[0], s0, 80, robot).states)
    assert not np.array_equal(together[0], rollout(plant, lambda x: controller(x)[0], starts[0], 80).states)


def test_a_claim_on_a_certified_run_is_kept_and_says_what_it_claims(certified_run: Path, tmp_path: Path) -> None:
    folder = fresh_copy(certified_run, tmp_path)
    run = read_run(folder)
    settings = ClaimSettings(0.5, 0.5, 5, 4, 0.1, "sequential")  # beta = P(Bin(5, 0.5) >= 4) = 0.1875
    lines: list[str] = []
    claim = claim_for_run(run, settings, max_checks=30, progress=lines.append)
    assert claim.certified and claim.stopped == "certified"
    assert claim.robot_checks == 8 and claim.rollouts == 8 * 5 and claim.expert_calls == 0  # ln(20) / 0.41 -> 8
    assert claim.beta == pytest.approx(0.1875) and claim.target == pytest.approx(0.59375)
    assert (
        "P_(theta~Theta)[P_(s0~rho)[" in claim.statement and "nor that every robot of the set is one" in claim.statement
    )
    assert "for any robot" not in claim.text() and "no expert call" in claim.text()
    assert claim.seen.startswith("of 8 robots, ") and "not a claim" in claim.seen
    record = json.loads(claim_file(folder, settings).read_text())
    assert record["claim"]["certified"] and len(record["checks"]) == 8
    assert str(folder.parent) not in json.dumps(record["claim"])  # the record names the folder, not this machine
    # A check is a function of (seed, index) only: its robot is the set's draw at its own index.
    robots = run.robots
    assert robots is not None
    assert [c["robot"] for c in record["checks"]] == [claim_robot(robots, 0, i).record() for i in range(8)]
    assert robots.draw(0, CLAIM_INDEX).record() == record["checks"][0]["robot"]
    assert len(lines) == 9 and "robot check    8" in lines[-1]


def test_a_stopped_claim_goes_on_from_its_checks_and_another_claim_reuses_them(
    certified_run: Path, tmp_path: Path
) -> None:
    folder = fresh_copy(certified_run, tmp_path)
    run = read_run(folder)
    settings = ClaimSettings(0.5, 0.5, 5, 4, 0.1, "sequential")
    made: list[str] = []

    def stop_after_three(line: str) -> None:
        made.append(line)
        if len(made) == 4:  # the opening line and three checks
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        claim_for_run(run, settings, max_checks=30, progress=stop_after_three)
    kept = json.loads(claim_file(folder, settings).read_text())["checks"]
    assert [c["index"] for c in kept] == [0, 1, 2]
    again: list[str] = []
    claim = claim_for_run(read_run(folder), settings, max_checks=30, progress=again.append)
    assert "3 robot checks kept" in again[0] and sum(" kept |" in line for line in again) == 3
    assert claim.certified and claim.robot_checks == 8
    fresh = robot_check(run.task, run.task.make_plant(0), run.policy, run.robots, 0, HORIZON, 2, 5)  # type: ignore[arg-type]
    assert kept[2] == {"index": 2, "robot": fresh.robot, "successes": fresh.successes}
    # Another claim with the same m takes the checks made, and draws no new one where those suffice.
    other = ClaimSettings(0.4, 0.5, 5, 4, 0.1, "sequential")
    heard: list[str] = []
    assert claim_for_run(read_run(folder), other, max_checks=30, progress=heard.append).certified
    assert "8 robot checks kept" in heard[0] and all(" kept |" in line for line in heard[1:])


def test_what_cannot_be_claimed_is_refused_in_one_line(certified_run: Path, tmp_path: Path) -> None:
    run = read_run(fresh_copy(certified_run, tmp_path))
    settings = ClaimSettings(0.5, 0.5, 5, 4, 0.1, "sequential")
    refusals = {
        "is on the exact model": replace(run, metadata=type(run.metadata)(**{**vars(run.metadata), "uncertainty": ""})),
        "holds no certificate": replace(run, certificate=None),
    }
    for reason, broken in refusals.items():
        with pytest.raises(ValueError, match=reason) as caught:
            claim_for_run(broken, settings)
        assert "\n" not in str(caught.value)
    with pytest.raises(ValueError, match="impossible at these settings: the sequential rule needs at least 8"):
        claim_for_run(run, settings, max_checks=5)
    with pytest.raises(ValueError, match="c must be an integer in"):
        ClaimSettings(0.9, 0.8, 50, 51)


def test_npp_robots_claims_maps_and_refuses(
    certified_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = fresh_copy(certified_run, tmp_path)
    assert cli.main(["claim", str(folder), "--q", "0.5", "--p-r", "0.5", "--m", "5", "--beta", "0.2",
                     "--rule", "sequential", "--json", str(tmp_path / "claim.json")]) == 0  # fmt: skip
    out, err = capsys.readouterr()
    assert "PER-ROBOT CLAIM" in out and "certified" in out and "robot check" in err
    assert json.loads((tmp_path / "claim.json").read_text())["c"] == 4
    assert cli.main(["claim", str(folder), "--m", "5", "--p-r", "0.9", "--beta", "0.05"]) == 2
    assert "use more starts per robot" in capsys.readouterr().err
    assert cli.main(["map", str(folder), "--figure", str(tmp_path / "map.png")]) == 0
    out = capsys.readouterr().out
    assert "gear[torque]/mass[pole]" in out and (tmp_path / "map.png").stat().st_size > 10_000
    assert cli.main(["threshold", "--m", "50", "--p-r", "0.8"]) == 0
    assert "pass at >= 45 successes" in capsys.readouterr().out


def test_the_run_gives_its_map(certified_run: Path) -> None:
    run: Run = read_run(certified_run)
    success = run.success_map
    assert success is not None
    checked = [row for row in run.episodes if row.policy_success is not None]
    assert success.policy.judged == len(checked) and success.expert.judged == 1
    delay = next(t for t in success.tables if t.axis.name == "delay")
    assert sum(t.judged for t in delay.policy) == len(checked)


def test_a_survey_goes_on_past_the_point_where_the_claim_is_out_of_reach() -> None:
    """One robot in four fails: after the first failure the mixture rule cannot certify within 60 checks, and stops
    there unless asked for 40 checks at least; the pass rate's upper bound then says the target is out of reach."""
    settings = ClaimSettings(0.9, 0.8, 50, 45)
    successes = [50, 50, 50, 10] * 25
    early = decide(settings, lambda i: successes[i], 60)
    assert not early.certified and early.stopped == "unreachable" and early.checks == 4
    survey = decide(settings, lambda i: successes[i], 60, min_checks=40)
    assert not survey.certified and survey.checks == 40 and survey.passed == 30
    assert pass_rate_upper(30, 40, 0.1) < settings.target < pass_rate_upper(40, 40, 0.1)
    with pytest.raises(ValueError, match="min checks"):
        decide(settings, lambda i: successes[i], 10, min_checks=20)
