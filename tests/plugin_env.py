"""The demo plug-in package (tests/plugins/npp_demo_tasks) installed as a user would install one, into a folder.

Installed with pip into a temporary --target, not into the venv: the tests that need it put the folder on
the path (sys.path in process, PYTHONPATH for the processes they start), so npp_ros sees the plug-in's
entry points exactly as it sees an installed package's, and nothing outside the tests lists the demo tasks.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

PLUGIN_SOURCE = Path(__file__).resolve().parent / "plugins" / "npp_demo_tasks"


def install_demo_plugin(target: Path) -> Path:
    """pip install --no-deps the demo plug-in into ``target``; returns ``target``.

    Built from a copy beside ``target``: a build leaves build/ and egg-info folders in its source tree.
    """
    source = target.parent / f"{target.name}-source"
    shutil.copytree(PLUGIN_SOURCE, source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "--no-deps",
         "--no-build-isolation", "--no-index", "--target", str(target), str(source)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    return target


def with_plugin_path(target: Path, environ: dict[str, str] | None = None) -> dict[str, str]:
    """An environment whose Python processes see the plug-in folder."""
    env = dict(os.environ if environ is None else environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(target), env.get("PYTHONPATH", "")) if p)
    return env
