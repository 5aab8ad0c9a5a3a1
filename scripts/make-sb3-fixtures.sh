#!/usr/bin/env bash
# Writes the import-sb3 fixtures (tests/fixtures/sb3_*.zip and sb3_reference.json) with
# Stable-Baselines3 itself, in a throwaway venv with the pinned versions (the peer benchmark's:
# the same pins, so one ~5 GB venv serves both). Not part of `make test`; the files are committed.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.deps/peers-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import stable_baselines3, torch' 2>/dev/null; then
  echo "make-sb3-fixtures: building $venv (stable-baselines3 2.9.2, torch, gymnasium 1.4.0, mujoco 3.17.0)"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "stable-baselines3==2.9.2" "sbx-rl==0.28.0" "gymnasium==1.4.0" \
    "mujoco==3.17.0" "torch==2.15.0" "jax==0.10.2" "jaxlib==0.10.2" "flax==0.12.8" "optax==0.2.8" \
    "numpy==2.4.6" "imageio==2.38.1" "packaging==26.4"
fi
exec "$venv/bin/python" "$root/tests/fixtures/make_sb3_fixtures.py" "$@"
