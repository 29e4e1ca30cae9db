#!/usr/bin/env bash
# Installs the benchmark-only reference (Stable-Baselines3, pinned) outside the clone and the venv:
# ~/.cache/comper/reference-sb3-<version>. Not a dependency of the suite; benchmarks/sb3_reference.py
# and `learning_bench.py --algorithms ... sb3_ddpg` find it there. Needs `make setup` first.
set -euo pipefail
cd "$(dirname "$0")/.."
SB3_VERSION=2.9.2
CLOUDPICKLE_VERSION=3.1.2
DEST="${COMPER_CACHE:-$HOME/.cache/comper}/reference-sb3-$SB3_VERSION"
if [ -d "$DEST/stable_baselines3" ]; then
  echo "[reference] stable-baselines3 $SB3_VERSION already in $DEST"; exit 0
fi
set +u  # colcon's local_setup.bash reads unset variables
. ./env.sh
set -u
# --no-deps: its dependencies (torch, gymnasium, numpy) are the venv's; cloudpickle is the one extra
python -m pip install --quiet --no-deps --target "$DEST.tmp" "stable-baselines3==$SB3_VERSION" \
  "cloudpickle==$CLOUDPICKLE_VERSION"
mv "$DEST.tmp" "$DEST"
echo "[reference] stable-baselines3 $SB3_VERSION installed in $DEST"
