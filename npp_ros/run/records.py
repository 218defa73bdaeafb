"""What one run records: its metadata, one row per episode, and the episode log every front end writes.

These are plain values: the run file (store.py), the loop, the nodes and the command lines all pass
them, and ``episodes.csv`` has one writer here, so npp-learn and npp-run write the same columns.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import numpy as np

from npp_ros.certificate.authoring import LOW_EXPERT_SUCCESS
from npp_ros.policy.dataset import FloatArray


class RunFileError(RuntimeError):
    """The run file is missing, damaged, of another version, or made for another run."""


class MissingMetadata(RunFileError, AttributeError):
    """A metadata key the run file lacks: a RunFileError naming it, and still an AttributeError for hasattr."""


# The expert's settings that decide its answers, resolved (RunConfig's fields of these names): which of the task's
# experts, its time budget, its iteration cap, what ends a request, what it stores as Q_t, the detuned lqr expert's
# control-cost scale. None where the option does not apply to the run's expert.
EXPERT_SETTINGS = ("expert_kind", "time_budget", "max_iterations", "expert_stop", "values", "control_weight")


class UnrecordedSettings(UserWarning):
    """A run resumes a file made before run files recorded some of the settings its answers depend on: what those
    settings were for the stored answers is not known, and nothing claims it (RunMetadata.unrecorded_settings)."""


class RunMetadata(SimpleNamespace):
    """What a run file was made for: the meta table's values by name, as ``RunConfig.metadata()`` gives them.

    A resumed run must ask for the same values; only where L came from (its detail) may differ.
    """

    PROVENANCE = ("lipschitz_detail",)
    RECORDED_SINCE = ("plant_fingerprint",)  # absent from older files: the first resume records them
    # Absent from files made before the choice existed, which all made this one: read as it.
    BEFORE_RECORDED: ClassVar[dict[str, object]] = {
        "policy": "open-loop",
        "explore": 0.0,
        "policy_lipschitz": "claim",
        "uncertainty": "",
        "expert_model": "robot",
        "robot_run": "",
        "prior": "",
    }
    # Absent from files made before run files recorded the expert's settings. What they were for such a file's
    # answers is not known: they are never compared, never written in later (a value written then would claim the
    # older answers too), and read as None; every resume says which are missing (unrecorded_settings).
    UNKNOWN_BEFORE = EXPERT_SETTINGS

    def __getattr__(self, name: str) -> object:
        """Only called for a key the meta table lacks (a hand-edited or damaged file): say which."""
        if name.startswith("__"):
            raise AttributeError(name)
        if name in self.BEFORE_RECORDED:
            return self.BEFORE_RECORDED[name]
        if name in self.UNKNOWN_BEFORE:
            return None
        raise MissingMetadata(f"the run file's metadata has no {name!r} (hand-edited or damaged?)")

    def mismatches(self, asked: RunMetadata) -> list[str]:
        """One line per value ``asked`` differs in from this file's: the key, the recorded value and the asked one.
        A key this (older) file never recorded is no mismatch (RECORDED_SINCE, UNKNOWN_BEFORE)."""
        return [
            f"{name}: file has {getattr(self, name, None)!r}, this run asks for {value!r}"
            for name, value in vars(asked).items()
            if name not in self.PROVENANCE
            and getattr(self, name, None) != value
            and not (name in self.RECORDED_SINCE and not hasattr(self, name))
            and not (name in self.UNKNOWN_BEFORE and name not in vars(self))
        ]

    def unrecorded(self, asked: RunMetadata) -> dict[str, object]:
        """What ``asked`` records that this (older) file does not yet, and the file takes from now on."""
        names = [name for name in self.RECORDED_SINCE if hasattr(asked, name) and not hasattr(self, name)]
        return {name: getattr(asked, name) for name in names}

    def unrecorded_settings(self, asked: RunMetadata) -> dict[str, object]:
        """The settings ``asked`` records that this (older) file never did (UNKNOWN_BEFORE), with the values asked:
        the file's answers so far were made under settings nobody recorded."""
        own = vars(self)
        return {name: value for name, value in vars(asked).items() if name in self.UNKNOWN_BEFORE and name not in own}

    def unrecorded_notice(self, asked: RunMetadata, path: Path) -> str:
        """What a resume of this file says when it never recorded some of ``asked``'s settings ('' when it did)."""
        missing = self.unrecorded_settings(asked)
        if not missing:
            return ""
        asks = ", ".join(f"{name} {value!r}" for name, value in missing.items())
        return (
            f"{path} was made before run files recorded {', '.join(missing)}: the settings its stored answers were "
            f"made with are not known, so they are not checked; this run asks for {asks} and records none of them "
            "(they would claim the older answers too)"
        )


