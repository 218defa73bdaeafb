"""Which robot a run on a robot is of, as its run file records it (RunConfig.robot_run): a resume on another robot,
or with the expert planning on another model, or with starts from elsewhere, is another run and is refused."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, get_args

from npp_ros.tasks.uncertainty import Robot

Starts = Literal["rho", "robot"]
STARTS: tuple[str, ...] = get_args(Starts)
STARTS_HELP = (
    "where a robot episode starts: rho (the reset is asked for an s0 drawn from the task's rho with the run's seed and "
    "the episode's index; the start the robot measures is what counts) or robot (wherever its own reset brings it)"
)


@dataclass(frozen=True)
class RobotIdentity:
    """The robot a run is on: its model fingerprint (computed from the description it publishes, as npp-deploy's gate
    computes it), the model its expert plans on (an identified robot's record, npp-identify's; '' the task's nominal
    model) and where its episodes start."""

    fingerprint: str
    expert_model: str = ""
    starts: Starts = "rho"

    def __post_init__(self) -> None:
        if not self.fingerprint:
            raise ValueError("a run on a robot needs the robot's model fingerprint (from its description)")
        if self.starts not in STARTS:
            raise ValueError(f"starts must be one of {', '.join(STARTS)}, got {self.starts!r}")
        if self.expert_model:
            Robot.from_record(self.expert_model)  # a ValueError saying what is wrong with it

    def record(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_record(cls, text: str) -> RobotIdentity:
        try:
            fields = json.loads(text)
            return cls(**fields)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"not a robot run's record ({exc}): {text[:200]!r}") from exc

    @property
    def planning_robot(self) -> Robot | None:
        """The model the expert plans on, as a robot of the task's model (None: the nominal model)."""
        return Robot.from_record(self.expert_model) if self.expert_model else None

    def describe(self) -> str:
        model = (
            "the task's nominal model"
            if not self.expert_model
            else f"the identified robot {Robot.from_record(self.expert_model).describe()}"
        )
        return f"model fingerprint {self.fingerprint[:16]}..., its expert planning on {model}"

    def starts_words(self) -> str:
        if self.starts == "rho":
            return "each reset asked for an s0 drawn from rho; the start the robot measured is the one counted"
        return "wherever the robot's own reset brought it"


def identified_planning_model(path: Path, task: str) -> str:
    """The model a run on a robot plans on from npp-identify's file (--out): the estimate's physical parameters (the
    first point of its region), as a robot record; its delay and noise are the robot's to show, not the plan's."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot read the identified robot {path}: {exc}") from None
    record = record.get("identification", record) if isinstance(record, dict) else record
    if not isinstance(record, dict) or not record.get("region"):
        raise ValueError(f"{path} is no identification with a region (npp-identify --out writes one)")
    if record.get("task") != task:
        raise ValueError(f"{path} identifies a {record.get('task')!r} robot; this run is of {task!r}")
    try:
        estimate = Robot.from_record(json.dumps(record["region"][0]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path} holds a region that is no list of robots: {exc}") from None
    return Robot(estimate.scales).record()
