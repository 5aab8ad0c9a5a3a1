#!/usr/bin/env bash
# What a resume without its replay buffer costs (issue 31), for the cheap `none` encoder:
# per seed (0-2), "straight" trains 0 → 100k steps keeping its buffer; "refilled" is the same
# run's 50k checkpoint resumed without one (train refills --refill transitions with the current
# policy, no updates, then goes on) to 100k. Both continue from one 50k state, so the only
# difference is the buffer. `report` compares success and return over the last 20k steps.
#
#   scripts/refill-cost.sh run [CORE]   # resumable; nice 19, pinned to CORE (default 1)
#   scripts/refill-cost.sh report       # the tables, markdown (docs/training.md)
#
# `report` also evaluates each finished pair's two 100k checkpoints on the same paired eval
# seeds (EVAL_EPISODES per condition, default 100; deterministic actions, 500-step limit): the
# training-tail numbers rest on ~25 exploring episodes each, the evaluation on 300.
# HALF / STEPS / LAST override 50000 / 100000 / 20000 (a quick trial of the script itself).
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
# The build cache .ci/run and make use, outside the work tree.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/gaitscope/target}"
out="${REFILL_COST_DIR:-$root/checkpoints/refill-cost}"
replay_root="${GAITSCOPE_REPLAY_ROOT:-$HOME/.cache/gaitscope/replay}/refill-cost"
half="${HALF:-50000}"
steps="${STEPS:-100000}"
last="${LAST:-20000}"
seeds=(0 1 2)

steps_done() {
  local json="$1/checkpoint.json"
  [ -f "$json" ] || { echo 0; return; }
  python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["steps_done"])' "$json"
}

# train CORE ARGS...: one trainer, nice 19, pinned. Under scripts/seed-runs.sh (which sets
# TRAINER_PID_FILE and STOP_FILE) its pid is where `seed-runs.sh stop|pause|cont` finds it, and
# a stop ends the job before the next trainer.
train() {
  local core=$1
  shift
  if [ -n "${STOP_FILE:-}" ] && [ -e "$STOP_FILE" ]; then exit 0; fi
  nice -n 19 taskset -c "$core" "$bin" train "$@" --quiet &
  local pid=$!
  if [ -n "${TRAINER_PID_FILE:-}" ]; then echo "$pid" >"$TRAINER_PID_FILE"; fi
  local code=0
  wait "$pid" || code=$?
  if [ -n "${TRAINER_PID_FILE:-}" ]; then rm -f "$TRAINER_PID_FILE"; fi
  if [ -n "${STOP_FILE:-}" ] && [ -e "$STOP_FILE" ]; then exit 0; fi
  return "$code"
}

