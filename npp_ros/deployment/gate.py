"""The gate: whether a run folder may command a robot, and the policy its certificate names.

No ROS here: npp-deploy (``npp_ros_graph/nodes/deploy/node.py``) calls :func:`load_deployment` at configure.
It refuses:

- a folder without a readable run file, or one whose data fail their SHA-256 checks (altered or
  damaged), or whose certificate does not follow from its own episode log (an edited certificate);
- a run without a certificate, or with one that is not proven;
- a certificate weaker than the operator accepts (epsilon, p, delta);
- a robot whose model fingerprint is not the certified plant's, or, for a run certified on a set of
  robots, whose description lies outside the set (robot_set.py);
- a run that does not follow from its own seed and stored expert answers (npp_ros.run.rederive): every episode's
  s0 and robot drawn again, every check re-run with the policy as it then was, the certificate issued again, and
  compared with the file; the first episode that differs is named. No override: an operator who knows why may
  turn the re-derivation off (``Acceptance.rederive``).

An operator may override the certificate and fingerprint checks (``Acceptance.override``), and every
overridden reason is kept for the log and /diagnostics. Nothing overrides a file the store cannot read
(npp_ros/run/read.py): its data are no run's, so there is no policy to deploy.
The run file's seal names any edit after the run, but an editor can seal again: a seal is a checksum anyone
with this code can recompute, not a proof of who wrote the run. Trusted keys (``Acceptance.trusted_keys``,
signing.py) make the gate require the signature of one of them over the seal: that is the proof. A file without
a seal is refused unless the operator allows unsealed files by name (``Acceptance.allow_unsealed``), since
dropping the seal table is itself an edit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from npp_ros.certificate.certifier import Certificate
from npp_ros.certificate.mixture import certifier_for
from npp_ros.deployment.robot_set import gate_reasons
from npp_ros.deployment.signing import signature_reasons
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.read import Run, read_run
from npp_ros.run.records import RunFileError, RunMetadata
from npp_ros.run.rederive import AgreedRuns, rederive
from npp_ros.run.seal import SealCheck
from npp_ros.run.store import RUN_FILE
from npp_ros.tasks.registry import Plant, Task, UnknownTaskError

UNSEALED = SealCheck("", ())


class GateRefusal(ValueError):
    """The gate refuses to deploy a run folder; the message says every reason."""


@dataclass(frozen=True)
class Acceptance:
    """What the operator accepts: the weakest certificate, the robot's model, and whether to override."""

    max_epsilon: float = math.inf
    min_p: float = 0.0
    max_delta: float = 1.0
    model_fingerprint: str = ""  # the robot's; must equal the run's plant fingerprint
    override: bool = False
    trusted_keys: tuple[Ed25519PublicKey, ...] = ()  # given any, only a run signed by one of them passes
    robot_description: str = ""  # the robot's MJCF: a run certified on a set of robots is compared with it
    allow_unsealed: bool = False  # accept a run file without a seal (from before seals): nothing then names an edit
    rederive: bool = True  # derive the run again from its seed and stored answers (rederive.py) and compare

    def __post_init__(self) -> None:
        if not self.max_epsilon > 0:
            raise ValueError(f"max_epsilon must be > 0, got {self.max_epsilon!r}")
        if not 0 <= self.min_p < 1:
            raise ValueError(f"min_p must lie in [0, 1), got {self.min_p!r}")
        if not 0 < self.max_delta <= 1:
            raise ValueError(f"max_delta must lie in (0, 1], got {self.max_delta!r}")


@dataclass(frozen=True)
class Deployment:
    """A run folder that passed the gate (or was let through by an override): the policy it names and its plant.

    ``certificate`` is the run's, None when it has none or one that does not follow from its run (overridden)."""

    run_file: Path
    metadata: RunMetadata
    certificate: Certificate | None
    policy: NonparametricPolicy
    task: Task
    plant: Plant
    checked_starts: FloatArray  # the s0 ~ rho the run checked whose trajectory is not in the policy's data
    overridden: tuple[str, ...] = ()  # the reasons the gate gave and the operator overrode
    seal: SealCheck = UNSEALED  # the run file's seal, intact or absent (a file from before seals)
    signed: str = "unsigned"  # who signed the run, in words (signing.signature_reasons)
    robot: str = ""  # for a run certified on a set of robots: which robot of it the robot's model is, in words
    derived: str = ""  # whether the run was derived again from its seed and answers, and what that found, in words

    @property
    def policy_trajectories(self) -> int:
        return self.policy.dataset.num_trajectories

    def describe(self) -> str:
        """One line: which run, which policy, what its certificate claims."""
        meta, cert = self.metadata, self.certificate
        policy = f"greedy over {self.policy_trajectories} trajectories ({len(self.policy.dataset)} points)"
        policy += f", acting {self.policy.kind}"
        head = f"{meta.task} seed {meta.seed}, {policy}, L {self.policy.lipschitz:g}"
        if cert is None:
            return f"{head}; NO certificate"
        spec = cert.spec
        claim = f"condition ({spec.condition}), epsilon {spec.epsilon:g}, p {spec.p:g}, delta {spec.delta:g}"
        proven = "proven" if cert.proven else "NOT proven"
        robot = f"; robot: {self.robot}" if self.robot else ""
        return f"{head}; certificate {claim}, certify={spec.certify}, H {meta.horizon}, {proven}{robot}"


