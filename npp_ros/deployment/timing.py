"""When commands go out: the watchdog that sends the safe command when fresh ones stop, and latency percentiles.

No ROS here: npp-deploy hands the watchdog its publishers as callables.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Literal, TypeVar

import numpy as np

T = TypeVar("T")
Fresh = Literal["sent", "resumed", "disarmed"]


class Watchdog:
    """Sends the safe command once when no fresh command went out for ``timeout`` seconds while armed.

    Its own thread waits until the deadline, so the safe command goes out on time whatever the executor
    is doing. Deciding that the deadline passed and sending the safe command (``on_expire(age_s)``) are
    one step under the lock that :meth:`send_fresh` holds while it sends a fresh command and restarts
    the clock: a safe command never goes out after a fresh one that beat its deadline, and no fresh
    command goes out after :meth:`disarm` sent the safe one. ``after_expire(age_s)`` (logging, reporting)
    runs after the lock is released, so it never delays a fresh command.
    """

    def __init__(
        self,
        timeout: float,
        on_expire: Callable[[float], None],
        after_expire: Callable[[float], None] | None = None,
    ) -> None:
        if not timeout > 0:
            raise ValueError(f"the watchdog timeout must be > 0, got {timeout!r}")
        self.timeout = float(timeout)
        self._on_expire = on_expire
        self._after_expire = after_expire
        self._last = time.monotonic()
        self._armed = False
        self.expired = False
        self.fired = 0
        self._wake = threading.Condition()  # its lock is re-entrant: on_expire may read the watchdog
        self._closed = False
        self._thread = threading.Thread(target=self._watch, name="npp-watchdog", daemon=True)
        self._thread.start()

    @property
    def armed(self) -> bool:
        return self._armed

    def send_fresh(self, send: Callable[[], None]) -> Fresh:
        """Send a fresh command and restart the clock, as one step against the watchdog's own decision.

        "sent"; "resumed" when it ends an expiry (states flow again); "disarmed" when the watchdog is
        not armed, and then nothing is sent (commanding has stopped)."""
        with self._wake:
            if not self._armed:
                return "disarmed"
            send()
            self._last = time.monotonic()
            if not self.expired:
                return "sent"
            self.expired = False
            self._wake.notify()  # it sleeps without a deadline while expired
            return "resumed"

    def feed(self) -> bool:
        """Restart the clock without sending anything; True when it ends an expiry."""
        with self._wake:
            self._last = time.monotonic()
            if not self.expired:
                return False
            self.expired = False
            self._wake.notify()
            return True

    def arm(self) -> None:
        """Start watching now, as if a state had just arrived."""
        with self._wake:
            self._last = time.monotonic()
            self._armed, self.expired = True, False
            self._wake.notify()

    def disarm(self, send: Callable[[], T] | None = None) -> T | None:
        """Stop watching; ``send`` (the safe command) runs in the same step, so no fresh command follows it."""
        with self._wake:
            self._armed = False
            self._wake.notify()
            return None if send is None else send()

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=2.0)

    def _watch(self) -> None:
        with self._wake:
            while not self._closed:
                if not self._armed or self.expired:
                    self._wake.wait()
                    continue
                left = self._last + self.timeout - time.monotonic()
                if left > 0:
                    self._wake.wait(left)
                    continue
                self.expired = True
                self.fired += 1
                age = time.monotonic() - self._last
                self._on_expire(age)  # under the lock: the decision and the safe command are one step
                if self._after_expire is not None:
                    self._wake.release()
                    try:
                        self._after_expire(age)
                    finally:
                        self._wake.acquire()


def percentiles(samples: Sequence[float], quantiles: Sequence[float] = (50, 99)) -> list[float]:
    """The given percentiles of the samples (NaN when there are none)."""
    if len(samples) == 0:
        return [math.nan for _ in quantiles]
    return [float(v) for v in np.percentile(np.asarray(samples, dtype=np.float64), quantiles)]
