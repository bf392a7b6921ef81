#!/usr/bin/env bash
# Make tf2_msgs (the TFMessage that /tf and /tf_static carry) importable in the venv.
# ROS 2 from PyPI has no tf2 packages; the rosidl generators and ament_cmake are on PyPI, so the
# interface is built from its definition (interfaces/tf2_msgs) into the venv prefix.
# Idempotent: where tf2_msgs already imports (a real ROS install, or an earlier build) it does
# nothing. Called by setup.sh; usage: bash launch_scripts/build_tf2_msgs.sh [VENV]
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${1:-${RSVO_VENV:-$REPO_ROOT/.venv}}"
PY="$VENV/bin/python"

found="$(AMENT_PREFIX_PATH="$VENV:${AMENT_PREFIX_PATH:-}" "$PY" -c \
    'import tf2_msgs.msg, os; print(os.path.dirname(tf2_msgs.__file__))' 2>/dev/null || true)"
if [ -n "$found" ]; then
    echo "[setup] tf2_msgs: found ($found)"
    exit 0
fi
echo "[setup] tf2_msgs: not installed; building it from interfaces/tf2_msgs (about 20 s)"

# The message wheels' exported CMake files name the wheel builder's Python and numpy include
# directories (/opt/python/cp3XX-.../include); point them at this venv's. Only files that still
# name the builder's paths are touched, so a second run finds nothing to do.
py_include="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
np_include="$("$PY" -c 'import numpy; print(numpy.get_include())')"
if [ ! -f "$py_include/Python.h" ]; then
    echo "[setup] tf2_msgs: no Python.h under $py_include (install the Python development" \
         "headers); /tf will not be published" >&2
    exit 1
fi
mapfile -t stale < <(grep -rl --include='*.cmake' '/opt/python/cp' "$VENV/share" 2>/dev/null || true)
if [ "${#stale[@]}" -gt 0 ]; then
    echo "[setup] tf2_msgs: re-pointing ${#stale[@]} exported CMake files at $py_include"
    sed -i -E \
        -e "s#/opt/python/cp[0-9]+-cp[0-9]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#$np_include#g" \
        -e "s#/opt/python/cp[0-9]+-cp[0-9]+/include/python3\.[0-9]+#$py_include#g" \
        "${stale[@]}"
fi

build="$(mktemp -d "${TMPDIR:-/tmp}/rsvo_tf2_msgs.XXXXXX")"
trap 'rm -rf "$build"' EXIT
export AMENT_PREFIX_PATH="$VENV:${AMENT_PREFIX_PATH:-}"
export CMAKE_PREFIX_PATH="$VENV:${CMAKE_PREFIX_PATH:-}"
export PATH="$VENV/bin:$PATH"
if ! { cmake -S "$REPO_ROOT/interfaces/tf2_msgs" -B "$build" -DCMAKE_INSTALL_PREFIX="$VENV" \
        -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF \
        && cmake --build "$build" -j2 && cmake --install "$build"; } > "$build/log" 2>&1; then
    tail -30 "$build/log" >&2
    echo "[setup] tf2_msgs: build failed (log above); /tf will not be published" >&2
    exit 1
fi
"$PY" -c 'import tf2_msgs.msg' && echo "[setup] tf2_msgs: built and installed into $VENV"
