"""The expert on the robot itself: a plan made on a model of the robot, run on the robot by the plan's feedback law.

After a failed check the robot is reset to the check's start; the expert plans from the start the robot then
measures, on the identified robot's model (npp-identify's) or the task's nominal one; the plan runs on the robot by
its own law, clamp(a_t + K_t (s - s_t)), and what the robot did (its measured states, the commands sent, the rewards
on the measured states) is the answer that joins the data: true of the robot whatever the model got wrong. A plan
the robot failed is stored and counted as any answer is. A fault cuts the run of a plan: it is stored and marked,
and the robot is reset and the expert asked again.
"""

from __future__ import annotations

from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.run.nominal_plan import plan_law, tracked_answer, tracked_steps
from npp_ros.run.on_robot.episodes import RobotEpisodes
from npp_ros.run.setup import PrivilegedExpert
from npp_ros.tasks.task import Expert
from npp_ros.tasks.uncertainty import Robot


class RobotPlanOracle:
    """The run's oracle when its plant is a robot: ``expert`` plans on ``planning`` (None: its nominal model), the
    robot runs the plan. ``window``: the expert stores window values, so the plan runs 2T - 1 periods."""

    def __init__(
        self,
        expert: Expert,
        episodes: RobotEpisodes,
        space: ControlSpace,
        *,
        planning: Robot | None,
        window: bool,
    ) -> None:
        self.expert, self.episodes, self.space = PrivilegedExpert(expert), episodes, space
        self.planning, self.window = planning, window

    def trajectory(self, initial_state: FloatArray) -> Trajectory:
        episodes = self.episodes
        episodes.close_start()
        episode = episodes.answering
        while True:
            start = episodes.reset(episode, initial_state, "answer")
            plan = self.expert.trajectory(start.state, robot=self.planning)
            law = plan_law(plan, self.space)
            item = episodes.run_law(episode, "answer", initial_state, start, law, tracked_steps(plan, self.window))
            if item.fault is None:
                states, actions, rewards = item.arrays(len(start.state), plan.actions.shape[1])
                return tracked_answer(plan, states, actions, rewards, window=self.window)
