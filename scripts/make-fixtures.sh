#!/usr/bin/env bash
# Regenerates the Gymnasium reference trajectories in tests/fixtures/ from Gymnasium itself, in a
# throwaway venv with the pinned versions (not part of `make test`; the files are committed).
#   scripts/make-fixtures.sh           # write tests/fixtures/gymnasium_ant_v4_*_parity.json
#   scripts/make-fixtures.sh --check   # exit 1 unless a fresh run reproduces them byte for byte
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.deps/fixture-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import gymnasium, mujoco' 2>/dev/null; then
  echo "make-fixtures: building $venv (gymnasium 1.4.0, mujoco 3.17.0, numpy, imageio and packaging for Gymnasium's MuJoCo import)"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "gymnasium==1.4.0" "mujoco==3.17.0" "numpy==2.4.6" "imageio==2.38.1" "packaging==26.4"
fi
exec "$venv/bin/python" "$root/tests/fixtures/make_gymnasium_fixtures.py" "$@"