def load_deployment(
    run_dir: str | Path, acceptance: Acceptance, progress: Callable[[int, int], None] | None = None
) -> Deployment:
    """The gate: the policy a run folder's certificate names, or a GateRefusal with every reason.

    Only what the run file cannot give (npp_ros.run.read) is reported as damage; any other error is raised as itself.
    ``progress(done, total)`` follows the re-derivation of the run's episodes."""
    run_file = _run_file(Path(run_dir))
    try:
        run = read_run(run_file)
    except RunFileError as exc:
        raise GateRefusal(f"the run file was altered or damaged: {exc}") from None
    except UnknownTaskError as exc:
        raise GateRefusal(f"{run_file}: {exc}") from None
    if not run.seal.sealed and not acceptance.allow_unsealed:
        # A seal's absence is no proof of age: dropping the seal table is itself an edit. No override but by name.
        raise GateRefusal(
            f"{run_file} has no seal, so nothing shows it unchanged since its run (a file from before seals, or one "
            "whose seal was removed): resume the run once to seal it (or sign it), or set allow_unsealed to accept "
            "it knowingly"
        )
    # A run the operator asked to be signed by a trusted key and is not: no override, as for altered data.
    unsigned, signed = signature_reasons(run_file.parent, run.seal.digest, acceptance.trusted_keys)
    if unsigned:
        raise GateRefusal("; ".join(unsigned))
    deployment = _pass_gate(run, acceptance)  # the quick checks first: a refusal there needs no re-derivation
    derived = "not derived again (rederive is off)"
    agreed = AgreedRuns()
    before = agreed.find(run.seal.digest) if acceptance.rederive else None
    if before is not None:
        derived = (
            f"derived again from its seed and answers on this machine at {before.get('at')}: "
            f"{before.get('episodes')} episodes agreed (this content, unchanged since)"
        )
    elif acceptance.rederive:
        found = rederive(run, progress)
        if not found.agrees:  # what the run's own seed and answers do not give was edited: no override
            raise GateRefusal(
                f"the run does not follow from its own seed and stored expert answers: {found.differences[0]} (an "
                "edit sealed again, or a run made by a version of npp_ros whose policy acts otherwise)"
            )
        agreed.remember(run.seal.digest, found)
        derived = f"derived again from its seed and answers: {found.episodes} episodes agree ({found.seconds:.1f} s)"
    return dataclasses.replace(deployment, signed=signed, derived=derived)


def _pass_gate(run: Run, acceptance: Acceptance) -> Deployment:
    dataset, certificate, rows = run.dataset, run.certificate, run.episodes
    if dataset.num_trajectories == 0:
        raise GateRefusal(f"{run.file} holds no expert trajectories: there is no policy to deploy")
    inconsistent = [] if certificate is None else _inconsistencies(run, certificate)
    if inconsistent:
        what = "; ".join(inconsistent)
        reasons = [f"the certificate does not follow from the run's own log ({what}): it was altered"]
        certificate = None
    else:
        reasons = _certificate_reasons(certificate, len(rows), dataset.num_trajectories, acceptance)
    plant = run.task.make_plant(run.metadata.seed)
    fingerprint = _fingerprint_reasons(run.metadata, acceptance)
    model_reasons, robot = gate_reasons(run.metadata, plant, acceptance.robot_description, fingerprint)
    reasons += model_reasons
    if reasons and not acceptance.override:
        raise GateRefusal("; ".join(reasons))
    # Overridden: the certificate's policy where the certificate agrees with its run, else all the data.
    count = dataset.num_trajectories if certificate is None else certificate.policy_trajectories
    data = dataset if count == dataset.num_trajectories else dataset.prefix(count)
    policy = run.policy_over(count)
    policy.v_lb(data.states[0])  # builds the search index now: the first state on the robot must not wait for it
    outside = [row.initial_state for row in rows if row.trajectory is None or row.trajectory >= count]
    checked_starts = np.array(outside, dtype=np.float64).reshape(len(outside), run.metadata.state_dim)
    return Deployment(
        run.file, run.metadata, certificate, policy, run.task, plant, checked_starts, tuple(reasons), run.seal,
        robot=robot,
    )  # fmt: skip


def _run_file(run_dir: Path) -> Path:
    if run_dir.is_file():
        return run_dir
    path = run_dir / RUN_FILE
    if not path.is_file():
        where = "does not exist" if not run_dir.exists() else f"holds no {RUN_FILE}"
        raise GateRefusal(f"the run folder {run_dir} {where}: there is no certified run to deploy")
    return path


