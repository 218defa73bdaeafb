"""The front door for Python users: learn a certified policy in process, and read a run folder back.

What ``npp-learn`` does, without a terminal: :func:`learn` builds the run exactly as the command does
(``npp_ros.run.setup``: the task's expert, L, config and loop) and runs Algorithm 1 to its certificate or its
budget; :func:`read_run` opens any run folder (made by ``npp-learn``, ``npp-run`` or ``npp-experiment``) and
gives its data, its episode log, its certificate as the typed record the loop resumes from, and the policy
that certificate names. Both are exported by ``npp_ros`` itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from npp_ros.certificate.certifier import Certificate, CheckedQuantity, StoppingRule
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.policy.feedback import DEFAULT_POLICY, PolicyKind
from npp_ros.run.loop import RunResult
from npp_ros.run.records import EpisodeRow, RunFileError, RunMetadata
from npp_ros.run.setup import build_config, build_loop, policy_for, resolve_lipschitz, spec_of
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task

RUN_FILE = "run.sqlite"


def learn(
    task: str,
    seed: int = 0,
    *,
    run_dir: str | Path | None = None,
    epsilon: float | None = None,
    lipschitz: str | float | None = None,
    policy: PolicyKind = DEFAULT_POLICY,
    certify: CheckedQuantity | None = None,
    rule: StoppingRule | None = None,
    horizon: int | None = None,
    max_episodes: int = 1000,
    explore: float = 0.0,
) -> RunResult:
    """Algorithm 1 in process on ``task`` until its certificate or ``max_episodes``; None means the task's default.

    With ``run_dir`` the run is stored there (``run.sqlite``) and resumes from it when it exists, as
    ``npp-learn --run-dir`` does; without, nothing is written. Raises ValueError for settings the run refuses.
    """
    definition = get_task(task)
    steps = definition.default_horizon if horizon is None else horizon
    expert = definition.make_expert(seed, steps, ExpertOptions())
    store_path = None if run_dir is None else Path(run_dir) / RUN_FILE
    constant = resolve_lipschitz(task, lipschitz, expert, seed=seed, horizon=steps, run_file=store_path)
    config = build_config(
        task, seed, constant, definition.epsilon(epsilon), horizon=steps, certify=certify, rule=rule, policy=policy,
        explore=explore,
    )  # fmt: skip
    loop = build_loop(config, expert, store_path=store_path)
    try:
        return loop.run(max_episodes)
    finally:
        if loop.store is not None:
            loop.store.close()


@dataclass(frozen=True)
class Run:
    """One run folder as it is on disk: what it was made for, its data, its log, and its certificate."""

    folder: Path
    metadata: RunMetadata
    dataset: Dataset
    episodes: list[EpisodeRow]
    certificate: Certificate | None

    @property
    def policy(self) -> NonparametricPolicy:
        """The certificate's policy (its first trajectories, acting as its spec names); uncertified: all the data."""
        spec = spec_of(self.metadata, get_task(str(self.metadata.task)).initial_state_diameter)
        count = self.dataset.num_trajectories if self.certificate is None else self.certificate.policy_trajectories
        data = self.dataset if count == self.dataset.num_trajectories else self.dataset.prefix(count)
        return policy_for(data, spec, str(self.metadata.task), int(self.metadata.seed))


def read_run(folder: str | Path) -> Run:
    """Open a run folder (or its run.sqlite) for reading; never takes the writer's lock, so a live run goes on.

    Raises RunFileError for a folder with no readable run file, or a damaged one.
    """
    path = Path(folder)
    run_file = path if path.is_file() else path / RUN_FILE
    if not run_file.is_file():
        raise RunFileError(f"{path} holds no {RUN_FILE}: no run was stored there")
    with RunStore.open(run_file) as store, store.snapshot():
        metadata, dataset, episodes = store.metadata, store.load_dataset(), store.episodes()
        record = store.certificate()
    certificate = None
    if record is not None:
        spec = spec_of(metadata, get_task(str(metadata.task)).initial_state_diameter)
        certificate = Certificate.from_record(record, spec)
    return Run(run_file.parent, metadata, dataset, episodes, certificate)
