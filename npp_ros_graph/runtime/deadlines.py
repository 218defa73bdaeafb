"""Service calls with deadlines, from a node's worker thread: what a pause of either end cannot hang.

A request or its answer is lost when either end was paused past the middleware's lease (a SIGSTOP,
a debugger, a starved host); a caller here notices and sends it again instead of waiting out its deadline.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from rclpy.client import Client
from rclpy.impl.rcutils_logger import RcutilsLogger

# A sim or policy that was paused (SIGSTOP, a debugger, an overloaded host) may have lost what was sent to
# it meanwhile: a reset unanswered this long is sent again, and trajectories the policy still lacks after
# this long are published again, so an episode never waits its whole rollout_timeout for data already stored.
RESEND_S = 2.0


def call_with_deadline(client: Client, request: Any, timeout: float, logger: RcutilsLogger) -> Any | None:
    """One service call with a deadline; an unanswered request is withdrawn, not left pending forever.

    The server leaves the graph and comes back, or this process finds that far more time passed than
    it waited: then the request is sent again (services here answer a repeated request the same way).
    None when the deadline passes first.
    """
    deadline = time.monotonic() + timeout
    while True:
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _f, done=done: done.set())
        left = False
        while True:
            before = time.monotonic()
            if done.wait(min(RESEND_S, max(deadline - before, 0.0))):
                return future.result()
            now = time.monotonic()
            if now >= deadline:
                client.remove_pending_request(future)
                future.cancel()
                return None
            ready = client.service_is_ready()
            left = left or not ready
            if ready and (left or now - before > 3 * RESEND_S):
                break
        client.remove_pending_request(future)
        future.cancel()
        logger.info(
            f"{client.srv_name}: the request may have been lost in a pause; sending it again",
            throttle_duration_sec=5.0,
        )
