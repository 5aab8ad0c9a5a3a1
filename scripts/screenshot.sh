#!/usr/bin/env bash
# Screenshot of a recording in the stock Rerun viewer under Xvfb with Mesa's software Vulkan
# (lavapipe): GL on llvmpipe lacks R32Float, which the viewer needs.
# Usage: scripts/screenshot.sh FILE.rrd OUT.png [WIDTHxHEIGHT]
set -euo pipefail
cd "$(dirname "$0")/.."
rrd="$1"; out="$2"; size="${3:-1600x1000}"
./scripts/setup.sh --viewer >/dev/null
if ! command -v Xvfb >/dev/null || ! command -v xdotool >/dev/null \
  || [ ! -e /usr/share/vulkan/icd.d/lvp_icd.x86_64.json ]; then
  apt-get update >/dev/null && apt-get install -y xvfb xauth xdotool mesa-vulkan-drivers libudev1 >/dev/null
fi
export WGPU_BACKEND=vulkan
rm -f "$out"
# The viewer writes the screenshot, then exits through a panic on shutdown (a known quirk of
# --screenshot-to): judge by the file, not the exit code.
# The pointer starts mid-screen, where it would raise a hover tooltip: park it in the corner.
# RUST_LOG=error: Rerun 0.41 shows its startup warnings (software rasterizer, a container) as
# toasts over the views; a screenshot taken while they show has them covering the plots.
RUST_LOG=error XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}" xvfb-run -a -s "-screen 0 ${size}x24" \
  bash -c '(for _ in $(seq 20); do xdotool mousemove 0 0 2>/dev/null; sleep 0.25; done) & exec "$@"' _ \
  .deps/rerun/rerun --window-size "$size" --screenshot-to "$out" "$rrd" >/dev/null 2>&1 || true
[ -s "$out" ] || { echo "no screenshot was written" >&2; exit 1; }
echo "wrote $out"
