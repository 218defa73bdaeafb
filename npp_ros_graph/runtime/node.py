"""How every npp_ros node process runs: main() through run_node, the one teardown (release), throttled warnings.

Nodes convert messages to core types (transport/convert.py), call the core, and publish; nothing here
does math. Topic names and QoS are in transport/topics.py, the Mailbox in mailbox.py, deadlines in deadlines.py.

Concurrency, the same in every node: one executor thread (run_node) runs the callbacks, and a
callback never blocks. It validates, does work that is short and bounded (a sim step, a policy
query), and hands anything long to the node's one worker thread through a Mailbox; results go out
from the worker as publications, or as a Future that an ``async`` service callback awaits. The
worker, in turn, makes synchronous calls with deadlines and waits on Conditions that callbacks
signal, never polls. This is the model of bdaiinstitute/synchros2 (blocking code in its own
thread, callbacks only hand data over), kept to one thread per node. Callback groups with a
MultiThreadedExecutor were the alternative: rclpy's runs every callback through a Python thread
pool, which adds GIL hand-offs to each control step (the loop the policy node must keep fast), and
a service that may hold a hundred requests in waiting would need a hundred pool threads.

Which executor: rclpy's SingleThreadedExecutor, except in the two nodes of the control loop (sim
and policy), which ask run_node for rclpy's EventsExecutor (``events=True``). The
SingleThreadedExecutor rebuilds its wait set from every entity of the node (subscriptions,
publishers' QoS events, timers, clients, the parameter services) on each wake-up, in Python; the
EventsExecutor (C++) is called by the middleware for the one entity that has work. For the policy
node that wait set was most of what its loop cost beyond a bare ping-pong's (README,
"Performance"; npp-bench --ros measures it), and much of the sim's CPU time per step. The
EventsExecutor is experimental in Jazzy, so run_node keeps to what it does well: it spins it with
spin_once and a timeout (its spin() busy-waits and misses shutdown in rclpy 7.1.6), and falls back
to the SingleThreadedExecutor where rclpy has none. It serves no guard conditions (the two nodes
create none), and it logs a callback's exception with its traceback before run_node reports it.

Stopping, the same in every node: SIGINT and SIGTERM only ask run_node to stop (``request_stop``),
and a node that must stop itself (a refusal) asks the same way; nothing shuts the context down from
a signal handler or a worker thread. rclpy's own handlers are not installed: they shut the context
down at once, from a signal handler, while a callback or a worker thread may be publishing (which
then fails with "publisher's context is invalid"), and they raise KeyboardInterrupt inside whatever
callback runs, which the EventsExecutor logs as FATAL. The EventsExecutor's own handler (it takes
SIGINT and SIGTERM when it is made) is replaced the same way. The spin loop then ends within
SPIN_ONCE_S, and ``release`` tears down in the one order in which nothing publishes into a context
that is gone: timers cancelled, the executor let go, the node destroyed (each node's destroy_node
stops its worker thread before its publishers go), and only then the context shut down. Further
signals during the teardown are ignored (a terminal's Ctrl-C reaches the node and npp-run, which
then sends its own SIGINT), except one more than FORCE_AFTER_S after the first, which ends a
teardown that hangs. A process leaves by itself when its teardown hangs past TEARDOWN_S, and when it is
still running STOP_BOUND_S after its first stop signal, whatever holds its main thread
(``watch_stop_signals``): one signal is all it may get.
"""

from __future__ import annotations

import itertools
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import suppress
from types import FrameType

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from npp_ros_graph.transport.startup import StartupError

try:  # rclpy >= 7.1 (Jazzy); the fallback is the SingleThreadedExecutor
    from rclpy.experimental import EventsExecutor
except ImportError:  # pragma: no cover - every supported rclpy has it
    EventsExecutor = None


def _empty_parameter(args: Sequence[str]) -> str | None:
    """The name in a `-p name:=` without a value, which rcl refuses with a traceback instead of a reason."""
    for flag, rule in itertools.pairwise(args):
        if flag in ("-p", "--param") and rule.endswith(":=") and rule[:-2]:
            return rule[:-2]
    return None


def _init(args: list[str]) -> None:
    """rclpy.init, with a one-line reason for arguments that are not ours or that rcl cannot read."""
    empty = _empty_parameter(args[args.index("--ros-args") :] if "--ros-args" in args else [])
    if empty is not None:
        raise StartupError(f"parameter {empty} has no value; give one (-p {empty}:=VALUE) or leave it out")
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)  # run_node takes the signals
    except RCLError as exc:
        raise StartupError(f"cannot read the ROS arguments: {str(exc).splitlines()[0]}") from None
    stray = remove_ros_args(args)[1:]
    if stray:
        rclpy.try_shutdown()
        raise StartupError(
            f"unexpected argument {stray[0]!r}: parameters go after --ros-args as -p name:=value (see --help)"
        )


