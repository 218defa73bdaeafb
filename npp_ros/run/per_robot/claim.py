"""A claim about the robots themselves: with probability >= 1 - delta, P_theta[r(theta) >= p_r] >= q.

A certificate over a set bounds P_((s0, theta) ~ rho x Theta)[success], an average over robots: writing
r(theta) = P_(s0 ~ rho)[success | theta], it allows r = 0 on a fifth of the set. This claim bounds the share of
robots on which the policy succeeds often: Q(q, p_r).

How (docs/concepts.md, "A claim about each robot"). Robot check i draws theta_i ~ Theta and m starts s0 ~ rho, each
from the run's seed and i only on streams of their own (no episode of a run, no held-out check draws them), rolls the
run's frozen certified policy out on theta_i from each start, and passes when its successes X_i >= c. Given theta,
X ~ Binomial(m, r(theta)), and P(X >= c) grows with r, so for a robot with r(theta) < p_r a check passes with
probability at most beta = P(Binomial(m, p_r) >= c). With G the event r(theta) >= p_r:

    P(pass) <= P(G) + beta (1 - P(G)),  so  P(pass) >= q + beta (1 - q)  implies  P(G) >= q.

The checks are i.i.d. given the frozen policy, so any of npp_ros's stopping rules (npp_ros.certificate) certifies
P(pass) >= q + beta (1 - q) at level delta, and the claim follows. No expert is asked: m rollouts per check.

A check is a function of (seed, index, m, the policy) only, so it is kept in the run folder as it is made (one JSON
file per claim, rewritten atomically after every check) and a stopped claim goes on from the checks it made; a claim
with the same m on the same run takes the checks another claim made there, the same ones it would draw.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.stats import beta as beta_dist
from scipy.stats import binom

from npp_ros.certificate.certifier import (
    SUCCESS_CHECK,
    SUCCESS_EPSILON,
    CertificationSpec,
    CertificationStatus,
    Certifier,
    StoppingRule,
)
from npp_ros.certificate.mixture import MixtureCertifier, certifier_for
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run import defaults
from npp_ros.tasks.registry import Plant, Task, task_label
from npp_ros.tasks.suite_plant import SuitePlant
from npp_ros.tasks.uncertainty import Robot, RobotEffects, UncertaintySet, as_robot

if TYPE_CHECKING:
    from npp_ros.run.read import Run

CLAIM_INDEX = 1 << 31  # check i draws theta at episode index CLAIM_INDEX + i: no run (< 2^30), no held-out check
START_STREAM = 2  # the spawn key of a check's starts beside theta's (ROBOT_STREAM, 1)
DEFAULT_RULE: StoppingRule = "mixture"  # a frozen policy learns nothing from a failure (docs: which rule, when)
DEFAULT_BETA = 0.05
DEFAULT_MAX_CHECKS = 400
CLAIM_FILE = "robot-claim-{key}.json"
NO_EXPERT = "no expert call: each robot check is m rollouts of the frozen policy on its robot"


def binomial_tail(m: int, p: float, c: int) -> float:
    """P(Binomial(m, p) >= c)."""
    return float(binom.sf(c - 1, m, p))


def threshold_for(m: int, p_r: float, beta: float = DEFAULT_BETA) -> tuple[int, float]:
    """The smallest c with P(Binomial(m, p_r) >= c) <= ``beta`` (the most lenient pass that keeps beta), and that
    tail; a ValueError where even c = m keeps it above ``beta`` (more starts per check are needed)."""
    check_counts(m, p_r)
    if not 0 < beta < 1:
        raise ValueError(f"beta must lie in (0, 1), got {beta!r}")
    for c in range(1, m + 1):
        tail = binomial_tail(m, p_r, c)
        if tail <= beta:
            return c, tail
    raise ValueError(
        f"with m = {m} starts no pass threshold keeps beta <= {beta:g} at p_r = {p_r:g} (all {m} met: "
        f"beta = {p_r**m:.3g}): use more starts per robot"
    )


def check_counts(m: int, p_r: float) -> None:
    if isinstance(m, bool) or not isinstance(m, int) or m < 1:
        raise ValueError(f"m (starts per robot check) must be an integer >= 1, got {m!r}")
    if not 0 < p_r < 1:
        raise ValueError(f"p_r must lie in (0, 1), got {p_r!r}")


@dataclass(frozen=True)
class ClaimSettings:
    """Q(q, p_r) with m starts per robot, passing at c successes, at level delta under a stopping rule."""

    q: float
    p_r: float
    m: int
    c: int
    delta: float = defaults.DELTA  # the run's own level unless the claim names another
    rule: StoppingRule = DEFAULT_RULE

    def __post_init__(self) -> None:
        check_counts(self.m, self.p_r)
        if not 0 < self.q < 1:
            raise ValueError(f"q must lie in (0, 1), got {self.q!r}")
        if not 0 < self.delta < 1:
            raise ValueError(f"delta must lie in (0, 1), got {self.delta!r}")
        if isinstance(self.c, bool) or not isinstance(self.c, int) or not 1 <= self.c <= self.m:
            raise ValueError(f"c must be an integer in [1, m = {self.m}], got {self.c!r}")
        if self.rule not in ("sequential", "mixture"):
            raise ValueError(f"the claim's rule must be sequential or mixture (valid however often looked at), "
                             f"got {self.rule!r}")  # fmt: skip

    @property
    def beta(self) -> float:
        """The most a robot with r(theta) < p_r passes a check: P(Binomial(m, p_r) >= c)."""
        return binomial_tail(self.m, self.p_r, self.c)

    @property
    def target(self) -> float:
        """What the robot checks must certify: P(pass) >= q + beta (1 - q)."""
        return self.q + self.beta * (1 - self.q)

    @property
    def key(self) -> str:
        return f"q{self.q:g}-pr{self.p_r:g}-m{self.m}-c{self.c}-delta{self.delta:g}-{self.rule}"

    def spec(self) -> CertificationSpec:
        """The stopping rule's spec: condition (i) on P(pass) >= target, a success claim (it bounds no gap, so no L
        is read)."""
        unused = LipschitzConstant(1.0, "user", "not read: a success claim bounds no gap")
        return CertificationSpec("i", SUCCESS_EPSILON, self.target, self.delta, unused, certify="success",
                                 rule=self.rule)  # fmt: skip


def claim_certifier(spec: CertificationSpec) -> Certifier | MixtureCertifier:
    """The rule's certifier with its first test open: the policy is frozen before the first robot check (a run's
    certifier begins with an episode that has no policy; here there is one from the start)."""
    certifier = certifier_for(spec)
    if isinstance(certifier, Certifier):
        certifier.tests = 1
    return certifier


@dataclass(frozen=True)
class RobotCheck:
    """One robot check as kept: its index, its robot (Robot.record()) and its successes of m starts."""

    index: int
    robot: str
    successes: int


@dataclass(frozen=True)
class ClaimOutcome:
    """Where the rule stands after the checks fed to it, and why it stopped."""

    certified: bool
    checks: int  # robot checks the rule used
    passed: int
    status: CertificationStatus
    stopped: str  # "certified", "budget" (max checks reached) or "unreachable" (the rule could not certify in time)


def decide(
    settings: ClaimSettings,
    successes: Callable[[int], int],
    max_checks: int,
    on_check: Callable[[int, int, CertificationStatus], None] | None = None,
    min_checks: int = 0,
) -> ClaimOutcome:
    """Feeds robot checks 0, 1, ... (``successes(i)``: X_i) to the claim's rule until it certifies, reaches
    ``max_checks``, or, after ``min_checks`` (a survey of the set beside the claim), cannot certify within them.
    When to stop is free under a sequentially valid rule: stopping early only gives up chances to certify."""
    if not 1 <= max_checks or not 0 <= min_checks <= max_checks:
        raise ValueError(f"need 0 <= min checks <= max checks and max checks >= 1, got {min_checks}, {max_checks}")
    spec = settings.spec()
    certifier = claim_certifier(spec)
    passed = 0
    status = certifier.status()
    if status.reachable_within(max_checks) is False:
        return ClaimOutcome(False, 0, 0, status, "unreachable")
    for i in range(max_checks):
        x = successes(i)
        ok = x >= settings.c
        passed += ok
        status = certifier.observe(SUCCESS_CHECK[ok], failed=not ok)
        if on_check is not None:
            on_check(i, x, status)
        if status.certified:
            return ClaimOutcome(True, i + 1, passed, status, "certified")
        if i + 1 >= min_checks and status.reachable_within(max_checks - i - 1) is False:
            return ClaimOutcome(False, i + 1, passed, status, "unreachable" if i + 1 < max_checks else "budget")
    return ClaimOutcome(False, max_checks, passed, status, "budget")


def checks_needed(settings: ClaimSettings) -> int:
    """The fewest robot checks after which the rule could certify (every check passing)."""
    status = claim_certifier(settings.spec()).status()
    assert status.episodes_to_certify is not None
    return status.episodes_to_certify


# ---------------------------------------------------------------------------------------------- the robot checks
def claim_robot(robots: UncertaintySet, seed: int, index: int) -> Robot:
    """theta of robot check ``index``: the set's own draw at an episode index no run reaches."""
    return robots.draw(seed, CLAIM_INDEX + index)


