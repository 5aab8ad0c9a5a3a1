#!/usr/bin/env bash
# The evidence runs, two lanes, one per core, at nice 19, so they only take what foreground work
# leaves. Issue 31's and 33's runs in the paper's world (checkpoints/seeds/) are done. Now issue
# 47's calibration in the dead-joints world (checkpoints/dead-joints/): the oracle (true damage
# as input) and the baseline. Seed 0 of both reached 1M and the `damage` oracle (scales as
# inputs) still did not beat the baseline under damage, so two oracles that read the same truth
# as torque lost (1 − scale, 0 while whole) train first, to 500k, the step the baselines'
# seeds 0 and 1 were compared at. They did not learn to walk, so the world changes next: in
# `dead-legs` only whole legs die, all by step 60 (fewer patterns, most of the walk damaged);
# its oracle and baseline train to 500k. There the oracle was still worse under damage, with most
# training steps spent by flipped Ants flailing to the 1,000-step limit, so `dead-legs-short`
# (the same deaths, 400 steps, a flip ends the episode) trains its pair to 500k next; then the
# dead-legs pair is asked the narrower question: an oracle and a baseline both warm-started
# from its 500k baseline (train --init-from; the oracle's damage inputs start at zero weight),
# 250k steps each, the same seed — what the truth is worth to a policy that already walks (done:
# not met, +6 / −13 / −10). Then the dead-legs pair goes on from 500k to 1M (its oracle was still
# gaining; done: +19 / −24 / −28, not met), then dead-joints' baseline-s1 and oracle-s1 go on to 1M. The LSTM runs
# follow once oracle − baseline ≥ 15 points on held-out seeds. Each run resumes from its last checkpoint (every
# 10,000 steps), so `start` is the same command on the first day and on a fresh machine after a
# clone. The replay buffers live outside the work tree (~/.cache/gaitscope/replay/<world>/<run>),
# so a kept machine resumes with its buffer; a new machine refills one with the current policy
# (train --refill, 50,000 transitions) before updating.
#
#   scripts/seed-runs.sh start    # build, then run/resume both lanes in the background
#   scripts/seed-runs.sh status   # steps done per run, and what is running
#   scripts/seed-runs.sh stop     # Ctrl-C each trainer (it saves a checkpoint), stop the lanes
#   scripts/seed-runs.sh pause|cont   # SIGSTOP/SIGCONT the trainers (for benchmarks)
#
# Runs live in checkpoints/<world folder>/<model>-s<seed>; commit everything there but
# replay.bin. While lanes run, leave the run folders' files to the trainers: no `git stash`,
# checkout or commit -a (a stash once replaced metrics.jsonl under two trainers;
# docs/training.md). Commit run state with `stop`, `git add checkpoints/...`, commit, `start`.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
# The build cache .ci/run and make use, outside the work tree.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/gaitscope/target}"
runs_dir="$root/checkpoints"
state="$root/.deps/seed-runs"   # git-ignored: the binary copy, pids and logs
replay_root="${GAITSCOPE_REPLAY_ROOT:-$HOME/.cache/gaitscope/replay}"
steps=1000000

# Each lane's runs, as <world folder>/<model>-s<seed> under checkpoints/.
lane_runs() {
  case $1 in
    # Seed 0's pair first, one model per lane, so a pair finishes together.
    0) echo "dead-joints/oracle-s0 dead-joints/oracle-lost-s0 dead-legs-short/oracle-s0 dead-legs/oracle-warm-s0 dead-legs/oracle-s0 dead-joints/baseline-s1" ;;
    1) echo "dead-joints/baseline-s0 dead-joints/oracle-lost-s1 dead-legs-short/baseline-s0 dead-legs/baseline-warm-s0 dead-legs/baseline-s0 dead-joints/oracle-s1" ;;
  esac
}

# The training flags of a fresh run beyond its seed (a resume keeps the run's own).
flags_of() {
  local world=${1%%/*} model=${1##*/}
  local flags=()
  [ "$world" = seeds ] || flags+=(--world "$world")
  case $model in
    # Warm starts (train --init-from): all from the world's 500k baseline, kept as
    # baseline-500k-s0 while baseline-s0 trains on (the first warm pair's source, CRC and all) —
    # told the damage, told nothing, or given an encoder whose z starts at zero weight —
    # filling a 10,000-transition buffer with its policy before the first update.
    *-warm-*)
      flags+=(--init-from "$runs_dir/$world/baseline-500k-s0" --learning-starts 10000)
      case $model in
        oracle-*) flags+=(--privileged damage) ;;
        encoder-lstm-aux-*) flags+=(--encoder lstm --aux dynamics) ;;
        encoder-lstm-*) flags+=(--encoder lstm) ;;
        encoder-mlp-*) flags+=(--encoder mlp-window) ;;
      esac
      ;;
    oracle-lost-*) flags+=(--privileged torque-lost) ;;
    oracle-*) flags+=(--privileged damage) ;;
    baseline-*) flags+=(--encoder none) ;;
    encoder-lstm-aux-*) flags+=(--encoder lstm --aux dynamics) ;;
    encoder-lstm-*) flags+=(--encoder lstm) ;;
    encoder-mlp-*) flags+=(--encoder mlp-window) ;;
  esac
  echo "${flags[*]}"
}

