"""A stored run derived again from its own seed: what a gate can check that no seal or signature can.

A seal is a checksum anyone can recompute after an edit, and a signature says who signed, not that what they
signed is right. But a run is a function of its settings, its seed and its expert's answers: each episode's s0 and
robot are drawn from (seed, episode), each check is the policy as it then was rolled out on that robot from that s0
(the plant is deterministic given the robot), and the certificate follows from the checks. So the run can be
computed again, in process, with the stored answers as its oracle (no expert is asked), and compared with what the
file says, row by row. An edit of a drawn robot, an s0, a check's outcome or return, a success flag, a trajectory
(its checksum recomputed), epsilon or the set of robots (the seal recomputed) then shows as the first episode
that differs, or as an answer asked from another state than the one stored.

A re-derivation that agreed is remembered on the machine that made it (:class:`AgreedRuns`, in the user's cache
folder, never in the run folder an editor may write), under the run's seal digest and this npp_ros's version: the
same file, unchanged, is not derived again at its next deployment.

What this does not re-derive: the expert's answers themselves (asking again costs what the run cost, and an
optimizer with a time budget need not answer the same twice). An answer that does not start where the run asked
is a difference; an answer the run's expert never gave, starting at the right state, is not found here: that is
what a signature is for.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from npp_ros.policy.dataset import Dataset, FloatArray, Trajectory
from npp_ros.run.loop import EpisodeCut, NPPLoop, RunConfig
from npp_ros.run.on_robot.episodes import RobotEpisodes
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.on_robot.recorded import RecordedRobot, RecordMismatch
from npp_ros.run.on_robot.setup import build_robot_loop
from npp_ros.run.read import Run
from npp_ros.run.records import EpisodeRow
from npp_ros.run.setup import build_loop
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.rollout import episode_return
from npp_ros.tasks.task import ExpertOptions
from npp_ros.tasks.uncertainty import Robot, as_robot

# Fields of a row that are measurements of the machine, not of the run.
UNDERIVED = ("wall_time",)


class AnswerMismatch(Exception):
    """The re-derived run asked the expert for an answer the stored run does not hold where it asked."""


class StoredAnswers:
    """The oracle of a re-derivation: the run's stored trajectories, in stored order, each checked to start where
    the re-derived run asks (a privileged expert's answers too: the robot is the episode's own, drawn again).

    An answer's own return (what an oracle check compares the policy with) is not stored: it is the H-step return
    of the answer's actions replayed on the episode's robot model from its start, as every expert computes it."""

    def __init__(self, dataset: Dataset, plant: Plant) -> None:
        self.dataset = dataset
        self.plant = plant
        self.given = 0

    def trajectory(self, initial_state: FloatArray, robot: Robot | None = None) -> Trajectory:
        index = self.given
        if index >= self.dataset.num_trajectories:
            raise AnswerMismatch(
                f"the run asks the expert a {index + 1}th time; the file stores {self.dataset.num_trajectories} answers"
            )
        answer = self.dataset.trajectory(index)
        # An expert stores the state its plant reads back after the reset, in the stored representation (an angle
        # wrapped, the last bits of a float): the asked state is compared as the plant reads it back too.
        asked = self.plant.reset(np.asarray(initial_state, dtype=np.float64))
        if not np.allclose(answer.states[0], asked, rtol=1e-9, atol=1e-9):
            raise AnswerMismatch(
                f"the run asks for trajectory {index} from {_state(initial_state)}; the stored one starts at "
                f"{_state(answer.states[0])}"
            )
        self.given += 1
        return replace(answer, expert_return=self._replayed_return(answer, robot))

    def _replayed_return(self, answer: Trajectory, robot: Robot | None) -> float:
        rewards = np.empty(len(answer))
        with as_robot(self.plant, robot):
            self.plant.reset(answer.states[0])
            for t, action in enumerate(answer.actions):
                rewards[t] = self.plant.step(action)
        return episode_return(rewards)


@dataclass(frozen=True)
class Rederivation:
    """What deriving the run again found: the first difference (empty: none), the episodes compared, the time."""

    differences: tuple[str, ...]
    episodes: int
    seconds: float

    @property
    def agrees(self) -> bool:
        return not self.differences


class AgreedRuns:
    """Seal digests of runs this machine derived again and found to agree, one small JSON file each.

    The folder is the operator's own (``NPP_ROS_CACHE``, else ``$XDG_CACHE_HOME/npp_ros``, else ``~/.cache/npp_ros``),
    apart from any run folder: whoever may write a run folder must not be able to say it was checked. A digest
    names the file's every stored value, so an entry holds for exactly that content."""

    def __init__(self, folder: Path | None = None) -> None:
        self.folder = (folder or cache_folder()) / "rederived"

    def _entry(self, digest: str) -> Path:
        return self.folder / f"{digest}.json"

    def find(self, digest: str) -> dict[str, object] | None:
        """What was found when this digest was derived again with this npp_ros, or None."""
        if not digest:
            return None
        try:
            entry = json.loads(self._entry(digest).read_text())
        except (OSError, ValueError):
            return None
        ok = isinstance(entry, dict) and entry.get("digest") == digest and entry.get("npp_ros") == _version()
        return entry if ok else None

    def remember(self, digest: str, found: Rederivation) -> None:
        """Keep an agreement (a failure to keep it costs only a later re-derivation)."""
        if not digest or not found.agrees:
            return
        entry = {
            "digest": digest, "npp_ros": _version(), "episodes": found.episodes, "seconds": round(found.seconds, 3),
            "at": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        }  # fmt: skip
        with contextlib.suppress(OSError):
            self.folder.mkdir(parents=True, exist_ok=True)
            tmp = self.folder / f".{digest}.{os.getpid()}.new"
            tmp.write_text(json.dumps(entry) + "\n")
            os.replace(tmp, self._entry(digest))


