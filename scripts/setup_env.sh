#!/usr/bin/env bash
# Sets up the project environment in .venv: ROS 2 Jazzy wheels from PyPI, pinned numerics,
# the meshfg_msgs interfaces generated and installed into the venv, and meshfg_ros itself.
# Idempotent: a stamp (hash of every input) makes a second run return in well under a second.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
STAMP="$VENV/.meshfg-setup-stamp"
cd "$ROOT"

inputs_hash() {
  cat requirements.txt requirements-core.txt scripts/setup_env.sh setup.py setup.cfg package.xml \
      meshfg_msgs/CMakeLists.txt meshfg_msgs/package.xml meshfg_msgs/msg/*.msg | sha256sum | cut -d' ' -f1
}

if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$(inputs_hash)" && -x "$VENV/bin/meshfg" ]]; then
  exit 0
fi

log() { echo "[setup] $*" >&2; }

PYTHON="${MESHFG_PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null && "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PYTHON="$candidate"; break
    fi
  done
fi
if [[ -z "$PYTHON" ]]; then
  echo "[setup] error: Python 3.11 is required (the ROS 2 Jazzy PyPI wheels are cp311 only); set MESHFG_PYTHON" >&2
  exit 1
fi

if [[ ! -x "$VENV/bin/python" ]]; then
  log "creating virtual environment $VENV with $PYTHON"
  "$PYTHON" -m venv "$VENV"
fi
PY="$VENV/bin/python"

log "installing pinned packages (requirements.txt)"
"$PY" -m pip install --quiet --disable-pip-version-check -r requirements.txt

# Packaging defect of the ROS wheels: their exported CMake files hard-code the build host's
# Python and numpy include directories (/opt/python/cp311-cp311/...), so any package that
# generates Python interfaces fails to configure. Point them at this venv's Python and numpy.
# Only files inside this project's venv are touched.
PY_INCLUDE="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
NUMPY_INCLUDE="$("$PY" -c 'import numpy; print(numpy.get_include())')"
{ grep -rlZ --include='*.cmake' '/opt/python/cp311-cp311' "$VENV" 2>/dev/null || true; } | xargs -0 -r sed -i \
  -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#${NUMPY_INCLUDE}#g" \
  -e "s#/opt/python/cp311-cp311/include/python3.11#${PY_INCLUDE}#g"

log "generating and installing meshfg_msgs into the venv"
BUILD="$ROOT/build/venv/meshfg_msgs"
mkdir -p "$BUILD"
export AMENT_PREFIX_PATH="$VENV"
cmake -S meshfg_msgs -B "$BUILD" -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
  -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF >"$BUILD/configure.log" 2>&1 \
  || { cat "$BUILD/configure.log" >&2; exit 1; }
cmake --build "$BUILD" -j "$(nproc)" >"$BUILD/build.log" 2>&1 || { tail -50 "$BUILD/build.log" >&2; exit 1; }
cmake --install "$BUILD" >"$BUILD/install.log" 2>&1 || { tail -50 "$BUILD/install.log" >&2; exit 1; }

log "installing meshfg_ros (editable) into the venv"
"$PY" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e . \
  >"$BUILD/pip-editable.log" 2>&1 || { cat "$BUILD/pip-editable.log" >&2; exit 1; }

"$PY" -c 'import rclpy, meshfg_msgs.msg, meshfg_ros' || { echo "[setup] error: import check failed" >&2; exit 1; }
inputs_hash >"$STAMP"
log "environment ready: $VENV"
