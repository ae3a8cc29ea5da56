#!/usr/bin/env bash
# One idempotent set-up step for a fresh Debian 12 machine with Python 3.11:
#   1. Debian libraries open3d needs + cmake/g++ (installed when root, else the apt line is printed)
#   2. ./.venv (override with VENV=...) with the pinned requirements
#   3. the terrain_msgs interface package built from msg/ into the venv
#   4. this project installed editable, with its console scripts
# Each step records a fingerprint of its inputs in the venv and is skipped when nothing changed,
# so a second run takes about a second and changes nothing.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"
STAMPS="$VENV/.terrain_setup"
APT_PKGS=(libusb-1.0-0 libgl1 libegl1 libx11-6 cmake g++ make)

say() { printf '[setup] %s\n' "$*"; }
fingerprint() { cat "$@" 2>/dev/null | sha256sum | cut -d' ' -f1; }
stamp_ok() { [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]; }
stamp_set() { mkdir -p "$STAMPS"; printf '%s' "$2" > "$STAMPS/$1"; }

# ---- 1. system packages -------------------------------------------------------------------
missing=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    say "installing Debian packages: ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "Missing Debian packages. Run this once, then run the same command again:" >&2
    echo "  sudo apt-get install -y ${missing[*]}" >&2
    exit 1
  fi
fi

# ---- 2. virtual environment ---------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' 2>/dev/null || {
    echo "Python 3.11 is required (ROS 2 Jazzy wheels are built for it); set PYTHON=..." >&2
    exit 1; }
  say "creating $VENV"
  "$PY" -m venv "$VENV"
fi
req_fp=$(fingerprint "$ROOT/requirements.txt" "$ROOT/constraints.txt")
if ! stamp_ok requirements "$req_fp"; then
  say "installing pinned requirements (first run takes a few minutes)"
  "$VENV/bin/python" -m pip install -q --upgrade pip setuptools wheel
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements.txt" -c "$ROOT/constraints.txt"
  rm -f "$STAMPS/msgs" "$STAMPS/project"
  stamp_set requirements "$req_fp"
fi

# ---- 3. terrain_msgs ----------------------------------------------------------------------
msg_fp=$(fingerprint "$ROOT"/msg/*.msg "$ROOT/msg/CMakeLists.txt" "$ROOT/msg/package.xml")
if ! stamp_ok msgs "$msg_fp"; then
  say "building the terrain_msgs interface package"
  # The wheels' exported CMake files name the wheel builder's Python and numpy include dirs.
  pyinc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  npinc=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')
  { grep -rl '/opt/python/cp311-cp311' "$VENV/share" --include='*.cmake' 2>/dev/null || true; } \
  | while read -r f; do
    sed -i -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$npinc#g" \
           -e "s#/opt/python/cp311-cp311/include/python3.11#$pyinc#g" "$f"
  done
  build="$ROOT/build/terrain_msgs"
  rm -rf "$build"
  mkdir -p "$build"
  (
    cd "$build"
    export PATH="$VENV/bin:$PATH"
    cmake "$ROOT/msg" -DCMAKE_INSTALL_PREFIX="$VENV" -DCMAKE_PREFIX_PATH="$VENV" \
      -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
      -DCMAKE_BUILD_TYPE=Release > cmake.log 2>&1 || { tail -30 cmake.log >&2; exit 1; }
    make -j"$(nproc)" > make.log 2>&1 || { tail -30 make.log >&2; exit 1; }
    make install > install.log 2>&1 || { tail -30 install.log >&2; exit 1; }
  )
  "$VENV/bin/python" -c 'import terrain_msgs.msg' || { echo "terrain_msgs did not import" >&2; exit 1; }
  stamp_set msgs "$msg_fp"
fi

# ---- 4. the project (editable) ------------------------------------------------------------
proj_fp=$(fingerprint "$ROOT/setup.py" "$ROOT/package.xml")
if ! stamp_ok project "$proj_fp"; then
  say "installing the project (editable) and its console scripts"
  # compat mode: a .pth with the repo root, so packages added later import without reinstalling
  mkdir -p "$STAMPS"
  "$VENV/bin/python" -m pip install -q --no-deps --no-build-isolation \
    --config-settings editable_mode=compat -e "$ROOT" > "$STAMPS/project.log" 2>&1 \
    || { tail -30 "$STAMPS/project.log" >&2; exit 1; }
  stamp_set project "$proj_fp"
fi
say "ready: $VENV"