def expert_settings(expert: object, kind: str, options: object) -> dict[str, object]:
    """The EXPERT_SETTINGS a run records of its expert: as the built expert resolved them (the task's defaults filled
    in, so that asking for the default and asking for its value are the same run), else as ``options`` (the
    ExpertOptions it was built with) asked; None where an option does not apply to this expert (the closed-form lqr
    experts have no time budget; only the detuned one has a control-cost scale)."""

    def resolved(name: str, asked: object, kinds: tuple[type, ...]) -> object:
        value = getattr(expert, name, asked)
        return value if isinstance(value, kinds) and not isinstance(value, bool) else asked

    weight = getattr(expert, "control_weight", None)
    return {
        "expert_kind": kind,
        "time_budget": resolved("time_budget", getattr(options, "time_budget", None), (int, float)),
        "max_iterations": resolved("max_iterations", getattr(options, "max_iterations", None), (int,)),
        "expert_stop": resolved("stop", getattr(options, "stop", None), (str,)),
        "values": resolved("values", getattr(options, "values", None), (str,)),
        "control_weight": float(weight) if isinstance(weight, (int, float)) else None,
    }


@dataclass(frozen=True)
class EpisodeRow:
    """One episode of Algorithm 1 as stored (and as logged to CSV)."""

    episode: int
    initial_state: tuple[float, ...]
    v_lb: float
    v_ub: float
    gap: float
    oracle_called: bool
    trajectory: int | None
    dataset_size: int
    oracle_calls: int
    quiet_episodes: int
    window: int
    required: int
    certified: bool
    expert_value: float | None = None
    policy_return: float | None = None
    wall_time: float = 0.0
    checked_gap: float = math.inf  # the quantity the certification checked (see npp_ros.certificate)
    test: int = 0  # the test this episode belongs to (0: no policy yet; the mixture rule: no verification runs)
    test_delta: float = 0.0  # the confidence that test may spend
    explored: int = 0  # more trajectories asked from where the policy's rollout left the data (npp_ros.run.explore)
    # The task's success criterion (npp_ros.tasks.success) on this episode; None when not known: the task states
    # none, no answer or rollout was there to judge, or the file is from before success was recorded.
    expert_success: bool | None = None  # on the expert's answer from s0 (its stored states)
    policy_success: bool | None = None  # on the policy's own rollout from s0
    robot: str | None = None  # the episode's drawn robot (Robot.record()); None: the exact model

    @property
    def trajectories_stored(self) -> int:
        """The expert trajectories this episode stored: the one from s0 and those asked where the policy went."""
        return int(self.oracle_called) + self.explored


@dataclass(frozen=True)
class GapRecord:
    """One episode's decision as a viewer of the run reads it: the part of its EpisodeRow a running graph reports
    (/npp/gap), with the spec it was checked against (epsilon, condition, checked quantity). npp-learn's and
    npp-run's progress lines are both made from one (npp_ros.run.progress.progress_text), and npp-dashboard shows
    one whether it came from the graph, a bag or a run file's row (``of``)."""

    episode: int
    initial_state: tuple[float, ...]
    v_lb: float
    v_ub: float
    gap: float
    checked_gap: float
    epsilon: float
    oracle_called: bool
    dataset_size: int
    oracle_calls: int
    quiet_episodes: int
    required: int
    test: int
    test_delta: float
    condition: str
    certify: str

    @classmethod
    def of(cls, row: EpisodeRow, *, epsilon: float, condition: str, certify: str) -> GapRecord:
        """The record of a stored (or just decided) episode row, checked against that spec."""
        return cls(
            episode=row.episode, initial_state=tuple(row.initial_state), v_lb=row.v_lb, v_ub=row.v_ub, gap=row.gap,
            checked_gap=row.checked_gap, epsilon=epsilon, oracle_called=row.oracle_called,
            dataset_size=row.dataset_size, oracle_calls=row.oracle_calls, quiet_episodes=row.quiet_episodes,
            required=row.required, test=row.test, test_delta=row.test_delta, condition=condition, certify=certify,
        )  # fmt: skip


@dataclass(frozen=True)
class EpisodeOutcome:
    """One episode's outcome as a running graph reports it (/npp/episode): None where it is not known (the policy
    did not drive, V*(s0) was not computed); ``robot`` is the drawn robot's record, "" for the exact model."""

    episode: int
    policy_return: float | None
    steps: int
    initial_state: tuple[float, ...]
    expert_value: float | None
    v_lb: float
    robot: str = ""


@dataclass(frozen=True)
class PlantRecord:
    """The plant a running graph's sim describes (/npp/sim/plant): its task, seed and episode length, its step, the
    sizes of a state and an action, its joints, the fingerprint of its model, its angle entries and the range of
    its actuators."""

    task: str
    seed: int
    horizon: int
    timestep: float
    state_dim: int
    action_dim: int
    joint_names: tuple[str, ...]
    actuated_joint_names: tuple[str, ...]
    model_sha256: str
    angle_entries: tuple[int, ...]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]


