"""npp-expert: serves the task's expert trajectories for exactly the plant the sim describes.

The expert is built from the sim's latched plant description, never from its own parameters, and
proves it models the same plant by comparing model fingerprints. Every request is validated; a bad
one gets success = false and a message naming the problem, and the node keeps serving.

Trajectories are computed by the node's worker thread, handed over through a Mailbox (an optimizer
expert's by a pool of worker processes the thread hands them to, npp_ros.expert_pool), while the
executor keeps taking requests off the wire, so the node always knows its backlog: beyond
`max_queue` waiting requests it answers at once with success = false and a message starting
"busy:", instead of letting the middleware's queue overflow and drop requests silently.

A request may name a drawn robot (model uncertainty, npp_ros.tasks.uncertainty): the expert then plans on it, its
model made into that robot for the request and nominal again after it (in a worker process too), as the in-process
privileged expert does. A task whose expert cannot plan on a robot refuses such a request, saying why.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future as PoolFuture
from dataclasses import dataclass

import numpy as np
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.task import Future

from npp_ros.policy.dataset import Trajectory
from npp_ros.policy.vectors import finite_vector, state_digest
from npp_ros.run.request import EXPERT_FIELDS, RunRequest
from npp_ros.tasks.expert_pool import ExpertPool, PooledAnswer, default_workers
from npp_ros.tasks.registry import MAX_HORIZON, Expert, ExpertOptions, StopsAtTimeBudget, get_task
from npp_ros.tasks.uncertainty import Robot, as_robot, supports_robots
from npp_ros.trajopt.batch_steps import default_threads
from npp_ros_graph.runtime.diagnostics import ERROR, OK, DiagnosticsReporter, Health
from npp_ros_graph.runtime.mailbox import Mailbox
from npp_ros_graph.runtime.node import publishers_of, run_node
from npp_ros_graph.transport.convert import robot_from_field, state_layout, trajectory_to_response
from npp_ros_graph.transport.expert_api import robot_refusal
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.parameters import Param, declare_settings, parameter_help, request_params
from npp_ros_graph.transport.topics import (
    BUSY,
    EXPERT_SERVICE,
    LATCHED_READER_QOS,
    NOT_READY,
    PLANT,
    SERVICE_QOS,
)

PARAMETERS = (
    *request_params(EXPERT_FIELDS),
    Param("max_horizon", 10000, "largest horizon a request may ask for", 1, MAX_HORIZON),
    Param("max_queue", 100, "requests that may wait for the worker; more are refused at once with 'busy:'", 1),
    Param("workers", 0, "processes computing an optimizer expert's requests at once (answers are the one-at-a-time "
          "answers); 0 = one per core; a closed-form expert answers in the node", 0),
    Param("threads", 0, "threads of each worker's iLQR derivatives (mujoco.batch; answers are the same at any "
          "count); 0 = the cores over the workers, at least 1, so that workers x threads <= cores", 0),
)  # fmt: skip


@dataclass(frozen=True)
class ExpertSettings:
    """The expert's parameters; the run request's checks check its options (the same the supervisor's are)."""

    gamma: float
    time_budget: float | None  # None: the task's
    expert_stop: str | None
    values: str | None
    max_iterations: int | None
    max_horizon: int
    max_queue: int
    workers: int
    threads: int

    def __post_init__(self) -> None:
        self.request()

    def request(self) -> RunRequest:
        """The run request's expert options, as given here: the supervisor measures L with the same expert."""
        return RunRequest(**{name: getattr(self, name) for name in EXPERT_FIELDS})

    def options(self, workers: int) -> ExpertOptions:
        """What the task's make_expert gets (a closed-form expert refuses options it has no use for)."""
        return self.request().expert_options(threads=self.threads or default_threads(workers))


USAGE = f"""npp-expert: the task's expert oracle as a ROS 2 service (node "npp_expert").

Builds the expert the task registry names for the plant the sim publishes (lqr: the closed-form
optimal controller; swing-up tasks: iLQR within time_budget seconds per request) and answers
trajectory requests from any state, one at a time (an optimizer expert: `workers` at once, in worker
processes, each answer the one-at-a-time answer). A long request never blocks the service: others
wait their turn, and beyond max_queue are refused at once with "busy:". Bad requests get
success = false and a precise message.

subscribes  /{PLANT} (npp_interfaces/msg/PlantDescription, latched): the plant to model
serves      /{EXPERT_SERVICE} (npp_interfaces/srv/ExpertTrajectory)
              request:  float64[] state (qpos then qvel), uint32 horizon (0 = the plant's horizon),
                        string robot (a drawn robot to plan on, '' = the nominal model; refused by an
                        expert that cannot plan on one)
              response: success, message, state_dim, action_dim, row-major states, actions, values

{parameter_help(PARAMETERS)}
"""


class ExpertNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_expert")
        settings = declare_settings(self, PARAMETERS, ExpertSettings)
        self.gamma, self.max_horizon, self.max_queue = settings.gamma, settings.max_horizon, settings.max_queue
        self.workers = settings.workers or default_workers()
        self.options = settings.options(self.workers)
        self.waiting = 0  # accepted requests not yet answered (executor thread only)
        self.busy_refusals = 0
        self.computed = 0  # trajectories computed (by the worker thread, or under _counting by the pool's)
        self._pool: ExpertPool | None = None  # an optimizer expert's worker processes (started by the worker thread)
        self._pool_for: tuple[str, int, int] | None = None  # the plant they model: task, seed, horizon
        self._pool_budget_stops = 0  # answers of the pool the time budget cut (under _counting)
        self._counting = threading.Lock()
        self._jobs: Mailbox[tuple[Expert, np.ndarray, int, Robot | None, Future]] = Mailbox()
        self._worker = threading.Thread(target=self._work, name="npp-expert-worker", daemon=True)
        self._worker.start()
        self.expert: Expert | None = None
        self.description: PlantDescription | None = None
        self.refusal: str | None = None  # set when the described plant cannot be modelled
        self.plans_on_robot = False  # whether the modelled task's expert can plan on a drawn robot
        self.run_seal = RunSeal.from_environment()
        self.seal: RunSeal | None = None  # the run's seal for the modelled plant
        self._plant_sub = self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_READER_QOS)
        # Reentrant: the next request is taken while earlier ones await the worker (a mutually exclusive
        # group would hold every request back until the one before it is answered).
        self._service = self.create_service(
            ExpertTrajectory,
            EXPERT_SERVICE,
            self.on_request,
            qos_profile=SERVICE_QOS,
            callback_group=ReentrantCallbackGroup(),
        )
        self.diagnostics = DiagnosticsReporter(self, lambda: Health(
            "serving" if self.expert is not None else "waiting for a plant it can model",
            {"waiting requests": self.waiting, "busy refusals": self.busy_refusals},
            ERROR if self.refusal else OK, self.refusal or ""))  # fmt: skip
        self.get_logger().info(
            f"waiting for the plant description on {self._plant_sub.topic_name}; "
            f"serving {self.resolve_service_name(EXPERT_SERVICE)} (gamma {self.gamma}, max_horizon {self.max_horizon}, "
            f"max_queue {self.max_queue})"
        )

    # ------------------------------------------------------------------ plant
    def on_plant(self, desc: PlantDescription) -> None:
        try:
            self.run_seal.check(desc, "a plant description")
        except SealError as exc:
            self.get_logger().error(
                f"ignored: {exc} (publishers of {self._plant_sub.topic_name}: {publishers_of(self, PLANT)})",
                throttle_duration_sec=5.0,
            )
            return
        try:
            self._adopt(desc)
        except Exception as exc:  # a callback must never take the node down
            self.expert, self.description = None, desc
            self.refusal = f"cannot model the plant described on {self._plant_sub.topic_name}: {exc}"
            self.get_logger().error(self.refusal)

    def _adopt(self, desc: PlantDescription) -> None:
        key = (desc.task, desc.seed, desc.horizon, desc.model_sha256)
        if self.description is not None and key == (
            self.description.task,
            self.description.seed,
            self.description.horizon,
            self.description.model_sha256,
        ):
            return  # the same plant again (e.g. a second latched delivery)
        if self.expert is not None:
            assert self.description is not None
            self.get_logger().error(
                f"ignored a description of another plant ({desc.task} seed {desc.seed}, fingerprint "
                f"{desc.model_sha256[:12]}; publishers of {self._plant_sub.topic_name}: {publishers_of(self, PLANT)}): "
                f"this expert keeps modelling {self.description.task} seed {self.description.seed}; restart it to "
                "model another plant",
                throttle_duration_sec=5.0,
            )
            return
        self.expert, self.description, self.refusal = None, desc, None
        expert = get_task(desc.task).make_expert(int(desc.seed), int(desc.horizon), self.options)
        mine = expert.plant.model_sha256()
        if mine != desc.model_sha256:
            self.refusal = (
                f"model mismatch: the sim's {desc.task} seed {desc.seed} has fingerprint {desc.model_sha256!r}, "
                f"this expert's model has {mine!r}; refusing to serve trajectories for a different plant"
            )
            self.get_logger().error(self.refusal)
            return
        self.expert, self.seal = expert, self.run_seal.for_plant(mine)
        self.plans_on_robot = bool(getattr(get_task(desc.task), "plans_on_robot", False)) and supports_robots(
            expert.plant
        )
        if self.workers > 1 and isinstance(expert, StopsAtTimeBudget):
            self._pool_for = (desc.task, int(desc.seed), int(desc.horizon))
        self.get_logger().info(
            f"modelling {desc.task} seed {desc.seed} (state_dim {expert.plant.state_dim}, "
            f"action_dim {expert.plant.action_dim}, default horizon {expert.horizon}, fingerprint {mine[:12]})"
        )

    # ---------------------------------------------------------------- service
    async def on_request(
        self, request: ExpertTrajectory.Request, response: ExpertTrajectory.Response
    ) -> ExpertTrajectory.Response:
        """Validate at once; hand the computation to the worker, or refuse as busy when the queue is full.

        A coroutine: a service answers from its callback, so the callback awaits the worker's Future
        while the executor takes further requests; the backlog is counted here rather than hidden in
        the middleware's queue.
        """
        robot: Robot | None = None
        try:
            problem = self._problem(request.state, int(request.horizon))
            if problem is None:
                robot, problem = self._robot(request.robot)
        except Exception as exc:  # never let an exception escape into the executor
            problem = f"internal error while checking the request: {exc}"
        if problem is not None:
            return self._refuse(response, problem, request)
        if self.waiting >= self.max_queue:
            self.busy_refusals += 1
            return self._refuse(
                response,
                f"{BUSY} {self.waiting} requests are waiting (parameter max_queue {self.max_queue}); "
                "nothing was computed, ask again later",
                request,
            )
        assert self.expert is not None and self.description is not None
        expert, seal, fingerprint = self.expert, self._seal_for(request), self.description.model_sha256
        done = Future()
        self.waiting += 1
        try:
            self._jobs.put((expert, np.asarray(request.state, dtype=np.float64), int(request.horizon), robot, done))
            traj: Trajectory = await done
        except Exception as exc:
            self.get_logger().error(f"expert request failed: {type(exc).__name__}: {exc}")
            return self._refuse(response, f"internal error while computing the trajectory: {exc}", request)
        finally:
            self.waiting -= 1
        response.success = True
        response.message = f"{len(traj)} steps of {expert.task} seed {expert.seed}" + (
            "" if robot is None else f" on the robot {robot.describe()}"
        )
        response.plant = fingerprint
        return seal.seal(trajectory_to_response(traj, response), answering=request)

    def _work(self) -> None:
        """Worker thread: one trajectory at a time, in arrival order; wakes the executor when one is done."""
        while (job := self._jobs.take()) is not None:
            expert, state, horizon, robot, done = job
            if self._pool_for is not None:
                self._hand_to_pool(expert, state, horizon, robot, done)
                continue
            stops = expert.budget_stops if isinstance(expert, StopsAtTimeBudget) else 0
            started = time.monotonic()
            try:
                with as_robot(expert.plant, robot):  # the model is nominal again after the request
                    done.set_result(expert.trajectory(state, horizon or expert.horizon))
            except Exception as exc:  # reported to the waiting request, never kills the worker
                done.set_exception(exc)
            else:
                self.computed += 1
                self.get_logger().info(
                    f"computed a trajectory from s0 {state_digest(state)} in {time.monotonic() - started:.3f} s "
                    f"({self.computed} computed by this process)"
                )
            if isinstance(expert, StopsAtTimeBudget) and expert.budget_stops > stops:
                self.get_logger().warning(
                    f"the request from {np.array2string(np.asarray(state), precision=4)} stopped at the time budget "
                    f"({expert.time_budget:g} s) before converging: its answer depends on this machine's speed "
                    f"({expert.budget_stops} such requests so far; a larger time_budget keeps answers reproducible)"
                )
            executor = self.executor
            if executor is not None:
                executor.wake()

    def _hand_to_pool(self, expert: Expert, state: np.ndarray, horizon: int, robot: Robot | None, done: Future) -> None:
        """Worker thread: pass a request to a free worker process, without waiting for its answer."""
        if self._pool is None:
            assert self._pool_for is not None
            self._pool = ExpertPool(*self._pool_for, self.options, self.workers)
            self.get_logger().info(
                f"computing trajectories in {self.workers} worker processes, {self._pool.threads} iLQR threads each"
            )
        started = time.monotonic()
        self._pool.submit(state, horizon, robot).add_done_callback(
            lambda answer: self._pooled_answer(expert, state, done, started, answer)
        )

    def _pooled_answer(
        self, expert: Expert, state: np.ndarray, done: Future, started: float, answer: PoolFuture[PooledAnswer]
    ) -> None:
        """A worker process answered (called on the pool's thread): as the worker thread reports its own."""
        try:
            pooled = answer.result()
        except Exception as exc:  # reported to the waiting request (a cancelled one too)
            done.set_exception(exc)
        else:
            with self._counting:
                self.computed += 1
                self._pool_budget_stops += pooled.budget_stopped
                computed, stops = self.computed, self._pool_budget_stops
            done.set_result(pooled.trajectory)
            self.get_logger().info(
                f"computed a trajectory from s0 {state_digest(state)} in {time.monotonic() - started:.3f} s "
                f"({computed} computed by this process)"
            )
            if pooled.budget_stopped and isinstance(expert, StopsAtTimeBudget):
                self.get_logger().warning(
                    f"the request from {np.array2string(np.asarray(state), precision=4)} stopped at the time budget "
                    f"({expert.time_budget:g} s) before converging: its answer depends on this machine's speed "
                    f"({stops} such requests so far; a larger time_budget keeps answers reproducible)"
                )
        executor = self.executor
        if executor is not None:
            executor.wake()

    def destroy_node(self) -> None:
        self._jobs.close()
        self._worker.join(timeout=5.0)
        if self._pool is not None:
            self._pool.close()
        super().destroy_node()

    def _problem(self, state: Sequence[float], horizon: int) -> str | None:
        """What is wrong with a request, in words, or None if it can be served."""
        if self.refusal is not None:
            return self.refusal
        if self.expert is None:
            return f"{NOT_READY} no plant description received yet from the sim on {self._plant_sub.topic_name}"
        assert self.description is not None
        try:
            finite_vector(state, self.expert.plant.state_dim, "state", state_layout(self.description))
        except ValueError as exc:
            return str(exc)
        effective = horizon or self.expert.horizon
        if effective > self.max_horizon:
            what = f"horizon {horizon}" if horizon else f"the default horizon {effective} (the plant's)"
            return (
                f"{what} exceeds max_horizon {self.max_horizon} (parameter max_horizon); ask for 1..{self.max_horizon}"
            )
        return None

    def _robot(self, field: str) -> tuple[Robot | None, str | None]:
        """(the robot a request names, or None for the nominal model; why it cannot be planned on, or None)."""
        try:
            robot = robot_from_field(field)
        except ValueError as exc:  # a damaged record: say what is wrong with it
            return None, str(exc)
        if robot is None or self.plans_on_robot:
            return robot, None
        assert self.description is not None
        return None, robot_refusal(self.description.task)

    def _refuse(
        self, response: ExpertTrajectory.Response, message: str, request: ExpertTrajectory.Request
    ) -> ExpertTrajectory.Response:
        self.get_logger().warning(f"refused a request: {message}", throttle_duration_sec=1.0)
        response.success = False
        response.message = message
        seal = self._seal_for(request)
        return response if seal is None else seal.seal(response, answering=request)

    def _seal_for(self, request: ExpertTrajectory.Request) -> RunSeal | None:
        """The asking run's seal (its identity comes with the request), or the plant's for a request that names no
        run (someone querying the service by hand): an answer made for one run does not check in another."""
        if self.seal is None or not request.run:
            return self.seal
        return self.seal.for_run(request.run)


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(ExpertNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
