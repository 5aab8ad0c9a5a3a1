#!/usr/bin/env bash
# Idempotent setup: fetches the native pieces gaitscope links against, from PyPI only,
# into the git-ignored folder .deps/. Safe to run any number of times.
#   .deps/mujoco/lib/libmujoco.so.3.17.0  (+ libmujoco.so link)  from the mujoco==3.17.0 wheel
set -euo pipefail

MUJOCO_VERSION=3.17.0
root=$(cd "$(dirname "$0")/.." && pwd)
deps="$root/.deps"
lib_dir="$deps/mujoco/lib"
lib="$lib_dir/libmujoco.so.$MUJOCO_VERSION"

if [ ! -s "$lib" ]; then
  echo "setup: fetching libmujoco $MUJOCO_VERSION from PyPI (mujoco==$MUJOCO_VERSION wheel)"
  wheels="$deps/wheels"
  mkdir -p "$wheels" "$lib_dir"
  python3 -m pip download --quiet --no-deps --only-binary=:all: \
    --platform manylinux_2_28_x86_64 --python-version 3.11 \
    "mujoco==$MUJOCO_VERSION" -d "$wheels"
  wheel=$(ls "$wheels"/mujoco-"$MUJOCO_VERSION"-*.whl | head -n 1)
  # Unpack only the shared library; write to a temp name, then rename, so an
  # interrupted setup never leaves a truncated library behind.
  python3 - "$wheel" "$lib" <<'PY'
import os, shutil, sys, zipfile
wheel, dest = sys.argv[1], sys.argv[2]
member = "mujoco/" + os.path.basename(dest)
with zipfile.ZipFile(wheel) as zf, zf.open(member) as src, open(dest + ".tmp", "wb") as out:
    shutil.copyfileobj(src, out)
os.chmod(dest + ".tmp", 0o755)
os.replace(dest + ".tmp", dest)
PY
fi
ln -sfn "libmujoco.so.$MUJOCO_VERSION" "$lib_dir/libmujoco.so"
echo "setup: libmujoco ready in $lib_dir"