def claim_starts(task: Task, seed: int, index: int, m: int) -> FloatArray:
    """The m starts s0 ~ rho of robot check ``index``, on a stream of their own."""
    rng = np.random.default_rng([int(seed), CLAIM_INDEX + int(index), START_STREAM])
    return np.array([task.sample_initial_state(rng) for _ in range(m)])


def advance(plant: Plant) -> Callable[[Any, FloatArray], None]:
    """How to step a clone of ``plant`` one control step when only its states are wanted: a dm_control suite plant
    as its own ``step`` does, without computing the reward (half a cart-pole step's time); any other plant by its
    ``step``. ``rollouts_on_robot``'s test holds the states equal to npp_ros.tasks.rollout's, bit for bit."""
    if isinstance(plant, SuitePlant) and type(plant).step is SuitePlant.step:

        def physics_only(clone: Any, action: FloatArray) -> None:
            clone.physics.set_control(np.clip(clone.check_action(action), clone.action_low, clone.action_high))
            clone.physics.step(clone.substeps)
            clone.steps += 1

        return physics_only
    return lambda clone, action: clone.step(action)


def rollouts_on_robot(
    plant: Plant, controller: Callable[[FloatArray], Any], starts: FloatArray, horizon: int, robot: Robot
) -> FloatArray:
    """The states of rollouts from many s0 on one robot, shape (starts, horizon, state_dim): stepped in lockstep on
    plant clones (which share the robot's model), each with its own delay queue and noise; the same states as
    npp_ros.tasks.rollout.rollout one s0 at a time, faster (one policy query per step, no rewards)."""
    count = len(starts)
    states = np.empty((count, horizon, plant.state_dim))
    effects = [RobotEffects(robot, plant.action_dim) for _ in range(count)]
    step = advance(plant)
    with as_robot(plant, robot):
        plants = [plant.clone() for _ in range(count)]
        x = np.array([p.reset(s0) for p, s0 in zip(plants, starts, strict=True)])
        for t in range(horizon):
            read = np.array([e.observe(x[k]) for k, e in enumerate(effects)])
            u = np.asarray(controller(read), dtype=np.float64).reshape(count, plant.action_dim)
            states[:, t] = x
            for k, p in enumerate(plants):
                step(p, effects[k].command(u[k]))
                x[k] = p.state()
    return states