# Where a run stops: the torque-lost oracles and the dead-legs-short pair at 500k (the
# calibration's comparison step), the rest at 1M. The dead-legs pair was compared at 400k and
# 500k (the oracle gaining on every condition, the baseline flat) and goes on to 1M once
# dead-legs-short is done: whether a longer budget gives the oracle its headroom.
steps_of() {
  case $1 in
    */oracle-lost-* | dead-legs-short/*) echo 500000 ;;
    */*-warm-*) echo 250000 ;;
    *) echo "$steps" ;;
  esac
}

steps_done() {
  local json="$runs_dir/$1/checkpoint.json"
  [ -f "$json" ] || { echo 0; return; }
  python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["steps_done"])' "$json"
}

# run_lane N: trains the lane's runs one after another, pinned to core N.
run_lane() {
  local core=$1 run dir
  for run in $(lane_runs "$core"); do
    [ -e "$state/stop" ] && return 0
    dir="$runs_dir/$run"
    if [ "$(steps_done "$run")" -ge "$(steps_of "$run")" ]; then
      continue
    fi
    local args
    if [ -f "$dir/checkpoint.json" ]; then
      args=(--resume "$dir")
    else
      mkdir -p "$(dirname "$dir")"
      # shellcheck disable=SC2207 # the flags are plain words
      args=($(flags_of "$run") --seed "${run##*-s}" --out "$dir")
    fi
    echo "$(date -u +%FT%TZ) lane $core: ${args[*]}"
    # `exec`-free so the lane survives to start the next run; the trainer's pid is kept for stop.
    nice -n 19 taskset -c "$core" "$state/gaitscope" train "${args[@]}" --steps "$(steps_of "$run")" \
      --replay-dir "$replay_root/$run" --quiet &
    echo $! >"$state/trainer-$core.pid"
    wait $! || echo "$(date -u +%FT%TZ) lane $core: $run exited with $?"
    rm -f "$state/trainer-$core.pid"
  done
  echo "$(date -u +%FT%TZ) lane $core: done"
}

# Live trainers only: a session that ended kills its trainers but leaves their pid files.
trainer_pids() {
  local f pid
  for f in "$state"/trainer-*.pid; do
    [ -f "$f" ] || continue
    pid=$(cat "$f")
    if kill -0 "$pid" 2>/dev/null; then echo "$pid"; else rm -f "$f"; fi
  done
}

# The whole command is one function, read before it runs: a lane keeps this script open for
# hours, and bash would otherwise read an edited file from the old offset mid-run.
main() {
case "${1:-status}" in
  start)
    if [ -n "$(trainer_pids)" ]; then
      echo "seed runs already going (scripts/seed-runs.sh status)"; exit 1
    fi
    mkdir -p "$state" "$runs_dir"
    rm -f "$state/stop"
    # A fresh clone has no libmujoco yet (the build links it): fetch it first, as `make` does.
    "$root/scripts/setup.sh"
    (cd "$root" && ${CARGO:-cargo} build --release --quiet)
    # A copy, so later builds never change the binary under a running trainer.
    cp "${CARGO_TARGET_DIR:-$root/target}/release/gaitscope" "$state/gaitscope.tmp"
    mv "$state/gaitscope.tmp" "$state/gaitscope"
    # Its debug info (file and line in a backtrace) lives beside it (docs/build.md).
    dwp="${CARGO_TARGET_DIR:-$root/target}/release/gaitscope.dwp"
    if [ -f "$dwp" ]; then cp "$dwp" "$state/gaitscope.dwp"; fi
    for core in 0 1; do
      nohup bash "$0" _lane "$core" >>"$state/lane-$core.log" 2>&1 &
    done
    echo "seed runs started; logs in $state/lane-{0,1}.log"
    ;;
  _lane) run_lane "$2" ;;
  stop)
    mkdir -p "$state"
    touch "$state/stop"
    for pid in $(trainer_pids); do kill -CONT "$pid" 2>/dev/null || true; kill -INT "$pid" 2>/dev/null || true; done
    for pid in $(trainer_pids); do
      while kill -0 "$pid" 2>/dev/null; do sleep 1; done
    done
    echo "seed runs stopped (each saved a checkpoint)"
    ;;
  pause) for pid in $(trainer_pids); do kill -STOP "$pid"; done ;;
  cont) for pid in $(trainer_pids); do kill -CONT "$pid"; done ;;
  status)
    for core in 0 1; do
      for run in $(lane_runs "$core"); do
        printf '%-28s %7s / %s steps\n' "$run" "$(steps_done "$run")" "$(steps_of "$run")"
      done
    done
    for pid in $(trainer_pids); do ps -o pid=,etime=,args= -p "$pid" || true; done
    ;;
  *) echo "usage: $0 start|status|stop|pause|cont" >&2; exit 2 ;;
esac
}

main "$@"; exit
