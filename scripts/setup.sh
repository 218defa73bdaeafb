#!/usr/bin/env bash
# Creates the project's virtual environment from the pinned set and builds the ROS interfaces.
# Idempotent: `make` re-runs it only when requirements.lock, pyproject.toml or msgs_py/ change.
# Usage: scripts/setup.sh [VENV_DIR]   (default: .venv in the repository)
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${1:-$repo/.venv}"
python="${PYTHON:-python3}"

if ! "$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "setup: npp_ros needs Python 3.11 (the ROS Jazzy wheels are cp311); found $("$python" --version 2>&1)" >&2
  exit 1
fi
if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating $venv" >&2
  "$python" -m venv "$venv"
fi
echo "setup: installing the pinned dependency set (requirements.lock)" >&2
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$repo/requirements.lock"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e "$repo"
if [ -d "$repo/msgs_py/npp_interfaces" ]; then
  echo "setup: building the ROS interfaces (msgs_py/npp_interfaces)" >&2
  bash "$repo/scripts/build_interfaces.sh" "$venv"
fi
# The dashboard's browser test (tests/ros/test_dashboard.py) needs a headless Chromium: Debian's, where apt is
# available and we may use it; elsewhere the test is skipped outside CI and says why.
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  echo "setup: installing chromium (apt) for the dashboard's browser test" >&2
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "setup: could not install chromium, which tests/ros/test_dashboard.py needs" >&2
fi
touch "$venv/.npp-setup-done"
echo "setup: done ($venv)" >&2