def robot_check(
    task: Task,
    plant: Plant,
    policy: NonparametricPolicy,
    robots: UncertaintySet,
    seed: int,
    horizon: int,
    index: int,
    m: int,
) -> RobotCheck:
    """Robot check ``index``: its robot, its m starts, the policy's rollouts there, the successes counted."""
    if task.success is None:
        raise ValueError(f"{task.name} states no success criterion: there is no success to count on a robot")
    robot = claim_robot(robots, seed, index)
    runs = rollouts_on_robot(plant, policy.controller(), claim_starts(task, seed, index, m), horizon, robot)
    return RobotCheck(index, robot.record(), sum(task.success.met(states) for states in runs))


# ---------------------------------------------------------------------------------------------- the kept checks
def policy_identity(
    task: str, seed: int, horizon: int, robots: str, policy: NonparametricPolicy, kind: str, m: int
) -> str:
    """What a robot check depends on, hashed: the task, seed, horizon, set, the policy's data and kind, and m."""
    digest = hashlib.sha256()
    for part in (task, str(seed), str(horizon), robots, kind, str(m)):
        digest.update(part.encode() + b"\0")
    data = policy.dataset
    for array in (data.states, data.actions, data.values):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


def write_atomically(path: Path, record: dict[str, Any]) -> None:
    """The file is the old one or the new one, never a torn one: a synced temporary file moved over it."""
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as f:
        json.dump(record, f, indent=1)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_claim_file(path: Path) -> dict[str, Any] | None:
    """A claim file's record; None where there is none or it is no JSON record (an atomic write leaves none torn)."""
    try:
        record = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return record if isinstance(record, dict) else None


