"""Which reports a viewer shows as this run's: npp-run's progress and certificate, npp-monitor, npp-dashboard.

The supervisor seals its reports (/npp/gap, /npp/episode, /npp/certificate) like the run's own data:
under the run key, the plant's model fingerprint and the run's identity, which the report names in
clear in its header (``report_context``). A recorded report replays unchanged, so the seal alone
cannot tell this run's reports from those of an earlier run under the same key (an NPP_RUN_KEY
exported once and reused for two runs, whose bag npp-replay plays back; a second run on the domain
with the same key). So a viewer that knows the key (``RunReports``) asks the live supervisor which run
it runs, through its dataset service, with a random number in the request that the sealed answer
covers: no recording can answer it. The viewer shows the reports of that run only, holds those that
arrive before the answer, and names once each other run whose reports it leaves out.

A viewer without the key cannot verify anything: it shows every report, and says so of each
(``unverified_mark``): any run on the domain, or a replay, may have sent it.
"""

from __future__ import annotations

import secrets
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from npp_interfaces.srv import GetTrajectories
from rclpy.node import Node
from rclpy.task import Future

from npp_ros_graph.transport.message_seal import KEY_ENV, SEPARATOR, RunSeal, SealError
from npp_ros_graph.transport.topics import DATASET_SERVICE, SERVICE_QOS

ASK_EVERY_S = 1.0  # while reports wait, the supervisor is asked at most this often
ANSWER_TIMEOUT_S = 5.0  # an unanswered question is withdrawn and asked again
HELD = 2000  # reports held until the supervisor names its run: the 1000 gaps and 1000 episodes it keeps
UNVERIFIED = f"not verified: no run key ({KEY_ENV})"
ORIGIN = "/"  # between the plant's fingerprint and the run's identity in a report's context


def report_context(fingerprint: str, run: str) -> str:
    """What a report names in clear: the plant and the run whose seal it carries."""
    return f"{fingerprint}{ORIGIN}{run}"


def report_origin(msg: Any) -> tuple[str, str] | None:
    """(plant fingerprint, run identity) a report names, or None for one that names none."""
    context = msg.header.frame_id.rpartition(SEPARATOR)[0]
    fingerprint, _, run = context.partition(ORIGIN)
    return (fingerprint, run) if fingerprint and run else None


def unverified_mark(run: str) -> str:
    """What a viewer without the run's key adds to a report it shows: that it is not verified, and the run it names
    (``run``: its identity, "" for a report that names none)."""
    return UNVERIFIED + (f"; it names run {run[:12]}" if run else "")


class RunReports:
    """The reports of the run the live supervisor runs, handed to ``show`` in arrival order; ``say`` gets a
    line for each other run whose reports are left out.

    ``take`` is called from the node's subscription callbacks, and everything here runs on its executor's
    thread (the supervisor's answer too). Without a private key, every report is shown (see ``unverified_mark``).
    """

    def __init__(
        self, node: Node, show: Callable[[Any], None], say: Callable[[str], None], seal: RunSeal | None = None
    ) -> None:
        self.seal = RunSeal.from_environment() if seal is None else seal
        self.verified = self.seal.private
        self.show, self.say = show, say
        self.live = ""  # the identity of the run the supervisor answered for
        self._held: deque[tuple[str, Any]] = deque(maxlen=HELD)  # (run, report) waiting for the answer
        self._fingerprints: set[str] = set()  # plants named by the held reports: the answer is checked for each
        self._left_out: set[str] = set()  # runs already named as left out
        self._question: tuple[Future, GetTrajectories.Request, float] | None = None
        self._asked_at = -ASK_EVERY_S
        if self.verified:
            self._client = node.create_client(GetTrajectories, DATASET_SERVICE, qos_profile=SERVICE_QOS)
            node.create_timer(ASK_EVERY_S, self._ask)

    def take(self, msg: Any) -> None:
        """A report off the wire: shown, held until the supervisor names its run, or left out."""
        if not self.verified:
            self.show(msg)
            return
        origin = report_origin(msg)
        if origin is None:
            return  # sealed by none of this run's supervisors (an older npp_ros, or no npp_ros at all)
        fingerprint, run = origin
        try:
            self.seal.for_plant(fingerprint).for_run(run).check_header(msg, "a report")
        except SealError:
            return  # another key: another run's
        if run == self.live:
            self.show(msg)
            return
        self._fingerprints.add(fingerprint)
        self._held.append((run, msg))
        self._ask()

    def waiting(self) -> str:
        """Why reports are not shown yet, for a viewer's "nothing received" notice ("" when none wait)."""
        if not self._held:
            return ""
        return (
            f"{len(self._held)} sealed reports held until the run's supervisor says which run it runs "
            f"(/{DATASET_SERVICE} {'answers' if self._client.service_is_ready() else 'is not reachable'})"
        )

    def _ask(self) -> None:
        """Ask the supervisor which run it runs, while reports wait; one question at a time."""
        now = time.monotonic()
        if self._question is not None:
            future, _, asked = self._question
            if now - asked < ANSWER_TIMEOUT_S:
                return
            self._client.remove_pending_request(future)
            self._question = None
        if not self._held or now - self._asked_at < ASK_EVERY_S or not self._client.service_is_ready():
            return
        # A start past any dataset asks for no trajectory; its random value is what no recording can answer.
        request = GetTrajectories.Request(start=2**31 + secrets.randbelow(2**31), max_count=1)
        future = self._client.call_async(request)
        self._question, self._asked_at = (future, request, now), now
        future.add_done_callback(self._answered)

    def _answered(self, future: Future) -> None:
        if self._question is None or future is not self._question[0]:
            return  # withdrawn
        request = self._question[1]
        self._question = None
        response = future.result()
        if response is None or not response.success or not response.run:
            return  # not running yet: asked again while reports wait
        for fingerprint in self._fingerprints:
            try:
                self.seal.for_plant(fingerprint).for_run(response.run).check(
                    response, "the supervisor's answer", answering=request
                )
            except SealError:
                continue
            break
        else:
            return  # not this key's supervisor of a plant whose reports wait
        self.live = response.run
        held, self._held = self._held, deque(maxlen=HELD)
        self._fingerprints.clear()
        for run, msg in held:
            if run == self.live:
                self.show(msg)
            elif run not in self._left_out:
                self._left_out.add(run)
                self.say(
                    f"left out: reports of run {run[:12]}, sealed with this run's key, but the run's supervisor "
                    f"runs {self.live[:12]} (a replay of a recorded run, or another run with the same key)"
                )