@dataclass(frozen=True)
class RobotEpisode:
    """One episode a robot ran for a run whose plant is the robot (npp_ros.run.on_robot), stored when it ended.

    ``role`` is "check" (the policy's episode, which the run's check judges), "answer" (an expert plan run on the
    robot by its feedback law, which joins the data as what the robot did) or "start" (a reset whose episode no
    policy could drive, the run having no data yet: its measured start is the episode's s0, and nothing ran).
    ``fault`` says why the robot cut it short (None: it ran to its end); a cut episode is kept and marked, never a
    check. ``rollout`` is the measured states, the commands sent and the rewards on the measured states, as float64
    rows [s, a, r] (empty for a failed reset).
    """

    id: int
    episode: int
    role: str
    requested: tuple[float, ...] | None  # the start asked of the robot's reset (None: its own)
    start: tuple[float, ...]  # the start as the robot measured it (empty when the reset failed)
    steps: int
    started_at: float  # the robot's clock at its measured start (seconds)
    robot_time: float  # seconds of the robot's clock from its start to its last state
    late_commands: int
    fault: str | None
    success: bool | None
    policy_return: float | None
    rollout: bytes = b""

    ROLES: ClassVar[tuple[str, ...]] = ("check", "answer", "start")

    def arrays(self, state_dim: int, action_dim: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(states, actions, rewards) of the stored rollout."""
        flat = np.frombuffer(self.rollout, dtype="<f8").reshape(-1, state_dim + action_dim + 1)
        return flat[:, :state_dim].copy(), flat[:, state_dim:-1].copy(), flat[:, -1].copy()

    @staticmethod
    def pack(states: FloatArray, actions: FloatArray, rewards: FloatArray) -> bytes:
        """A rollout as the bytes the run file stores (little-endian float64 rows)."""
        rows = np.hstack([np.asarray(states), np.asarray(actions), np.asarray(rewards)[:, None]])
        return np.ascontiguousarray(rows, dtype="<f8").tobytes()


ROBOT_EPISODE_COLUMNS = tuple(f.name for f in fields(RobotEpisode))
EPISODE_COLUMNS = tuple(EpisodeRow.__dataclass_fields__)
SUCCESS_COLUMNS = ("expert_success", "policy_success")  # absent from files made before success was recorded
LATER_COLUMNS = {"robot": "TEXT"}  # absent from files made before robots were drawn: added at the next write


@dataclass(frozen=True)
class SuccessCounts:
    """How often the expert and the policy met the task's success criterion over a run's episodes.

    ``expert``: the expert's answers from s0 that were judged, and how many succeeded; ``policy``: the episodes
    whose check measured the policy's own rollout, and how many of those rollouts succeeded (a surrogate check
    measures none, so ``policy_checked`` counts only rows the caller says were checked on a rollout).
    """

    expert_successes: int
    expert_answers: int
    policy_successes: int
    policy_checked: int

    @classmethod
    def of(cls, rows: Iterable[EpisodeRow], policy: bool = True) -> SuccessCounts:
        """The counts over ``rows``; ``policy`` False: the run's check measured no rollout (surrogate)."""
        rows = list(rows)
        expert = [row.expert_success for row in rows if row.expert_success is not None]
        driven = [row.policy_success for row in rows if row.policy_success is not None] if policy else []
        return cls(sum(expert), len(expert), sum(driven), len(driven))

    @property
    def expert_rate(self) -> float:
        """The share of judged answers that succeeded (NaN when none was judged)."""
        return self.expert_successes / self.expert_answers if self.expert_answers else math.nan

    @property
    def expert_fails(self) -> bool:
        """Whether the expert met the criterion on fewer than LOW_EXPERT_SUCCESS of its judged answers."""
        return bool(self.expert_answers) and self.expert_rate < LOW_EXPERT_SUCCESS

    def warning(self, criterion: str) -> list[str]:
        """The lines a command prints before anything else when the expert fails (none when it does not)."""
        if not self.expert_fails:
            return []
        return [
            f"WARNING: the expert succeeded on {self.expert_successes} of its {self.expert_answers} answers "
            f"({self.expert_rate:.0%}); success: {criterion}.",
            "WARNING: a certificate is relative to its expert: this run compares the policy with an expert that "
            "fails the task on most of its answers, so a certificate of it says nothing about doing the task. "
            "Check the expert first (npp-bench --only experts --expert-tasks TASK).",
        ]


def _episode_cells(row: EpisodeRow) -> list[object]:
    """One CSV line of a row; a state is written as its numbers, space-separated, to full precision."""
    cells = (getattr(row, name) for name in EPISODE_COLUMNS)
    return [" ".join(f"{x:.17g}" for x in v) if isinstance(v, tuple) else v for v in cells]


def write_episode_log(path: Path, rows: Iterable[EpisodeRow]) -> None:
    """The whole episode log at once, replaced atomically (npp-learn, at the end of a run)."""
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(EPISODE_COLUMNS)
        writer.writerows(_episode_cells(row) for row in rows)
    tmp.replace(path)


def append_episode_log(path: Path, row: EpisodeRow) -> None:
    """One more line of the episode log, with the header when the file is new (the supervisor, per episode)."""
    new = not path.exists()
    with path.open("a", newline="") as fh:
        writer = csv.writer(fh)
        if new:
            writer.writerow(EPISODE_COLUMNS)
        writer.writerow(_episode_cells(row))


def state_tuple(state: FloatArray) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(state).ravel())
