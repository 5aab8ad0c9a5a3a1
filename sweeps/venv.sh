#!/usr/bin/env bash
# Builds (once) the sweep launcher's own venv with Ray Tune at the pinned version and prints its
# python (.deps/sweep-venv, git-ignored). Python lives only here, never in the build.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.deps/sweep-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import ray.tune, tensorboardX, optuna' 2>/dev/null; then
  echo "sweep-venv: building $venv (ray[tune]==2.60.0, tensorboardX, optuna)" >&2
  python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
    { echo "sweep-venv: needs Python ≥ 3.11 (tomllib), found $(python3 --version 2>&1)" >&2; exit 1; }
  python3 -m venv "$venv" ||
    { echo "sweep-venv: python3 -m venv failed (on Debian: apt-get install python3-venv)" >&2; exit 1; }
  "$venv/bin/pip" install --quiet "ray[tune]==2.60.0" "tensorboardX==2.6.4" "optuna==4.5.0" >&2
fi
echo "$venv/bin/python"