def kept_checks(folder: Path, identity: str) -> list[RobotCheck]:
    """The robot checks of this identity already made in ``folder`` by any claim, from index 0 without a gap."""
    found: dict[int, RobotCheck] = {}
    for path in sorted(folder.glob(CLAIM_FILE.format(key="*"))):
        record = read_claim_file(path)
        if record is None or record.get("identity") != identity:
            continue
        for item in record.get("checks", []):
            try:
                check = RobotCheck(int(item["index"]), str(item["robot"]), int(item["successes"]))
            except (KeyError, TypeError, ValueError):
                continue
            found.setdefault(check.index, check)
    checks = []
    while len(checks) in found:
        checks.append(found[len(checks)])
    return checks


@dataclass(frozen=True)
class RobotClaim:
    """The claim as a user reads it and the run folder keeps it."""

    task: str
    run: str  # the run folder's name
    robots: str  # the set in words
    policy: str  # which frozen policy
    q: float
    p_r: float
    m: int
    c: int
    beta: float
    target: float  # P(pass) the checks certify: q + beta (1 - q)
    delta: float
    rule: str
    certified: bool
    stopped: str
    robot_checks: int
    passed: int
    rollouts: int
    expert_calls: int
    test: int
    delta_spent: float
    statement: str
    seen: str = ""  # what the checks' success counts show, robot by robot: a description, not a claim

    def text(self) -> str:
        return "\n".join([
            f"PER-ROBOT CLAIM ({task_label(self.task)}, run {self.run}): "  # the task file's name, not its path
            f"{'certified' if self.certified else 'NOT certified'}",
            f"  set             {self.robots}",
            f"  policy          {self.policy}",
            f"  q, p_r, delta   {self.q:g}, {self.p_r:g}, {self.delta:g}",
            f"  m, c, beta      {self.m} starts per robot, pass at >= {self.c} successes, "
            f"beta = P(Binomial({self.m}, {self.p_r:g}) >= {self.c}) = {self.beta:.4f}",
            f"  checked         P(pass) >= q + beta (1 - q) = {self.target:.4f}, rule {self.rule}",
            f"  robot checks    {self.robot_checks} ({self.passed} passed), {self.rollouts} rollouts, "
            f"{self.expert_calls} expert calls ({NO_EXPERT})",
            f"  test            {self.test}, spent delta {self.delta_spent:.4g}",
            f"  statement       {self.statement}",
            *([f"  seen            {self.seen}"] if self.seen else []),
        ])  # fmt: skip


SEEN_BANDS = (1.0, 0.95, 0.9, 0.8, 0.5)  # the success shares robots are counted above, in what a claim saw


def pass_rate_upper(passed: int, checks: int, delta: float) -> float:
    """The one-sided Clopper-Pearson upper bound on P(pass) at level delta from ``passed`` of ``checks`` (a count
    fixed in advance): an upper bound below the claim's target says the target is out of reach at these m and c."""
    return 1.0 if passed >= checks else float(beta_dist.ppf(1 - delta, passed + 1, checks - passed))


def seen_counts(successes: Sequence[int], settings: ClaimSettings) -> str:
    """The robots of the checks by their share of successes of m: a plug-in description of r(theta) over the set
    (each share is r(theta) measured on m starts), which the checks saw and no rule certified; and the pass rate with
    its upper bound."""
    if not successes:
        return ""
    m, p_r = settings.m, settings.p_r
    passed = sum(x >= settings.c for x in successes)
    upper = pass_rate_upper(passed, len(successes), settings.delta)
    shares = np.asarray(successes, dtype=np.float64) / m
    bands = ", ".join(f">= {band:g}: {int(np.sum(shares >= band - 1e-12))}" for band in SEEN_BANDS)
    reached = int(np.sum(shares >= p_r - 1e-12))
    return (
        f"of {len(shares)} robots, {reached} ({reached / len(shares):.0%}) met the task on at least p_r = {p_r:g} of "
        f"their {m} starts; robots by their share of starts met: {bands}; the lowest {shares.min():.2f}, the median "
        f"{float(np.median(shares)):.2f}; passed {passed} of {len(shares)}, P(pass) <= {upper:.3f} with probability "
        f"{1 - settings.delta:g} (Clopper-Pearson, as if the count were fixed in advance) against the target "
        f"{settings.target:.4f} (what the checks saw, not a claim)"
    )


