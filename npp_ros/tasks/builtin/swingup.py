"""The swing-up experts' one base: iLQR on the task's own plant, warm-started by a controller of the task's.

A swing-up expert names its plant, its warm-start controller, the cost iLQR refines and its iteration cap;
everything a request does, and every option (horizon, time budget, values, stop), is OptimizingExpert's
(npp_ros/trajopt/expert.py), so the three swing-ups cannot drift apart in how they are asked.
"""

from __future__ import annotations

from typing import Any, ClassVar

from npp_ros.tasks.suite_plant import SuitePlant
from npp_ros.tasks.task import DEFAULT_HORIZON
from npp_ros.trajopt.expert import DEFAULT_STOP, DEFAULT_VALUES, OptimizingExpert
from npp_ros.trajopt.ilqr import StageCost


class SwingUpExpert(OptimizingExpert):
    """An OptimizingExpert on its own instance of ``plant_class`` (replays never disturb the caller's plant)."""

    plant_class: ClassVar[type[SuitePlant]]
    max_iterations_cap: ClassVar[int]  # iLQR's iterations a request may take when the caller names none
    values_convention: ClassVar[str] = DEFAULT_VALUES  # the stored-value convention when the caller names none
    reward_lipschitz_note: ClassVar[str] = "not computed for the smooth swing-up reward"

    def __init__(
        self,
        seed: int = 0,
        horizon: int = DEFAULT_HORIZON,
        time_budget: float | None = None,
        max_iterations: int | None = None,
        cost: StageCost | None = None,
        values: str | None = None,
        stop: str = DEFAULT_STOP,
    ) -> None:
        plant = self.plant_class(seed)
        warm_start = self.make_warm_start(plant)
        super().__init__(
            plant,
            cost if cost is not None else self.default_cost(warm_start),
            warm_start,
            plant.represent,
            horizon=horizon,
            time_budget=time_budget,
            max_iterations=self.max_iterations_cap if max_iterations is None else max_iterations,
            values=self.values_convention if values is None else values,
            stop=stop,
        )
        self.seed = int(seed)
        self.task = self.plant_class.task
        self.reward_lipschitz_detail = self.reward_lipschitz_note

    def make_warm_start(self, plant: Any) -> Any:
        """The controller whose rollout from s0 iLQR starts from (and that continues a window value past H)."""
        raise NotImplementedError

    def default_cost(self, warm_start: Any) -> StageCost:
        """The smooth cost iLQR refines when the caller gives none."""
        raise NotImplementedError
