#!/usr/bin/env bash
# Builds (once) the Python venv with Stable-Baselines3, SBX, torch, JAX, Gymnasium and MuJoCo at
# the pinned versions, and prints its python. Shared by scripts/bench-peers.sh and
# scripts/make-sb3-fixtures.sh (~5 GB with torch; in .deps/, git-ignored).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.deps/peers-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import sbx, stable_baselines3, torch' 2>/dev/null; then
  echo "peers-venv: building $venv (stable-baselines3, sbx-rl, torch, jax, gymnasium, mujoco)" >&2
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "stable-baselines3==2.9.2" "sbx-rl==0.28.0" "gymnasium==1.4.0" \
    "mujoco==3.17.0" "torch==2.15.0" "jax==0.10.2" "jaxlib==0.10.2" "flax==0.12.8" "optax==0.2.8" \
    "numpy==2.4.6" "imageio==2.38.1" "packaging==26.4" >&2
fi
echo "$venv/bin/python"