SPIN_ONCE_S = 1.0  # the longest wait for an event before run_node checks for a stop
FORCE_AFTER_S = 20.0  # a signal this long after the first ends a teardown that hangs (the waits in it are shorter)
TEARDOWN_S = 30.0  # a process whose ROS teardown has not returned by then leaves without it (npp-run waits 60 s)
STOP_BOUND_S = 45.0  # a process still here this long after its first stop signal leaves (npp-run waits 60 s)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class _Stop:
    """The node process's one stop request: a signal, or the node itself (``request_stop``)."""

    def __init__(self) -> None:
        self.requested = threading.Event()
        self.first_signal_at: float | None = None
        self.executor: Executor | None = None  # the spinning executor, woken by a request from another thread
        self.node: Node | None = None  # whose exit code a process that must leave exits with


_stop = _Stop()


def request_stop() -> None:
    """Ask run_node to stop this node process in order (see the module's docstring); from any thread.

    What a node calls instead of rclpy.shutdown when it must stop (a refusal): the context stays
    valid until the node's timers, worker and publishers are gone.
    """
    _stop.requested.set()
    executor = _stop.executor
    if executor is not None:
        executor.wake()


def stop_requested() -> bool:
    """Whether this node process was asked to stop: a wait inside a callback ends early for it."""
    return _stop.requested.is_set()


def _on_signal(signum: int, _frame: FrameType | None) -> None:
    """SIGINT and SIGTERM: a stop request, never an exception inside whatever callback runs now."""
    now = time.monotonic()
    if _stop.first_signal_at is None:
        _stop.first_signal_at = now
    elif now - _stop.first_signal_at > FORCE_AFTER_S:
        name, program = signal.Signals(signum).name, os.path.basename(sys.argv[0])
        print(f"{program}: {name} again, {FORCE_AFTER_S:g} s into a teardown that has not ended; leaving without it",
              file=sys.stderr, flush=True)  # fmt: skip
        os._exit(128 + signum)
    _stop.requested.set()


