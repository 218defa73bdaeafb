"""Why a node refuses to start: the error every node's settings raise and the node runtime reports.

Apart from the parameters it is about, so that a tool on the node runtime imports it without the run's settings.
"""

from __future__ import annotations


class StartupError(RuntimeError):
    """A node refuses to start; the message says why."""
