#!/usr/bin/env bash
# Does the fused update learn like candle's autograd? One 20k-step run of each encoder on each
# path (seed 0, `gaitscope train` defaults otherwise), one after another on one core, then one
# curves figure per encoder and a summary table. The two paths agree to ~1e-6 per update, so
# the runs diverge only as rounding grows; they should not differ in what they learn.
#
#   scripts/fused-vs-reference.sh [STEPS] [CORE]   # defaults: 20000 1
#
# Runs go to bench/fused-vs-reference/runs (git-ignored: checkpoints, replay);
# figures and summary.md to bench/fused-vs-reference/.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
steps=${1:-20000}
core=${2:-1}
out="$root/bench/fused-vs-reference"
runs="$out/runs"
bin="${CARGO_TARGET_DIR:-$root/target}/release/gaitscope"
(cd "$root" && ${CARGO:-cargo} build --release --quiet)
mkdir -p "$runs"
# A copy, so a rebuild while this runs never swaps the binary under it.
cp "$bin" "$runs/gaitscope.tmp" && mv "$runs/gaitscope.tmp" "$runs/gaitscope"
bin="$runs/gaitscope"

for encoder in none lstm mlp-window; do
  for update in fused reference; do
    dir="$runs/$encoder-$update"
    if [ -f "$dir/checkpoint.json" ] && python3 -c 'import json,sys; sys.exit(json.load(open(sys.argv[1]))["steps_done"] < int(sys.argv[2]))' "$dir/checkpoint.json" "$steps"; then
      echo "$encoder/$update: done already"
      continue
    fi
    rm -rf "$dir"
    echo "$encoder/$update: $steps steps on core $core"
    taskset -c "$core" "$bin" train --encoder "$encoder" --update "$update" --threads 1 \
      --steps "$steps" --seed 0 --out "$dir" --no-save-replay --quiet
  done
  "$bin" curves --run "$runs/$encoder-fused" "$runs/$encoder-reference" \
    --out "$out/curves-$encoder.png"
done

python3 - "$runs" "$steps" >"$out/summary.md" <<'PY'
import json, statistics, sys, pathlib
runs, steps = pathlib.Path(sys.argv[1]), int(sys.argv[2])
print(f"# Fused vs reference update: {steps:,}-step runs, seed 0\n")
print("Episodes of the second half of each run (steps ≥ {:,}). steps/s: the run's wall clock, "
      "which shared the machine with other work (speed is measured in docs/training.md, not here). "
      "One seed per cell: these runs show whether either path fails to learn, not small differences."
      "\n".format(steps // 2))
print("| encoder | update | episodes | mean return | success | mean critic loss | final α | steps/s |")
print("|---|---|---:|---:|---:|---:|---:|---:|")
for encoder in ["none", "lstm", "mlp-window"]:
    for update in ["fused", "reference"]:
        d = runs / f"{encoder}-{update}"
        eps, losses, alpha = [], [], None
        for line in open(d / "metrics.jsonl"):
            m = json.loads(line)
            late = m["global_step"] >= steps // 2
            if "charts/episodic_return" in m and late:
                eps.append((m["charts/episodic_return"], m.get("charts/success", False)))
            if "losses/qf1" in m and late:
                losses.append((m["losses/qf1"] + m["losses/qf2"]) / 2)
            if "losses/alpha" in m:
                alpha = m["losses/alpha"]
        ck = json.load(open(d / "checkpoint.json"))
        rate = ck["steps_done"] / ck["wall_time_s"] if ck.get("wall_time_s") else float("nan")
        print(f"| {encoder} | {update} | {len(eps)} | {statistics.mean(r for r, _ in eps):.1f} | "
              f"{sum(s for _, s in eps)}/{len(eps)} | {statistics.mean(losses):.3f} | {alpha:.4f} | {rate:.1f} |")
PY
cat "$out/summary.md"
