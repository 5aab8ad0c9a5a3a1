#!/usr/bin/env bash
# Training speed side by side: Stable-Baselines3 (PyTorch) and SBX (JAX) on gaitscope's task in
# Python (python/gaitscope_gym.py), then `gaitscope bench train`, each pinned to the same core
# and one thread, one after another, with this repo's own background training paused. Prints one
# table: env steps/s with one SAC update per step, and gaitscope's ratio to each peer.
#   scripts/bench-peers.sh [STEPS]     (default 1000 learning steps after 1000 random ones)
# Builds its own venv (.deps/peers-venv, ~5 GB with torch) on first use; not part of `make test`.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
steps="${1:-1000}"
core="${BENCH_CORE:-1}"
venv="$root/.deps/peers-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import sbx, stable_baselines3' 2>/dev/null; then
  echo "bench-peers: building $venv (stable-baselines3, sbx-rl, torch, jax, gymnasium, mujoco)"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "stable-baselines3==2.9.2" "sbx-rl==0.28.0" "gymnasium==1.4.0" \
    "mujoco==3.17.0" "torch==2.15.0" "jax==0.10.2" "jaxlib==0.10.2" "flax==0.12.8" "optax==0.2.8" \
    "numpy==2.4.6" "imageio==2.38.1" "packaging==26.4"
fi
(cd "$root" && ${CARGO:-cargo} build --release --quiet)
bin="${CARGO_TARGET_DIR:-$root/target}/release/gaitscope"

# Our own trainers would compete for the core: pause them for the measurement.
"$root/scripts/seed-runs.sh" pause 2>/dev/null || true
trap '"$root/scripts/seed-runs.sh" cont 2>/dev/null || true' EXIT

results=$(mktemp)
run_peer() {
  echo "bench-peers: $1 $2" >&2
  taskset -c "$core" "$venv/bin/python" "$root/bench/peers/train_speed.py" \
    --lib "$1" --model "$2" --steps "$steps" >>"$results"
}
run_peer sb3 none
run_peer sb3 lstm
run_peer sbx none
run_peer sbx folded-mlp
echo "bench-peers: gaitscope bench train" >&2
taskset -c "$core" "$bin" bench train --steps "$steps" --json >>"$results"
# And with the machine to itself: two threads per update, on every core.
echo "bench-peers: gaitscope bench train --threads 2" >&2
"$bin" bench train --steps "$steps" --threads 2 --json >>"$results"

"$venv/bin/python" - "$results" "$steps" <<'PY'
import json, platform, subprocess, sys, datetime
rows = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
peers = {r["peer"]: r for r in rows if "peer" in r}
ours = {r["encoder"]: r for r in rows if r.get("threads", 1) == 1 and "encoder" in r}
ours2 = {r["encoder"]: r for r in rows if r.get("threads", 1) == 2}
cpu = next((l.split(":", 1)[1].strip() for l in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines() if l.startswith("Model name")), platform.processor())
print(f"\nenv steps/s, one SAC update per step, batch 256, one core ({cpu}), {sys.argv[2]} steps after 1000 random; {datetime.date.today()}\n")
print("| model | gaitscope | peer | peer steps/s | ratio | gaitscope, 2 threads | ratio |")
print("|---|---:|---|---:|---:|---:|---:|")
for enc, peer in [("none", "SB3 none"), ("none", "SBX none"), ("lstm", "SB3 lstm"), ("mlp-window", "SBX folded-mlp")]:
    if enc in ours and peer in peers:
        a, b = ours[enc]["train_steps_per_s"], peers[peer]["train_steps_per_s"]
        two = ours2.get(enc, {}).get("train_steps_per_s", float("nan"))
        print(f"| `{enc}` | {a:.1f} | {peer} | {b:.1f} | {a / b:.2f}× | {two:.1f} | {two / b:.2f}× |")
print("\nPeers and the first gaitscope column: one thread, pinned to one core. The last two: "
      "gaitscope with `--threads 2` on both cores (peers at one thread).")
print("\n" + "; ".join(sorted({r["version"] for r in peers.values()})))
PY