def cache_folder() -> Path:
    """The user's npp_ros cache folder (``NPP_ROS_CACHE``, ``$XDG_CACHE_HOME/npp_ros`` or ``~/.cache/npp_ros``)."""
    if os.environ.get("NPP_ROS_CACHE"):
        return Path(os.environ["NPP_ROS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "npp_ros"


def _version() -> str:
    try:
        return importlib.metadata.version("npp_ros")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def config_of(run: Run) -> RunConfig:
    """The run's config as its file records it (every RunConfig field is a metadata key of the same name)."""
    own = {f.name: getattr(run.metadata, f.name) for f in fields(RunConfig) if f.name != "spec"}
    return RunConfig(**own, spec=run.spec)  # type: ignore[arg-type]


def expert_options(config: RunConfig) -> ExpertOptions:
    """The options the run's expert was built with, as its file records them (None: the task's; a file from before
    they were recorded gives the task's own). Only its closed-form values and value basis are used here."""
    recorded = {
        "kind": config.expert_kind, "time_budget": config.time_budget, "max_iterations": config.max_iterations,
        "stop": config.expert_stop, "values": config.values, "control_weight": config.control_weight,
    }  # fmt: skip
    return ExpertOptions(gamma=config.gamma, **{k: v for k, v in recorded.items() if v is not None})  # type: ignore[arg-type]


def rederive(run: Run, progress: Callable[[int, int], None] | None = None) -> Rederivation:
    """Run Algorithm 1 again over the run's stored answers and compare every episode and the certificate.

    ``progress(done, total)`` is called after each episode. Stops at the first difference, which it names. A run on
    a robot is played back from the robot's stored episodes instead (:func:`rederive_on_robot`)."""
    if run.on_robot:
        return rederive_on_robot(run, progress)
    started = time.perf_counter()
    config = config_of(run)
    expert = run.task.make_expert(config.seed, config.horizon, expert_options(config))
    rollouts = config.spec.certify == "surrogate" and any(row.policy_return is not None for row in run.episodes)
    answers = StoredAnswers(run.dataset, run.task.make_plant(config.seed))
    loop = build_loop(config, expert, rollouts=rollouts, answers=answers)
    total = len(run.episodes)
    for done, stored in enumerate(run.episodes, start=1):
        try:
            derived = loop.run_episode()
        except AnswerMismatch as exc:
            return _found(f"episode {stored.episode}: {exc}", done - 1, started)
        difference = first_difference(stored, derived)
        if difference:
            return _found(f"episode {stored.episode}: {difference}", done - 1, started)
        if progress is not None:
            progress(done, total)
    if answers.given != run.dataset.num_trajectories:
        return _found(
            f"the run asked the expert {answers.given} times; the file stores {run.dataset.num_trajectories} answers",
            total,
            started,
        )
    for point, stored_choice in sorted(run.lipschitz_choices.items()):
        chosen = loop.choices.get(point)
        if chosen is None or chosen.value != stored_choice.value:
            derived_value = "none" if chosen is None else f"{chosen.value:.6g}"
            return _found(
                f"the policy's L chosen at {point} trajectories: stored {stored_choice.value:.6g}, derived "
                f"{derived_value}",
                total,
                started,
            )
    return _certificate_found(run, loop, total, started)


def rederive_on_robot(run: Run, progress: Callable[[int, int], None] | None = None) -> Rederivation:
    """A run on a robot played back through its own loop (npp_ros.run.on_robot.recorded): every command recomputed
    from the policy of its time at the state the robot measured, every answer checked against the robot episode it
    came from, every row, every robot episode and the certificate compared. The robot's physics are not re-derived."""
    started = time.perf_counter()
    config = config_of(run)
    identity = RobotIdentity.from_record(config.robot_run)
    expert = run.task.make_expert(config.seed, config.horizon, expert_options(config))
    plant = run.task.make_plant(config.seed)
    link = RecordedRobot(list(run.robot_episodes), config.state_dim, config.action_dim, float(plant.dt))
    try:
        loop = build_robot_loop(config, expert, link, identity, answers=run.dataset)
    except ValueError as exc:
        return _found(f"the run cannot be played back: {exc}", 0, started)
    total = len(run.episodes)
    done = 0
    while done < total:
        stored = run.episodes[done]
        try:
            derived = loop.run_episode()
        except EpisodeCut:
            continue
        except RecordMismatch as exc:
            return _found(f"episode {stored.episode}: {exc}", done, started)
        difference = first_difference(stored, derived)
        if difference:
            return _found(f"episode {stored.episode}: {difference}", done, started)
        done += 1
        if progress is not None:
            progress(done, total)
    derived_kept = loop.robot_facts.kept if isinstance(loop.robot_facts, RobotEpisodes) else []
    if len(derived_kept) != len(run.robot_episodes):
        return _found(f"the run's loop ran the robot {len(derived_kept)} times; the file stores "
                      f"{len(run.robot_episodes)} robot episodes", total, started)  # fmt: skip
    for said, found in zip(run.robot_episodes, derived_kept, strict=True):
        for item in fields(said):
            if not _same(getattr(said, item.name), getattr(found, item.name)):
                return _found(f"robot episode {said.id}: {item.name} is {_shown(getattr(said, item.name))} in the "
                              f"file, {_shown(getattr(found, item.name))} played back", total, started)  # fmt: skip
    return _certificate_found(run, loop, total, started)


def _certificate_found(run: Run, loop: NPPLoop, episodes: int, started: float) -> Rederivation:
    """The end of a re-derivation whose rows agreed: the stored certificate against the one derived again."""
    stored_record = None if run.certificate is None else run.certificate.record()
    derived_record = None if loop.certificate is None else loop.certificate.record()
    if stored_record != derived_record:
        return _found(f"the certificate: {_record_difference(stored_record, derived_record)}", episodes, started)
    return Rederivation((), episodes, time.perf_counter() - started)


def first_difference(stored: EpisodeRow, derived: EpisodeRow) -> str:
    """The first field in which a stored row differs from its re-derived one, in words ('' when none)."""
    for item in fields(EpisodeRow):
        if item.name in UNDERIVED:
            continue
        said, found = getattr(stored, item.name), getattr(derived, item.name)
        if not _same(said, found):
            return f"{item.name} is {_shown(said)} in the file, {_shown(found)} derived again from the run's seed"
    return ""


def _same(a: object, b: object) -> bool:
    """Equal, numbers to a relative 1e-9: a return summed in another order differs in its last bits, an edit by far
    more."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _record_difference(stored: dict[str, object] | None, derived: dict[str, object] | None) -> str:
    if stored is None or derived is None:
        return f"the file has {'none' if stored is None else 'one'}, deriving the run again gives " + (
            "none" if derived is None else "one"
        )
    for key in sorted(set(stored) | set(derived)):
        if not _same(stored.get(key), derived.get(key)):
            return f"{key} is {_shown(stored.get(key))} in the file, {_shown(derived.get(key))} derived again"
    return "its records differ"


def _found(difference: str, episodes: int, started: float) -> Rederivation:
    return Rederivation((difference,), episodes, time.perf_counter() - started)


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def _state(state: FloatArray) -> str:
    return "[" + ", ".join(f"{float(v):.6g}" for v in np.ravel(state)) + "]"
