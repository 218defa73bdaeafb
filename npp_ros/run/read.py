"""A run folder read back, typed and checked: its metadata and spec, its data, its episode log and its certificate.

The one reader of a finished or live run file: ``npp_ros.read_run`` for a script, and the deployment gate
(npp_ros.deployment.gate) before a robot moves, so both see the same run and refuse the same damage. The
certificate is read as the loop reads its own on resume (``Certificate.from_record`` for the spec the run's
metadata records), after every stored value it rests on has been checked to be of its type. What the file
cannot give (a refusal of the store itself: no readable file, a failed checksum, a missing table, values of
another type, a recorded spec that is no spec) is a :class:`RunFileError`: damage or an edit. Anything else
raised here is a bug, and is raised as itself.
"""

from __future__ import annotations

import json
import sqlite3
import types
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

from npp_ros.certificate.certifier import Certificate, CertificationSpec
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.per_robot.success_map import SuccessMap, model_bodies, run_success_map
from npp_ros.run.policy_lipschitz import LipschitzChoice, acted_by
from npp_ros.run.records import EpisodeRow, RobotEpisode, RunFileError, RunMetadata
from npp_ros.run.seal import SealCheck, check_file
from npp_ros.run.setup import policy_for, spec_of
from npp_ros.run.store import RUN_FILE, RunStore
from npp_ros.tasks.registry import Task, get_task, task_label
from npp_ros.tasks.uncertainty import UncertaintySet

# The metadata a reader relies on, with the type each must have (RunConfig.metadata() writes them).
METADATA_TYPES: dict[str, type] = {
    "task": str, "seed": int, "horizon": int, "state_dim": int, "action_dim": int,
    "condition": str, "epsilon": float, "p": float, "delta": float, "certify": str, "rule": str, "policy": str,
    "lipschitz": float, "lipschitz_source": str,
}  # fmt: skip
_KIND_NAMES = {str: "text", int: "an integer", float: "a number", bool: "true or false"}


@dataclass(frozen=True)
class Run:
    """One run file as it is on disk, checked: what it was made for, its data, its log and its certificate.

    ``claimed`` is what the certificate record says it certifies (the spec's fields as it stores them), which the
    gate compares with the run's own ``spec``; ``seal`` is the file's seal, intact or absent (from before seals).
    """

    file: Path
    metadata: RunMetadata
    task: Task
    spec: CertificationSpec
    dataset: Dataset
    episodes: list[EpisodeRow]
    certificate: Certificate | None
    claimed: dict[str, object]
    seal: SealCheck  # intact (or unsealed, from before seals): a broken seal is a RunFileError
    robot_episodes: tuple[RobotEpisode, ...] = ()  # a run on a robot: every episode it ran (npp_ros.run.on_robot)
    # The policy's L the run chose at each data size (policy_lipschitz select; npp_ros.run.policy_lipschitz).
    lipschitz_choices: dict[int, LipschitzChoice] = field(default_factory=dict)

    @property
    def folder(self) -> Path:
        """The run folder (it holds the run file, its signature and the node logs)."""
        return self.file.parent

    @property
    def on_robot(self) -> bool:
        """Whether the run's plant was a robot itself (its checks the robot's own episodes), not a model."""
        return bool(getattr(self.metadata, "robot_run", ""))

    @property
    def robots(self) -> UncertaintySet | None:
        """The set of robots the run drew from and a certificate covers (None: the exact model)."""
        record = str(self.metadata.uncertainty)
        return UncertaintySet.from_record(record) if record else None

    @property
    def expert_model(self) -> str:
        """Under uncertainty, what the expert planned on: each episode's robot, or the nominal model."""
        return str(self.metadata.expert_model)

    @property
    def success_map(self) -> SuccessMap | None:
        """Where in its set the run's policy (in its checks) and its expert (in its answers) failed the task, per bin
        of each drawn parameter (npp_ros.run.per_robot.success_map); None for a run on the exact model."""
        if self.robots is None:
            return None
        named = task_label(self.task.name)  # a task file's name, not its path (the identity stays in the run file)
        source = f"run {self.folder.name} ({named}, seed {self.metadata.seed}, {len(self.episodes)} episodes)"
        bodies = model_bodies(self.task, int(self.metadata.seed))
        return run_success_map(self.robots, self.episodes, source, bodies=bodies)

    @property
    def policy(self) -> NonparametricPolicy:
        """The certificate's policy (its first trajectories, acting as its spec names); uncertified: all the data."""
        count = self.dataset.num_trajectories if self.certificate is None else self.certificate.policy_trajectories
        return self.policy_over(count)

    def policy_over(self, count: int) -> NonparametricPolicy:
        """The run's policy over its first ``count`` trajectories, acting as its spec names, by the L it acted by."""
        data = self.dataset if count == self.dataset.num_trajectories else self.dataset.prefix(count)
        task, seed = str(self.metadata.task), int(self.metadata.seed)
        return policy_for(data, self.spec, task, seed, self.policy_lipschitz(count))

    def policy_lipschitz(self, count: int) -> LipschitzConstant | None:
        """The L the policy over ``count`` trajectories acts by where the run chose its own (None: the claim's): the
        choice at its size's choice point; for data the run's policy never held whole (an uncertified run's data with
        a test's trajectories held back), the last choice it made below that."""
        return acted_by(self.lipschitz_choices, count)


