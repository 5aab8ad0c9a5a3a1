#!/usr/bin/env bash
# Training speed side by side: Stable-Baselines3 (PyTorch) and SBX (JAX) on gaitscope's task in
# Python (python/gaitscope_gym.py), then `gaitscope bench train`, each pinned to the same core
# and one thread, one after another, with this repo's own background training paused. Prints one
# table: env steps/s with one SAC update per step, and gaitscope's ratio to each peer.
#   scripts/bench-peers.sh [STEPS]     (default 1000 learning steps after 1000 random ones)
# Uses scripts/peers-venv.sh (built on first use, ~5 GB with torch); not part of `make test`.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
steps="${1:-1000}"
core="${BENCH_CORE:-1}"
python=$("$root/scripts/peers-venv.sh")
(cd "$root" && ${CARGO:-cargo} build --release --quiet)
bin="${CARGO_TARGET_DIR:-$root/target}/release/gaitscope"

# Our own trainers would compete for the core: pause them for the measurement.
"$root/scripts/seed-runs.sh" pause 2>/dev/null || true
trap '"$root/scripts/seed-runs.sh" cont 2>/dev/null || true' EXIT

results=$(mktemp)
run_peer() {
  echo "bench-peers: $1 $2" >&2
  taskset -c "$core" "$python" "$root/bench/peers/train_speed.py" \
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

"$python" - "$results" "$steps" <<'PY'
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
