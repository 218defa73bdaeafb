"""The core package must run without ROS: nodes adapt it, never the other way round.

Statically, no core module imports ROS or npp_ros_graph, not even inside a function
(tests/test_layering.py); here, importing every core module is seen to load none of it.
"""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import npp_ros

CORE = Path(npp_ros.__file__).parent


def test_importing_every_core_module_loads_no_ros() -> None:
    modules = [m.name for m in pkgutil.walk_packages([str(CORE)], prefix="npp_ros.")]
    assert "npp_ros.run.loop" in modules and "npp_ros.policy.bounds" in modules
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('rclpy', 'rosidl', 'npp_interfaces', 'npp_ros_graph')))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_importing_the_plant_loads_no_compiled_index() -> None:
    """npp_ros.tasks.builtin.lqr and the loop's records are light: numba and the kd-tree load only with the policy."""
    code = (
        "import sys, npp_ros.tasks.builtin.lqr\n"
        "print(','.join(sorted(m for m in sys.modules if m.startswith(('numba', 'npp_ros.policy.kdtree')))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
