#!/usr/bin/env bash
# Builds (once) the sweep launcher's own venv with Ray Tune at the pinned version and prints its
# python (.deps/sweep-venv, git-ignored). Python lives only here, never in the build.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.deps/sweep-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import ray.tune, tensorboardX' 2>/dev/null; then
  echo "sweep-venv: building $venv (ray[tune]==2.60.0, tensorboardX)" >&2
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "ray[tune]==2.60.0" "tensorboardX==2.6.4" >&2
fi
echo "$venv/bin/python"