def claim_statement(settings: ClaimSettings, outcome: ClaimOutcome, robots: str, policy: str) -> str:
    """The claim in words, or why it was not made; never a statement about every robot of the set."""
    robot_share = (
        f"P_(theta~Theta)[P_(s0~rho)[the policy's rollout from s0 on theta meets the task's success criterion] >= "
        f"{settings.p_r:g}] >= {settings.q:g}"
    )
    if not outcome.certified:
        why = {
            "budget": "the robot checks ran out before the rule certified",
            "unreachable": "the rule could no longer certify within the robot checks allowed",
        }[outcome.stopped]
        return (
            f"Not claimed: {robot_share} ({why}: {outcome.passed} of {outcome.checks} robot checks passed, against "
            f"a pass rate of {settings.target:.4f} to certify). Nothing is claimed about the robots of the set."
        )
    return (
        f"With probability at least {1 - settings.delta:.4g}, {robot_share}, for {policy}, Theta being {robots}: "
        f"the share of robots of the set on which the policy succeeds from at least {settings.p_r:.0%} of the "
        f"initial states is at least {settings.q:.0%}. It says nothing about which robots those are, nor that "
        f"every robot of the set is one ({outcome.checks} robot checks of {settings.m} rollouts each, "
        f"{outcome.passed} passed at >= {settings.c} successes; beta = {settings.beta:.4f}; rule {settings.rule}; "
        "no expert call)."
    )


def make_claim(
    settings: ClaimSettings,
    check: Callable[[int], RobotCheck],
    *,
    file: Path | None = None,
    header: dict[str, Any] | None = None,
    kept: Sequence[RobotCheck] = (),
    max_checks: int = DEFAULT_MAX_CHECKS,
    min_checks: int = 0,
    on_check: Callable[[RobotCheck, CertificationStatus, bool], None] | None = None,
) -> tuple[ClaimOutcome, list[RobotCheck]]:
    """Runs the claim's rule over robot checks: ``kept`` ones first (never drawn again), then ``check(i)`` for the
    rest, each written to ``file`` (with ``header``) as soon as it is made. ``on_check`` hears each check, the
    rule's status and whether it was kept."""
    made = list(kept)
    for k, item in enumerate(made):
        if item.index != k:
            raise ValueError(f"kept robot check {k} has index {item.index}: the checks must run from 0 without a gap")

    def successes(i: int) -> int:
        if i < len(made):
            return made[i].successes
        item = check(i)
        if item.index != i or not 0 <= item.successes <= settings.m:
            raise ValueError(f"robot check {i} came back as {item}")
        made.append(item)
        if file is not None:
            write_atomically(file, {**(header or {}), "checks": [asdict(c) for c in made]})
        return item.successes

    def heard(i: int, x: int, status: CertificationStatus) -> None:
        if on_check is not None:
            on_check(made[i], status, i < len(kept))

    outcome = decide(settings, successes, max_checks, heard, min_checks)
    return outcome, made[: max(outcome.checks, len(kept))]


def claim_file(folder: Path, settings: ClaimSettings) -> Path:
    return Path(folder) / CLAIM_FILE.format(key=settings.key)


def finished_record(header: dict[str, Any], claim: RobotClaim, checks: Sequence[RobotCheck]) -> dict[str, Any]:
    return {**header, "claim": asdict(claim), "checks": [asdict(c) for c in checks]}


def as_settings(q: float, p_r: float, m: int, c: int | None, beta: float, delta: float, rule: str) -> ClaimSettings:
    """The settings of a command line: c chosen for ``beta`` where not given."""
    if c is None:
        c, _ = threshold_for(m, p_r, beta)
    return ClaimSettings(q, p_r, m, c, delta, rule)  # type: ignore[arg-type]


def reachable(settings: ClaimSettings, max_checks: int) -> None:
    """A ValueError, in one line, where the rule cannot certify within ``max_checks`` robot checks even if every
    one passes."""
    need = checks_needed(settings)
    if need > max_checks:
        raise ValueError(
            f"impossible at these settings: the {settings.rule} rule needs at least {need} robot checks, all passing, "
            f"to certify P(pass) >= {settings.target:.4f} (q {settings.q:g}, beta {settings.beta:.3g}), more than the "
            f"{max_checks} allowed"
        )


