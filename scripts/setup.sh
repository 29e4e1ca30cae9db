#!/usr/bin/env bash
# One idempotent set-up of the workspace (what `make setup` runs; `make run` and `make test` call it):
#   0. decides where ROS 2 Jazzy comes from (scripts/ros_install.sh detect): a full install that is sourced
#      (ROS_DISTRO=jazzy, its prefix on AMENT_PREFIX_PATH) or at /opt/ros/jazzy is used as it is
#      ("system" mode: steps 1-5 below change as marked); otherwise the PyPI wheels ("pypi" mode),
#   1. finds CPython 3.12 (the ROS 2 Jazzy wheels are cp312 only; system: the install's python3),
#   2. creates the virtual environment OUTSIDE the clone, cached by the hash of requirements.lock
#      ($COMPER_CACHE_DIR, default ~/.cache/comper), and installs the pinned lock into it,
#      and the test/benchmark extras of requirements-extras.lock next to it (--no-deps),
#      (system: a venv with --system-site-packages, from the lock without the ROS wheels and what the install
#      provides itself, scripts/ros_install.sh lock),
#   3. applies the wheel path fix the ros-jazzy CMake exports need (/opt/python/cp312-cp312; system: skipped),
#   4. builds the workspace with colcon (colcon.meta) when src/ changed since the last build,
#   5. writes env.sh: the one file to source (venv, ament paths, install/, the `ros2` stand-in; system: the
#      install's setup.bash first, and its real ros2 instead of the stand-in).
# A second run with nothing changed takes a few seconds.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
say() { printf '[setup] %s\n' "$*"; }
# one set-up at a time per clone (parallel `make test` runs would race in build/)
exec 8>"$ROOT/.setup.lock"
flock 8

