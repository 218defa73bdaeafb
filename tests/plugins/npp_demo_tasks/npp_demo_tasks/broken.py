"""A plug-in task whose module does not import: npp_ros must name it with its error and keep the others."""

from __future__ import annotations

import npp_demo_tasks_missing_dependency  # noqa: F401  # not installed, on purpose

TASK = None