# The whole command is one function, read before it runs: a lane keeps this script open for
# hours, and bash would otherwise read an edited file from the old offset mid-run.
main() {
case "${1:-}" in
  run)
    core="${2:-1}"
    if [ -n "${GAITSCOPE_BIN:-}" ]; then
      bin="$GAITSCOPE_BIN"   # seed-runs.sh's copy
    else
      (cd "$root" && ${CARGO:-cargo} build --release --quiet)
      # A copy, so that rebuilding in the work tree never swaps the binary under a trainer.
      mkdir -p "$root/.deps/refill-cost"
      bin="$root/.deps/refill-cost/gaitscope"
      cp "${CARGO_TARGET_DIR:-$root/target}/release/gaitscope" "$bin"
    fi
    mkdir -p "$out"
    for seed in "${seeds[@]}"; do
      a="$out/none-s$seed-straight" b="$out/none-s$seed-refilled"
      if [ ! -d "$b" ]; then
        # The shared first half.
        if [ -f "$a/checkpoint.json" ]; then
          train "$core" --resume "$a" --steps "$half" --replay-dir "$replay_root/straight-s$seed"
        else
          train "$core" --encoder none --seed "$seed" --out "$a" --steps "$half" \
            --replay-dir "$replay_root/straight-s$seed"
        fi
        [ "$(steps_done "$a")" -eq "$half" ] || { echo "$a is not at $half steps" >&2; exit 1; }
        # The branch: the folder as saved at the half, without a buffer of its own.
        cp -r "$a" "$b.partial"
        rm -f "$b.partial/replay.bin"
        mv "$b.partial" "$b"
      fi
      [ "$(steps_done "$a")" -ge "$steps" ] ||
        train "$core" --resume "$a" --steps "$steps" --replay-dir "$replay_root/straight-s$seed"
      # An empty replay dir the first time: the resume refills. After an interruption the
      # branch has a buffer of its own there and restores it.
      [ "$(steps_done "$b")" -ge "$steps" ] ||
        train "$core" --resume "$b" --steps "$steps" --replay-dir "$replay_root/refilled-s$seed"
    done
    echo "refill-cost runs done: scripts/refill-cost.sh report"
    ;;
  report)
    # The finished pairs, evaluated together (eval needs the binary; build it if absent).
    pairs=()
    for seed in "${seeds[@]}"; do
      a="$out/none-s$seed-straight" b="$out/none-s$seed-refilled"
      if [ "$(steps_done "$a")" -ge "$steps" ] && [ "$(steps_done "$b")" -ge "$steps" ]; then
        pairs+=("$a" "$b")
      fi
    done
    evaluated=""
    if [ ${#pairs[@]} -gt 0 ]; then
      evaluated=$(mktemp -d)
      trap 'rm -rf "$evaluated"' EXIT
      bin="${GAITSCOPE_BIN:-${CARGO_TARGET_DIR}/release/gaitscope}"
      [ -x "$bin" ] || (cd "$root" && ${CARGO:-cargo} build --release --quiet)
      "$bin" eval --checkpoint "${pairs[@]}" --episodes "${EVAL_EPISODES:-100}" \
        --out "$evaluated" >/dev/null 2>"$evaluated/eval.log" || { cat "$evaluated/eval.log" >&2; exit 1; }
    fi
    python3 - "$out" "$steps" "$last" "$evaluated" "${seeds[@]}" <<'EOF'
import json, statistics, sys
out, steps, last, evaluated = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
seeds = sys.argv[5:]

def steps_done(run):
    try:
        return json.load(open(f"{out}/{run}/checkpoint.json"))["steps_done"]
    except FileNotFoundError:
        return 0

def tail(run):
    eps = []
    with open(f"{out}/{run}/metrics.jsonl") as f:
        for line in f:
            try:
                m = json.loads(line)
            except json.JSONDecodeError:
                continue
            if "charts/episodic_return" in m and m["global_step"] > steps - last:
                eps.append((bool(m["charts/success"]), m["charts/episodic_return"]))
    return eps

def refills(run):
    """Each resume: at which step, the buffer restored or refilled, and how many."""
    state = json.load(open(f"{out}/{run}/train_state.json"))
    return "; ".join(
        f"{r['step']:,}: {r['buffer']}"
        + (f" {r['refill_transitions']:,}" if r["buffer"] != "restored" else "")
        for r in state.get("resumes", [])
    ) or "none"

print(f"| seed | run | episodes in the last {last:,} steps | success | mean return | resume record |")
print("|---|---|---:|---:|---:|---|")
# Only seeds whose two runs both reached `steps` enter the means and the paired differences.
pairs = []
for seed in seeds:
    row = {}
    for kind in ["straight", "refilled"]:
        run = f"none-s{seed}-{kind}"
        done = steps_done(run)
        if done < steps:
            print(f"| {seed} | {kind} | | | | not finished: {done:,} / {steps:,} steps |")
            continue
        eps = tail(run)
        succ = 100 * sum(s for s, _ in eps) / max(len(eps), 1)
        ret = statistics.mean(r for _, r in eps) if eps else float("nan")
        row[kind] = (succ, ret)
        print(f"| {seed} | {kind} | {len(eps)} | {succ:.1f} % | {ret:.1f} | {refills(run)} |")
    if len(row) == 2:
        pairs.append(row)
for kind in ["straight", "refilled"]:
    if pairs:
        print(f"| mean of {len(pairs)} | {kind} | | {statistics.mean(p[kind][0] for p in pairs):.1f} % | "
              f"{statistics.mean(p[kind][1] for p in pairs):.1f} | |")
if pairs:
    diffs = [p["refilled"][1] - p["straight"][1] for p in pairs]
    print()
    print("refilled − straight, mean return per seed: "
          + ", ".join(f"{d:+.1f}" for d in diffs) + f" (mean {statistics.mean(diffs):+.1f})")
if evaluated:
    report = json.load(open(f"{evaluated}/eval.json"))
    by_run = {}
    for e in report["episodes"]:
        by_run.setdefault(e["model"], []).append(e)
    n = report["episodes_per_cell"]
    print()
    print(f"Evaluation of the 100k checkpoints ({n} paired episodes per condition, healthy, mild "
          f"and severe pooled; deterministic actions, {report['max_steps']}-step limit):")
    print()
    print("| seed | run | success | mean final distance (m) | mean return |")
    print("|---|---|---:|---:|---:|")
    dist = {"straight": [], "refilled": []}
    for seed in seeds:
        for kind in ["straight", "refilled"]:
            eps = by_run.get(f"none-s{seed}-{kind}")
            if not eps:
                continue
            succ = 100 * sum(e["success"] for e in eps) / len(eps)
            d = statistics.mean(e["final_distance"] for e in eps)
            dist[kind].append(d)
            ret = statistics.mean(e["return"] for e in eps)
            print(f"| {seed} | {kind} | {succ:.1f} % | {d:.2f} | {ret:.1f} |")
    diffs = [r - s for s, r in zip(dist["straight"], dist["refilled"])]
    print()
    print("refilled − straight, mean final distance per seed (m; negative: the refilled run ends "
          "closer): " + ", ".join(f"{d:+.2f}" for d in diffs)
          + f" (mean {statistics.mean(diffs):+.2f})")
EOF
    ;;
  *)
    sed -n '2,13p' "$0"
    exit 2
    ;;
esac
}

main "$@"; exit