def take_stop_signals() -> None:
    """SIGINT and SIGTERM become stop requests. Called after the executor is made: the EventsExecutor takes
    both signals for itself when it is made (its handler shuts the context down), and this takes them back."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, _on_signal)


def watch_stop_signals(program: str) -> None:
    """Leave STOP_BOUND_S after the first SIGINT or SIGTERM, whatever the main thread is doing then.

    run_node's handler runs only when the main thread comes back to Python, and only its spin loop acts
    on the request: a callback blocked on a lock, or a main thread held in the middleware, would keep
    the process on the domain, with no second signal to come when npp-run was killed (its parent-death
    signal is one). Python's C-level handler writes each signal's number to the wakeup fd at once, from
    any state of the main thread; this thread reads it and arms the exit. Nothing is lost by leaving:
    the run file commits every episode.
    """
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)

    def watch() -> None:
        signum = os.read(read_end, 1)[0]
        while signum not in STOP_SIGNALS:  # another signal with a Python handler: not a stop
            signum = os.read(read_end, 1)[0]
        bound = STOP_BOUND_S
        code = int(getattr(_stop.node, "exit_code", 0))
        leave_if_teardown_hangs(program, bound, code, f"still running {bound:g} s after {signal.Signals(signum).name}")

    threading.Thread(target=watch, name="npp-stop-watch", daemon=True).start()


def run_node(
    factory: Callable[[], Node],
    argv: Sequence[str] | None = None,
    usage: str | Callable[[], str] = "",
    events: bool = False,
) -> int:
    """The Jazzy idiom: init, spin until a stop is requested (Ctrl-C, SIGTERM, the node itself) or the
    context ends, then release: timers, executor, node, and the context last.

    ``usage`` may be a function: --help then builds it (a listing that reads installed packages).
    ``events``: spin on rclpy's EventsExecutor where rclpy has one (see the module's docstring).
    """
    args = list(sys.argv if argv is None else argv)
    if any(a in ("-h", "--help") for a in args[1:]) and "--ros-args" not in args:
        print(usage() if callable(usage) else usage)
        return 0
    node: Node | None = None
    executor: Executor | None = None
    _stop.requested.clear()
    _stop.first_signal_at = None
    _stop.node = None
    try:
        _init(args)
        executor = EventsExecutor() if events and EventsExecutor is not None else SingleThreadedExecutor()
        take_stop_signals()
        watch_stop_signals(os.path.basename(args[0]))
        _stop.executor = executor
        node = _stop.node = factory()
        executor.add_node(node)
        while rclpy.ok() and not _stop.requested.is_set():
            executor.spin_once(timeout_sec=SPIN_ONCE_S)
    except (KeyboardInterrupt, ExternalShutdownException):  # a signal before take_stop_signals; a shutdown
        pass
    except StartupError as exc:
        print(f"{args[0]}: {exc}", file=sys.stderr)
        return 2
    finally:
        _stop.executor = None
        # One signal is all a node gets when npp-run dies (its parent-death signal): a DDS teardown that hangs
        # must not keep it alive on the domain, where it would be another graph for the next run.
        leaving = leave_if_teardown_hangs(os.path.basename(args[0]), TEARDOWN_S, int(getattr(node, "exit_code", 0)))
        try:
            release(executor, node)
        except KeyboardInterrupt:  # a Ctrl-C while shutting down, before take_stop_signals
            pass
        leaving.cancel()
    return int(getattr(node, "exit_code", 0))


def release(executor: Executor | None, node: Node | None) -> None:
    """Every entry point's teardown, in the one order in which nothing publishes into a shut-down context
    and nothing hangs.

    The node's timers are cancelled first, so none fires during the teardown. The executor lets go of
    the node next: destroy_node waits until nothing holds the node's entities, and a node still added
    to an executor could keep its process spinning there. The node's destroy_node stops its worker
    thread before its publishers go; the context is shut down last.
    """
    if node is not None and node.context.ok():
        for timer in list(node.timers):
            with suppress(InvalidHandle, RCLError):  # already destroyed, or the context went meanwhile
                timer.cancel()
    if executor is not None:
        executor.shutdown(timeout_sec=SPIN_ONCE_S)
    context = None if node is None else node.context  # a client's own context, or the default one
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown(context=context)


def leave_if_teardown_hangs(program: str, seconds: float, code: int = 0, why: str = "") -> threading.Timer:
    """Exit with ``code`` after ``seconds`` if the ROS teardown that follows has not returned by then, saying
    so (or ``why``) on stderr (every node's run_node, npp-run, npp-monitor).

    On a loaded machine a DDS teardown was seen to take minutes while its peers were shutting down
    too, and a sim whose npp-run was killed hung in it with no second signal to come. Leaving loses
    nothing: the run file commits every episode with its trajectory (fsynced), and a node keeps nothing else.
    """

    def leave() -> None:
        sys.stdout.flush()
        said = why or f"the ROS teardown did not finish within {seconds:g} s"
        print(f"{program}: {said}; leaving without it", file=sys.stderr, flush=True)
        os._exit(code)

    timer = threading.Timer(seconds, leave)
    timer.daemon = True
    timer.start()
    return timer


UNNAMED = "a node not yet named"  # a discovered endpoint whose node's name discovery has not brought yet


def node_name(namespace: str, name: str) -> str:
    if name == "_NODE_NAME_UNKNOWN_":  # its endpoint is discovered, its node not yet
        return UNNAMED
    return f"{namespace.rstrip('/')}/{name}"


def publishers_of(node: Node, topic: str) -> str:
    """Who publishes a topic, by node name: what a refusal of foreign data can tell the user."""
    names = sorted(node_name(i.node_namespace, i.node_name) for i in node.get_publishers_info_by_topic(topic))
    return ", ".join(names) or "no publisher known"


class ThrottledWarnings:
    """At most one warning per kind and second, with a count of what was suppressed: a flood of bad
    input must show up in the log without drowning it."""

    def __init__(self, node: Node, every_s: float = 1.0) -> None:
        self.node, self.every_s = node, every_s
        self._last: dict[str, tuple[float, int]] = {}
        self.counts: dict[str, int] = {}
        self.last = ""  # the newest warning, suppressed or not (a node's last error on /diagnostics)

    def __call__(self, kind: str, message: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        self.last = message
        now = time.monotonic()
        last, suppressed = self._last.get(kind, (-float("inf"), 0))
        if now - last < self.every_s:
            self._last[kind] = (last, suppressed + 1)
            return
        extra = f" ({suppressed} more like it suppressed)" if suppressed else ""
        self.node.get_logger().warning(message + extra)
        self._last[kind] = (now, 0)