def _certificate_reasons(
    certificate: Certificate | None, episodes: int, stored: int, acceptance: Acceptance
) -> list[str]:
    """Why a certificate (consistent with its run) may not be deployed: absent, not proven, too weak."""
    if certificate is None:
        return [
            f"the run file holds no certificate ({episodes} episodes, {stored} trajectories): the run was never "
            "certified, or its certificate was removed"
        ]
    spec = certificate.spec
    reasons = []
    if not certificate.proven:
        failing = [text for text in certificate.assumptions if "NOT" in text or "not sequentially" in text]
        why = failing[0] if failing else "it rests on a step that does not hold for this plant"
        reasons.append(f"the certificate is not proven (certify={spec.certify}, rule={spec.rule}: {why})")
    if spec.epsilon > acceptance.max_epsilon:
        reasons.append(
            f"the certificate's epsilon {spec.epsilon:g} is larger than this deployment accepts "
            f"(max_epsilon {acceptance.max_epsilon:g})"
        )
    if spec.condition == "ii" and acceptance.min_p > 0:
        reasons.append(
            "the certificate bounds the mean gap (condition ii) and states no share p of initial states; "
            f"this deployment asks for p >= {acceptance.min_p:g}"
        )
    elif spec.p < acceptance.min_p:
        reasons.append(f"the certificate's p {spec.p:g} is below min_p {acceptance.min_p:g}")
    if spec.delta > acceptance.max_delta:
        reasons.append(
            f"the certificate's delta {spec.delta:g} is larger than this deployment accepts "
            f"(max_delta {acceptance.max_delta:g})"
        )
    return reasons


def _inconsistencies(run: Run, certificate: Certificate) -> list[str]:
    """Where the certificate disagrees with the run's metadata and episode log (replayed through the Certifier)."""
    spec = run.spec
    problems = [
        f"{name} {run.claimed[name]!r} against the run's {value!r}"
        for name, value in spec.record().items()
        if run.claimed[name] != value
    ]
    if certificate.task != run.metadata.task:
        problems.append(f"task {certificate.task!r} against the run's {run.metadata.task!r}")
    if problems:
        return problems
    episodes, trajectories = certificate.episodes, certificate.policy_trajectories
    stored = run.dataset.num_trajectories
    if not 1 <= trajectories <= stored:
        return [f"it names {trajectories} trajectories, the run stores {stored}"]
    if not 1 <= episodes <= len(run.episodes):
        return [f"it was issued at episode {episodes}, the log holds {len(run.episodes)}"]
    # Replay the run's checks through its rule, as a resumed run does: the certificate must be issued at its
    # episode, and its policy holds every trajectory asked for except those a frozen test held back.
    certifier = certifier_for(spec)
    stored = joined = 0
    status = None
    for row in run.episodes[:episodes]:
        passed = spec.passes(row.checked_gap)
        stored += row.trajectories_stored
        status = certifier.observe(math.inf if row.checked_gap is None else row.checked_gap, not passed)
        if not status.frozen:
            joined = stored
    assert status is not None
    found = {"window": status.window, "required": status.required, "test": status.test, "failures": status.failures}
    said = {name: getattr(certificate, name) for name in found}
    if not status.certified or said != found:
        told = ", ".join(f"{name} {value}" for name, value in said.items())
        got = ", ".join(f"{name} {value}" for name, value in found.items())
        return [f"replaying its {episodes} episodes gives certified={status.certified}, {got}; it says {told}"]
    if trajectories != joined:
        return [f"it names {trajectories} trajectories; the first {episodes} episodes gave the policy {joined}"]
    points = int(run.dataset.trajectory_offsets[trajectories])
    if certificate.dataset_size != points:
        return [f"it names {certificate.dataset_size} points; the first {trajectories} trajectories hold {points}"]
    return []


def _fingerprint_reasons(metadata: RunMetadata, acceptance: Acceptance) -> list[str]:
    """Whether the robot is the one the run's data are of: the certified plant's model, or for a run on a robot
    itself, that robot (the fingerprint of the description it published when the run began), and no other."""
    robot = acceptance.model_fingerprint.strip()
    robot_run = str(getattr(metadata, "robot_run", "") or "")
    if robot_run:
        certified = RobotIdentity.from_record(robot_run).fingerprint
        if robot != certified:
            given = f"{robot[:12]}..." if robot else "not given"
            return [
                f"the run was certified on the robot itself, whose model fingerprint is {certified[:12]}...; this "
                f"robot's is {given}: its certificate is of that one robot only"
            ]
        return []
    certified = str(getattr(metadata, "plant_fingerprint", "") or "")
    if not certified:
        return ["the run records no model fingerprint: which plant its data came from is unknown"]
    if not robot:
        return ["no robot model fingerprint was given: the gate cannot check that the robot runs the certified model"]
    if robot != certified:
        return [f"the robot's model (fingerprint {robot[:12]}...) is not the certified one ({certified[:12]}...)"]
    return []
