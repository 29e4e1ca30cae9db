#!/usr/bin/env bash
# Print the path of a working CPython 3.12 (the ROS 2 Jazzy wheels are cp312 only).
# Honours $COMPER_PYTHON. Exits 1 with an explanation when none is found.
set -u
try() { [ -n "$1" ] && [ -x "$1" ] && "$1" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 12) else 1)' >/dev/null 2>&1 && { echo "$1"; exit 0; }; }
try "${COMPER_PYTHON:-}"
try "$(command -v python3.12 2>/dev/null)"
for p in "$HOME"/.pyenv/versions/3.12*/bin/python3.12 /root/.pyenv/versions/3.12*/bin/python3.12 \
         /usr/local/bin/python3.12 /usr/bin/python3.12 /opt/python/cp312-cp312/bin/python3.12; do
  try "$p"
done
cat >&2 <<'MSG'
error: no Python 3.12 interpreter found.
  The ROS 2 Jazzy wheels on PyPI (ros-jazzy-*) are built for CPython 3.12 only.
  Install one (e.g. `pyenv install 3.12`, or your distribution's python3.12 with venv support)
  or point COMPER_PYTHON at it: COMPER_PYTHON=/path/to/python3.12 make setup
MSG
exit 1
