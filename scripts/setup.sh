#!/usr/bin/env bash
# Sets up .venv in the repository root: CPU PyTorch (pinned), the package in editable
# mode, its test tools, and ROS 2 from PyPI when no system ROS 2 (rclpy) is present.
# Safe to run again; it only installs what is missing.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON=${PYTHON:-python3}

if "$PYTHON" -c "import rclpy" 2>/dev/null; then
  echo "setup: using the system ROS 2 (rclpy found); .venv sees system site-packages"
  venv_flags=(--system-site-packages)
  extras="test,posegraph,odometry,docs"
else
  echo "setup: no system ROS 2 found; installing the ROS 2 Jazzy wheels from PyPI into .venv"
  venv_flags=()
  extras="ros,test,posegraph,odometry,docs"
fi

# Debian's colcon, for the test that builds the package as ament_python (root + apt only).
if ! command -v colcon >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing Debian's colcon"
    (apt-get install -y -qq colcon >/dev/null 2>&1 || { apt-get update -qq && apt-get install -y -qq colcon; }) >/dev/null \
      || echo "setup: could not install colcon; the colcon build test will be skipped"
  else
    echo "setup: colcon not found and not root; the colcon build test will be skipped"
  fi
fi

[ -x .venv/bin/python ] || "$PYTHON" -m venv "${venv_flags[@]}" .venv
pip=(.venv/bin/python -m pip install --quiet --disable-pip-version-check)
# A .venv made before the ros extra named Jazzy holds Kilted's wheels (ros-rclpy 9.x, no
# ros-jazzy-rclpy): remove every ros-* wheel so that no Kilted library is left beside Jazzy's.
if [[ ",${extras}," == *",ros,"* ]] && .venv/bin/python -m pip show -q ros-rclpy >/dev/null 2>&1 \
    && ! .venv/bin/python -m pip show -q ros-jazzy-rclpy >/dev/null 2>&1; then
  echo "setup: replacing the ROS 2 wheels of an earlier setup (not Jazzy's) with Jazzy's"
  .venv/bin/python -m pip freeze --disable-pip-version-check | sed -n 's/^\(ros-[A-Za-z0-9_.-]*\)==.*/\1/p' \
    | xargs -r .venv/bin/python -m pip uninstall -y -q --disable-pip-version-check
fi
# torch first and pinned: an unpinned torch pulls several GB of CUDA packages.
"${pip[@]}" "torch==2.13.0"
"${pip[@]}" -e ".[${extras}]"
echo "setup: done ($(.venv/bin/python -c 'import torch, faiss; print("torch", torch.__version__, "faiss", faiss.__version__)'))"