def read_run(folder: str | Path) -> Run:
    """A run folder (or its run.sqlite) read back; never takes the writer's lock, so a live run goes on.

    A RunFileError for what the file cannot give (no run file, a broken seal, a missing table, values of
    another type, a recorded spec that is no spec), an UnknownTaskError for a task that does not load here.
    """
    path = Path(folder)
    run_file = path if path.is_file() else path / RUN_FILE
    if not run_file.is_file():
        raise RunFileError(f"{path} holds no {RUN_FILE}: no run was stored there")
    try:
        store = RunStore.open(run_file)
    except RunFileError:
        broken = check_file(run_file)  # an edit the store refuses (its format, its version) is named as one too
        if broken is not None and broken.mismatches:
            raise RunFileError(_unsealed_by(run_file, broken)) from None
        raise
    try:
        with store.snapshot():
            seal = store.check_seal()  # first: an edit is named as what it changed, before any value is read
            if seal.mismatches:
                raise RunFileError(_unsealed_by(run_file, seal))
            metadata = checked_metadata(store.metadata, run_file)
            task = task_of(metadata, run_file)
            try:
                record = store.certificate()
                rows = store.episodes()
                robot_episodes = tuple(store.robot_episodes())
                choices = store.lipschitz_choices()
            except (sqlite3.DatabaseError, json.JSONDecodeError) as exc:
                raise RunFileError(f"{run_file} cannot be read: {exc}") from exc
            dataset = store.load_dataset()
    finally:
        store.close()
    try:
        spec = spec_of(metadata, task.initial_state_diameter)
    except ValueError as exc:  # CertificationSpec's refusal of recorded values
        raise RunFileError(f"{run_file} records no valid specification: {exc}") from None
    if record is None:
        return Run(run_file, metadata, task, spec, dataset, rows, None, {}, seal, robot_episodes, choices)
    if not isinstance(record, Mapping):
        raise RunFileError(f"{run_file}'s certificate is {type(record).__name__}, not a record")
    claimed = {name: record.get(name, RunMetadata.BEFORE_RECORDED.get(name)) for name in spec.record()}
    certificate = certificate_of(record, spec, run_file)
    return Run(run_file, metadata, task, spec, dataset, rows, certificate, claimed, seal, robot_episodes, choices)


def _unsealed_by(run_file: Path, seal: SealCheck) -> str:
    return f"{run_file} no longer matches its seal: {', '.join(seal.mismatches)} changed after the run wrote it"


def checked_metadata(metadata: RunMetadata, run_file: Path) -> RunMetadata:
    """``metadata`` once every value a reader relies on is present (a MissingMetadata otherwise) and of its type."""
    for name, kind in METADATA_TYPES.items():
        value = getattr(metadata, name)
        if not holds(value, kind):
            raise RunFileError(f"{run_file}'s metadata has {name} {value!r}, not {_KIND_NAMES[kind]}")
    return metadata


def task_of(metadata: RunMetadata, run_file: Path) -> Task:
    """The run's task, whose dimensions must be the ones the file stores."""
    task = get_task(str(metadata.task))
    if (metadata.state_dim, metadata.action_dim) != (task.state_dim, task.action_dim):
        raise RunFileError(
            f"{run_file} stores {metadata.state_dim}-D states and {metadata.action_dim}-D actions, but {task.name} "
            f"has {task.state_dim} and {task.action_dim}"
        )
    return task


def certificate_of(record: Mapping[str, Any], spec: CertificationSpec, run_file: Path) -> Certificate:
    """The typed certificate of a stored record, for the run's ``spec``, as a resumed run reads it; a RunFileError
    naming the first field the record lacks or holds as another type."""
    hints = get_type_hints(Certificate)
    for item in fields(Certificate):
        if item.name == "spec" or (item.name not in record and item.default is not MISSING):
            continue
        if item.name not in record:
            raise RunFileError(f"{run_file}'s certificate has no {item.name}")
        if not holds(record[item.name], hints[item.name]):
            value, kind = record[item.name], hints[item.name]
            raise RunFileError(f"{run_file}'s certificate has {item.name} {value!r}, not {_KIND_NAMES.get(kind, kind)}")
    return Certificate.from_record(record, spec)


def holds(value: object, kind: Any) -> bool:
    """Whether a value read from JSON is of a field's type (a whole number counts as a float, a list as a tuple)."""
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is str:
        return isinstance(value, str)
    if kind is type(None):
        return value is None
    origin, args = get_origin(kind), get_args(kind)
    if origin is tuple and args[1:] == (Ellipsis,):
        return isinstance(value, (list, tuple)) and all(holds(v, args[0]) for v in value)
    if origin in (Union, types.UnionType):
        return any(holds(value, arg) for arg in args)
    raise TypeError(f"no check of a stored value for the type {kind!r}")  # a field of a new type: add it here
