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

# The stock Rerun viewer (only with `--viewer`): the `rerun` executable from PyPI's
# rerun-sdk==0.36.3 wheel, unpacked into .deps/rerun/. Not needed to record or test.
RERUN_VERSION=0.36.3
if [ "${1:-}" = "--viewer" ]; then
  viewer_dir="$deps/rerun"
  viewer="$viewer_dir/rerun"
  if [ ! -x "$viewer" ]; then
    echo "setup: fetching the Rerun $RERUN_VERSION viewer from PyPI (rerun-sdk==$RERUN_VERSION wheel)"
    wheels="$deps/wheels"
    mkdir -p "$wheels" "$viewer_dir"
    python3 -m pip download --quiet --no-deps --only-binary=:all: \
      --platform manylinux_2_28_x86_64 --python-version 3.11 \
      "rerun-sdk==$RERUN_VERSION" -d "$wheels"
    wheel=$(ls "$wheels"/rerun_sdk-"$RERUN_VERSION"-*.whl | head -n 1)
    python3 - "$wheel" "$viewer" <<'PY'
import os, shutil, sys, zipfile
wheel, dest = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(wheel) as zf, zf.open("rerun_sdk/rerun_cli/rerun") as src, open(dest + ".tmp", "wb") as out:
    shutil.copyfileobj(src, out)
os.chmod(dest + ".tmp", 0o755)
os.replace(dest + ".tmp", dest)
PY
    rm -f "$wheel"
  fi
  "$viewer" analytics disable >/dev/null 2>&1 || true
  echo "setup: Rerun viewer ready: $viewer"
fi