def claim_for_run(
    run: Run,
    settings: ClaimSettings,
    *,
    max_checks: int = DEFAULT_MAX_CHECKS,
    min_checks: int = 0,
    progress: Callable[[str], None] | None = None,
) -> RobotClaim:
    """Q(q, p_r) for a certified run on a set: its frozen policy checked on robots drawn from the set, the checks
    kept in the run folder as they are made (a stopped claim goes on from them), the claim written there at the end.

    A ValueError, in one line, where no claim can be made: a run on the exact model, one without a certificate, a
    task without a success criterion, settings no rule can certify within ``max_checks``; or where the claim's file
    holds checks of another policy."""
    name = run.folder.name
    if run.robots is None:
        raise ValueError(f"run {name} is on the exact model: there is one robot, and its certificate speaks of it")
    if run.certificate is None:
        raise ValueError(f"run {name} holds no certificate: there is no frozen certified policy to make a claim about")
    if run.task.success is None:
        raise ValueError(f"{run.task.name} states no success criterion: there is no success to count on a robot")
    reachable(settings, max_checks)
    seed, horizon = int(run.metadata.seed), int(run.metadata.horizon)
    policy = run.policy
    identity = policy_identity(
        run.task.name, seed, horizon, str(run.metadata.uncertainty), policy, run.spec.policy, settings.m
    )
    path = claim_file(run.folder, settings)
    own = read_claim_file(path)
    if own is not None and own.get("identity") != identity:
        raise ValueError(
            f"{path.name} holds robot checks of another policy or m than run {name}'s certified one: move it away "
            "to make this claim afresh"
        )
    kept = kept_checks(run.folder, identity)
    header = {"identity": identity, "settings": asdict(settings), "beta": settings.beta, "target": settings.target}
    plant = run.task.make_plant(seed)
    robots = run.robots
    count = run.certificate.policy_trajectories
    described = (
        f"the {run.spec.policy} policy over the certificate's {count} expert "
        f"{'trajectory' if count == 1 else 'trajectories'} (run {name}), frozen"
    )

    def check(i: int) -> RobotCheck:
        return robot_check(run.task, plant, policy, robots, seed, horizon, i, settings.m)

    def heard(item: RobotCheck, status: CertificationStatus, was_kept: bool) -> None:
        if progress is None:
            return
        verdict = "pass" if item.successes >= settings.c else "FAIL"
        where = Robot.from_record(item.robot).describe()
        stage = (
            f"verification {status.test}: {status.window} checks, {status.failures} failed, needs {status.required}"
            if status.stage == "verification"
            else f"screen {status.window}/{status.required}" if status.stage == "screen"
            else f"test {status.test}: {status.window}/{status.required} in a row"
        )  # fmt: skip
        progress(
            f"robot check {item.index + 1:4d} | {item.successes:3d}/{settings.m} met {verdict} (c {settings.c})"
            f"{' kept' if was_kept else ''} | {where} | {stage}"
        )

    if progress is not None:
        progress(
            f"claim Q(q {settings.q:g}, p_r {settings.p_r:g}) on run {name}: {settings.m} rollouts per robot, pass at "
            f">= {settings.c} (beta {settings.beta:.4f}), certify P(pass) >= {settings.target:.4f} by the "
            f"{settings.rule} rule; {len(kept)} robot checks kept in the run folder"
        )
    outcome, checks = make_claim(
        settings,
        check,
        file=path,
        header=header,
        kept=kept,
        max_checks=max_checks,
        min_checks=min_checks,
        on_check=heard,
    )
    claim = RobotClaim(
        task=run.task.name, run=name, robots=robots.describe(), policy=described, q=settings.q, p_r=settings.p_r,
        m=settings.m, c=settings.c, beta=settings.beta, target=settings.target, delta=settings.delta,
        rule=settings.rule, certified=outcome.certified, stopped=outcome.stopped, robot_checks=outcome.checks,
        passed=outcome.passed, rollouts=outcome.checks * settings.m, expert_calls=0,
        test=outcome.status.test, delta_spent=outcome.status.test_delta,
        statement=claim_statement(settings, outcome, robots.describe(), described),
        seen=seen_counts([c.successes for c in checks[: outcome.checks]], settings),
    )  # fmt: skip
    write_atomically(path, finished_record(header, claim, checks))
    return claim


def stderr_progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