# --- 0. where ROS 2 Jazzy comes from -----------------------------------------------------------
DETECT=$("$ROOT/scripts/ros_install.sh" detect)
ROS_MODE=${DETECT%% *}
ROS_PREFIX=""
CACHE=${COMPER_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/comper}
mkdir -p "$CACHE"
if [ "$ROS_MODE" = system ]; then
  ROS_PREFIX=${DETECT#system }
  say "ROS 2 Jazzy install at $ROS_PREFIX: building against it (venv with --system-site-packages, no ROS wheels; COMPER_ROS=pypi forces the wheels)"
  set +u; . "$ROS_PREFIX/setup.bash"; set -u      # ROS setup files read unset variables
  PY=$(command -v python3)
  if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' || ! "$PY" -c 'import rclpy' 2>/dev/null; then
    echo "error: after sourcing $ROS_PREFIX/setup.bash, $PY is not a Python 3.12 that imports rclpy" >&2
    exit 1
  fi
  LOCK=$(mktemp)
  trap 'rm -f "$LOCK"' EXIT
  "$ROOT/scripts/ros_install.sh" lock requirements.lock > "$LOCK"
  KEY=$( { cat "$LOCK"; echo "system $ROS_PREFIX"; "$PY" -c 'import sys; print(sys.version)'; } | sha256sum | cut -c1-16)
  VENV="$CACHE/venv-system-$KEY"
  VENV_ARGS=(--system-site-packages)
  say "system dependencies are rosdep's: rosdep install --from-paths src --ignore-src -y (not run here: it needs apt)"
else
  PY=$("$ROOT/scripts/find_python312.sh")
  LOCK=requirements.lock
  KEY=$( { cat requirements.lock; "$PY" -c 'import sys; print(sys.version)'; } | sha256sum | cut -c1-16)
  VENV="$CACHE/venv-$KEY"
  VENV_ARGS=()
fi

# --- 2. virtual environment -------------------------------------------------------------------
mkdir -p "$CACHE"
exec 9>"$CACHE/.venv.lock"   # and one venv creation at a time per cache (clones share it)
flock 9
if [ ! -f "$VENV/.comper-complete" ]; then
  say "creating the virtual environment $VENV (lock $KEY) with $PY; the first time takes a few minutes (torch is ~3 GB)"
  rm -rf "$VENV"
  mkdir -p "$CACHE"
  "$PY" -m venv "${VENV_ARGS[@]}" "$VENV"
  "$VENV/bin/python" -m pip install --quiet --no-input -r "$LOCK"
  touch "$VENV/.comper-complete"
  say "installed $(grep -c '==' "$LOCK") pinned packages"
else
  say "virtual environment up to date: $VENV"
fi
flock -u 9
ln -sfn "$VENV" "$ROOT/.venv"
VPY="$VENV/bin/python"
SITE=$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')

# --- 2b. test and benchmark extras (requirements-extras.lock: not runtime dependencies) ----------
EXTRAS_KEY=$( { cat requirements-extras.lock; echo "$KEY"; } | sha256sum | cut -c1-16)
EXTRAS="$CACHE/extras-$EXTRAS_KEY"
if [ ! -f "$EXTRAS/.comper-complete" ]; then
  say "installing the test/benchmark extras (requirements-extras.lock) into $EXTRAS"
  rm -rf "$EXTRAS" "$EXTRAS.tmp"
  # --no-deps: their dependencies are the venv's (requirements.lock)
  "$VPY" -m pip install --quiet --no-input --no-deps --target "$EXTRAS.tmp" -r requirements-extras.lock
  touch "$EXTRAS.tmp/.comper-complete"
  mv "$EXTRAS.tmp" "$EXTRAS"
fi

# --- 3. wheel path fix ------------------------------------------------------------------------
# The ros-jazzy wheels' exported CMake targets hard-code the paths of the machine that built them.
PYINC=$("$VPY" -c 'import sysconfig, os; print(os.path.dirname(sysconfig.get_paths()["include"]))')
FIXROOT=/opt/python/cp312-cp312
link_to() {  # link_to LINK TARGET: create or repoint a symlink we own; never replace a real directory
  local link=$1 target=$2
  if [ -L "$link" ]; then
    [ "$(readlink "$link")" = "$target" ] && return 0
    ln -sfn "$target" "$link"; say "repointed $link -> $target"
  elif [ -e "$link" ]; then
    say "kept existing $link (not a link of ours)"
  else
    mkdir -p "$(dirname "$link")" && ln -s "$target" "$link"; say "linked $link -> $target"
  fi
}
if [ "$ROS_MODE" = system ]; then
  :   # the install's CMake files name its own paths
elif [ -w /opt ] || [ -w "$FIXROOT" ] || [ "$(id -u)" = 0 ]; then
  link_to "$FIXROOT/include" "$PYINC"
  link_to "$FIXROOT/lib/python3.12/site-packages" "$SITE"
elif [ ! -e "$FIXROOT/include/python3.12/Python.h" ]; then
  echo "error: $FIXROOT must exist for the ROS wheels' CMake files and /opt is not writable." >&2
  echo "  run once as root: mkdir -p $FIXROOT/lib/python3.12 && ln -s $PYINC $FIXROOT/include && ln -s $SITE $FIXROOT/lib/python3.12/site-packages" >&2
  exit 1
fi

# --- 4. colcon build --------------------------------------------------------------------------
export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
if [ "$ROS_MODE" = pypi ]; then
  export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
fi   # system: the install's setup.bash set them
SRC_HASH=$( { echo "$VENV"; git ls-files -co --exclude-standard -- src colcon.meta | LC_ALL=C sort | xargs -r sha256sum; } | sha256sum | cut -c1-16)
STAMP="$ROOT/install/.comper-build-hash"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$SRC_HASH" ] && [ -f "$ROOT/install/local_setup.bash" ]; then
  say "workspace build up to date"
else
  # CMake caches the interpreter and include paths: a build made against another venv is stale
  if [ -f "$ROOT/build/.comper-venv" ] && [ "$(cat "$ROOT/build/.comper-venv")" != "$VENV" ]; then
    say "the venv changed since the last build: removing build/ and install/"
    rm -rf "$ROOT/build" "$ROOT/install"
  fi
  mkdir -p "$ROOT/build" && echo "$VENV" > "$ROOT/build/.comper-venv"
  say "colcon build (log: log/latest_build)"
  start=$(date +%s)
  if ! colcon build --metas colcon.meta --event-handlers console_cohesion- summary+ status- \
        > "$ROOT/.colcon-build.out" 2>&1; then
    tail -n 60 "$ROOT/.colcon-build.out" >&2
    echo "error: colcon build failed (full output: .colcon-build.out, log/latest_build)" >&2
    exit 1
  fi
  echo "$SRC_HASH" > "$STAMP"
  say "built $(ls "$ROOT/install" | grep -c '^comper_') packages in $(( $(date +%s) - start )) s"
fi

# --- 5. env.sh --------------------------------------------------------------------------------
STANDIN=""
real_ros2=$(PATH=$(printf '%s' "$PATH" | tr ':' '\n' | grep -v -x "$ROOT/scripts/ros2-standin" | paste -sd: -) command -v ros2 || true)
if [ -z "$real_ros2" ]; then
  STANDIN="$ROOT/scripts/ros2-standin"
else
  say "a real ros2 exists ($real_ros2): the stand-in is not put on PATH"
fi
if [ "$ROS_MODE" = system ]; then
  ROS_ENV=". \"$ROS_PREFIX/setup.bash\"   # the ROS 2 Jazzy install this workspace was built against"
  AMENT_ENV="# AMENT_PREFIX_PATH and CMAKE_PREFIX_PATH: set by the install's setup.bash"
else
  ROS_ENV="# ROS 2 Jazzy: the PyPI wheels in the venv"
  AMENT_ENV="export AMENT_PREFIX_PATH=\"$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}\"
export CMAKE_PREFIX_PATH=\"$VENV\${CMAKE_PREFIX_PATH:+:\$CMAKE_PREFIX_PATH}\""
fi
cat > "$ROOT/env.sh" <<ENV
# Generated by scripts/setup.sh: source it to use the workspace (ros2 run, python, pytest).
$ROS_ENV
export COMPER_ROOT="$ROOT"
export VIRTUAL_ENV="$VENV"
export PATH="${STANDIN:+$STANDIN:}$VENV/bin:\$PATH"
$AMENT_ENV
. "$ROOT/install/local_setup.bash"
# test and benchmark extras (requirements-extras.lock), after the workspace's own packages
export PYTHONPATH="\${PYTHONPATH:+\$PYTHONPATH:}$EXTRAS"
# DDS discovery stays on this host unless a range was chosen before sourcing (the nodes' entry points do the
# same): several hosts need ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (docs/security.md)
if [ -z "\${ROS_AUTOMATIC_DISCOVERY_RANGE:-}" ] && [ -z "\${ROS_LOCALHOST_ONLY:-}" ]; then
  export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
fi
ENV
say "ready: source $ROOT/env.sh"
