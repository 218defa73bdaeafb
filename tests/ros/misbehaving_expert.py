"""The example external expert (examples/external_expert) made to misbehave one way: a real process to refuse.

NPP_TEST_FAULT names the fault: wrong_dimensions (a state entry short), non_finite (a NaN value),
inflated_values (every value 1000 above what its trajectory earns), inconsistent_values (values
from step 10 on raised by 0.5, so consecutive values contradict the step's reward). Run as
``python -m misbehaving_expert`` with tests/ros on PYTHONPATH.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples" / "external_expert"))
from lqr_expert import ExternalLQRExpert, main  # the example is not a package

FAULTS = ("wrong_dimensions", "non_finite", "inflated_values", "inconsistent_values")


class MisbehavingExpert(ExternalLQRExpert):
    """Answers as the example does, then breaks the answer the way NPP_TEST_FAULT says (sealed all the same)."""

    fault = os.environ.get("NPP_TEST_FAULT", "")

    def fill(self, response, states: np.ndarray, actions: np.ndarray, values: np.ndarray, ret: float) -> None:  # type: ignore[override]
        values = values.copy()
        if self.fault == "wrong_dimensions":
            states = states[:, :-1]
        elif self.fault == "non_finite":
            values[3] = math.nan
        elif self.fault == "inflated_values":
            values += 1000.0
        elif self.fault == "inconsistent_values":
            values[10:] += 0.5
        else:
            raise ValueError(f"NPP_TEST_FAULT must be one of {', '.join(FAULTS)}, got {self.fault!r}")
        super().fill(response, states, actions, values, ret)


if __name__ == "__main__":
    sys.exit(main(MisbehavingExpert))
