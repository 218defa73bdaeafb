"""A task file's values read with their types checked: every refusal names the file and the dotted key.

The modules that read a task file (npp_ros.tasks.task_file.schema, _model, _terms) share one
:class:`Reader` per file, so every problem is one line: ``task file PATH: KEY: PROBLEM``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


class TaskFileError(ValueError):
    """A task file that cannot define a task; the message names the file, the key and the problem."""


class Reader:
    """Typed access to the parsed file, every refusal naming the dotted key."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, key: str, problem: str) -> TaskFileError:
        return TaskFileError(f"task file {self.path}: {key}: {problem}")

    def unknown_keys(self, table: dict[str, Any], allowed: set[str], where: str) -> None:
        for key in table:
            if key not in allowed:
                known = ", ".join(sorted(allowed))
                raise self.fail(f"{where}{key}", f"unknown key (known here: {known})")

    def number(self, value: Any, key: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(key, f"must be > 0, got {value!r}")
        return float(value)

    def non_negative(self, value: Any, key: str) -> float:
        """A finite number >= 0 (a margin, a weight that may be zero)."""
        number = self.number(value, key)
        if number < 0:
            raise self.fail(key, f"must be >= 0, got {number:g}")
        return number

    def text(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        return value

    def names(self, value: Any, key: str) -> list[str]:
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise self.fail(key, f"must be a list of names, got {value!r}")
        return list(value)

    def interval(self, value: Any, key: str) -> tuple[float, float]:
        if not isinstance(value, list) or len(value) != 2:
            raise self.fail(key, f"must be [low, high], got {value!r}")
        low, high = (self.number(v, key) for v in value)
        if low > high:
            raise self.fail(key, f"is empty: low {low:g} > high {high:g}")
        return low, high

    def table(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a table, got {value!r}")
        return value
