"""The core package must run without ROS: nodes adapt it, never the other way round."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import npp_ros

CORE = Path(npp_ros.__file__).parent


def test_no_core_source_mentions_rclpy() -> None:
    offenders = [str(p) for p in CORE.rglob("*.py") if "rclpy" in p.read_text() or "npp_interfaces" in p.read_text()]
    assert offenders == []


def test_importing_every_core_module_loads_no_ros() -> None:
    modules = [m.name for m in pkgutil.walk_packages([str(CORE)], prefix="npp_ros.")]
    assert "npp_ros.loop" in modules and "npp_ros.bounds" in modules
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('rclpy', 'rosidl', 'npp_interfaces')))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_importing_the_plant_loads_no_compiled_index() -> None:
    """npp_ros.lqr and the loop's records are light: numba and the kd-tree load only with the policy."""
    code = (
        "import sys, npp_ros.lqr\n"
        "print(','.join(sorted(m for m in sys.modules if m.startswith(('numba', 'npp_ros.kdtree')))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
