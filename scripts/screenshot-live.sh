#!/usr/bin/env bash
# The live viewer under Xvfb with Mesa software rendering: starts `gaitscope live` (the egui panel
# on GL/llvmpipe, the stock Rerun viewer on Vulkan/lavapipe), lets it run, and writes one image of
# both windows, then prints the panel frame rate and how far the sim kept up.
# Xvfb's framebuffer does not receive lavapipe's Vulkan presentation (xwd sees the viewer window
# black), so the viewer half is the viewer's own screenshot of the same session, saved with
# `--save` and opened with `--screenshot-to` right after; the panel half is an X screenshot taken
# while the session runs.
# Usage: scripts/screenshot-live.sh [OUT.png] [SECONDS] [-- more `gaitscope live` args]
# Works on a fresh Debian/Ubuntu machine (installs Xvfb, Mesa and xwd with apt when missing).
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-docs/live.png}"
secs="${2:-10}"
shift $(( $# < 2 ? $# : 2 ))
[ "${1:-}" = "--" ] && shift
target="${CARGO_TARGET_DIR:-target}"
./scripts/setup.sh --viewer >/dev/null
need=()
command -v Xvfb >/dev/null || need+=(xvfb xauth)
command -v xwd >/dev/null || need+=(x11-apps)
[ -x /usr/bin/convert ] || need+=(imagemagick)  # /usr/bin: not a stand-in earlier on PATH
[ -e /usr/share/vulkan/icd.d/lvp_icd.x86_64.json ] || need+=(mesa-vulkan-drivers)
ldconfig -p | grep -q libGL.so.1 || need+=(libgl1 libgl1-mesa-dri libegl1)
ldconfig -p | grep -q libxkbcommon-x11 || need+=(libxkbcommon-x11-0 libxcursor1 libxrandr2 libxi6)
ldconfig -p | grep -q libudev.so.1 || need+=(libudev1)
if [ ${#need[@]} -gt 0 ]; then
  apt-get update >/dev/null && apt-get install -y --no-install-recommends "${need[@]}" >/dev/null
fi
cargo build --release --quiet
bin="$target/release/gaitscope"
[ -z "${1:-}" ] && set -- --checkpoint checkpoints/encoder-lstm --compare checkpoints/baseline
log=$(mktemp)
work=$(mktemp -d)
export WGPU_BACKEND=vulkan XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
mkdir -p "$(dirname "$out")"
rm -f "$out"
# One private X screen holds both windows: the viewer at the left, the panel at the right edge
# (x = 1920 − 520 = 1400). --exit-after closes the viewer `live` started with it.
xvfb-run -a -s "-screen 0 1920x1080x24" bash -c '
  "$0" live --exit-after "$1" --save "$2/session.rrd" "${@:3}" 2>"'"$log"'" &
  live=$!
  sleep "$(( $1 - 1 ))"
  xwd -root -silent | /usr/bin/convert xwd:- -crop 520x1080+1400+0 +repage "$2/panel.png"
  wait "$live"
' "$bin" "$secs" "$work" "$@" || { cat "$log" >&2; exit 1; }
# A live session is saved in small chunks (one per entity every few steps); the 0.41 viewer's
# --screenshot-to fires while it is still loading so many (views half-drawn, a loading
# indicator), so compact them first, as `rerun rrd optimize` does for any recording.
.deps/rerun/rerun rrd optimize "$work/session.rrd" -o "$work/compact.rrd" 2>/dev/null
# A second X server right after the first can race its teardown: retry briefly.
for _ in 1 2 3; do
  ./scripts/screenshot.sh "$work/compact.rrd" "$work/viewer.png" 1400x1080 >/dev/null 2>&1 && break
  sleep 3
done
# The viewer screenshots at 2 pixels per point; scale it to the panel's 1080 rows.
/usr/bin/convert \( "$work/viewer.png" -resize x1080 \) "$work/panel.png" -background black +append "$out"
rm -rf "$work"
grep -E "^(streaming|panel:|sim at|session saved)" "$log" || cat "$log"
[ -s "$out" ] || { echo "no screenshot was written" >&2; exit 1; }
echo "wrote $out"
