#!/usr/bin/env bash
# Issue 48's report: `gaitscope search` on the committed models (the paper world's, then
# dead-legs'), one search after another, each into docs/results/search/<name>/ (the folder is
# the state: a second start resumes a killed search and skips finished ones). Runs the binary
# copied at start, so a rebuild does not change it mid-way.
#
#   scripts/search-runs.sh [NAME...]   # all searches, or the named ones
set -euo pipefail
# One function, read whole before it runs: bash would read an edited file from the old offset.
main() {
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/gaitscope/target}"
cargo build --release --quiet
mkdir -p .deps/search-runs
bin=.deps/search-runs/gaitscope
cp "$CARGO_TARGET_DIR/release/gaitscope" "$bin"
out=docs/results/search
common=(--evaluations 150 --episodes 16 --held-out 100 --top 3 --shrink-evaluations 60 --seed 0)

# name, then the search's own flags
searches=(
  "baseline-k1|--checkpoint checkpoints/baseline --budget 1"
  "encoder-lstm-k1|--checkpoint checkpoints/encoder-lstm --budget 1"
  "lstm-fails-baseline-succeeds-k1|--checkpoint checkpoints/encoder-lstm --against checkpoints/baseline --budget 1"
  "baseline-fails-lstm-succeeds-k1|--checkpoint checkpoints/baseline --against checkpoints/encoder-lstm --budget 1"
  "baseline-k2|--checkpoint checkpoints/baseline --budget 2"
  "encoder-lstm-k2|--checkpoint checkpoints/encoder-lstm --budget 2"
  "baseline-k3|--checkpoint checkpoints/baseline --budget 3"
  "encoder-lstm-k3|--checkpoint checkpoints/encoder-lstm --budget 3"
  # A shove instead of damage: joints all but whole (K = 0.05), one push of at most 1 N·s
  # (the Ant is 0.9 kg: up to about 1 m/s at once).
  "baseline-push1|--checkpoint checkpoints/baseline --budget 0.05 --push-impulse 1"
  "baseline-push5|--checkpoint checkpoints/baseline --budget 0.05 --push-impulse 5"
  "lstm-fails-baseline-succeeds-push1|--checkpoint checkpoints/encoder-lstm --against checkpoints/baseline --budget 0.05 --push-impulse 1"
  # baseline-push1 again with one search episode of shrink slack: the same search, a shrinker
  # that may drop the 1 % nudges the strict one kept.
  "baseline-push1-slack1|--checkpoint checkpoints/baseline --budget 0.05 --push-impulse 1 --shrink-slack 1"
  # The dead-legs world (issue 47), its warm-started pair at 250k: budget 2 is one leg's worth.
  # Where the oracle, told the damage, beats the baseline most — and the reverse — then each
  # model's worst damage. Their episodes run to the world's 1,000 steps.
  "dead-legs-baseline-fails-oracle-succeeds-k2|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --against checkpoints/dead-legs/oracle-warm-s0 --budget 2"
  "dead-legs-oracle-fails-baseline-succeeds-k2|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --against checkpoints/dead-legs/baseline-warm-s0 --budget 2"
  "dead-legs-baseline-k2|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --budget 2"
  "dead-legs-oracle-k2|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --budget 2"
  # The same pair searched by legs (one scale and onset per leg, as the world kills them): at
  # K = 2 one dead leg's worth, at K = 4 two (the world's severe).
  "dead-legs-by-leg-baseline-fails-oracle-succeeds-k2|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --against checkpoints/dead-legs/oracle-warm-s0 --unit leg --budget 2"
  "dead-legs-by-leg-oracle-fails-baseline-succeeds-k2|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --against checkpoints/dead-legs/baseline-warm-s0 --unit leg --budget 2"
  "dead-legs-by-leg-baseline-fails-oracle-succeeds-k4|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --against checkpoints/dead-legs/oracle-warm-s0 --unit leg --budget 4"
  "dead-legs-by-leg-oracle-fails-baseline-succeeds-k4|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --against checkpoints/dead-legs/baseline-warm-s0 --unit leg --budget 4"
  # Scaling over-budget damage down spreads it thin, so none of those reached a dead leg; the
  # same searches keeping the largest damages whole (--concentrate).
  "dead-legs-by-leg-concentrated-baseline-fails-oracle-succeeds-k2|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --against checkpoints/dead-legs/oracle-warm-s0 --unit leg --concentrate --budget 2"
  "dead-legs-by-leg-concentrated-oracle-fails-baseline-succeeds-k2|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --against checkpoints/dead-legs/baseline-warm-s0 --unit leg --concentrate --budget 2"
  "dead-legs-by-leg-concentrated-baseline-fails-oracle-succeeds-k4|--checkpoint checkpoints/dead-legs/baseline-warm-s0 --against checkpoints/dead-legs/oracle-warm-s0 --unit leg --concentrate --budget 4"
  "dead-legs-by-leg-concentrated-oracle-fails-baseline-succeeds-k4|--checkpoint checkpoints/dead-legs/oracle-warm-s0 --against checkpoints/dead-legs/baseline-warm-s0 --unit leg --concentrate --budget 4"
)
for entry in "${searches[@]}"; do
  name=${entry%%|*}
  if [ $# -gt 0 ] && [[ " $* " != *" $name "* ]]; then continue; fi
  [ -f "$out/$name/summary.md" ] && { echo "done: $name"; continue; }
  echo "search: $name"
  # shellcheck disable=SC2086
  "$bin" search ${entry#*|} "${common[@]}" --out "$out/$name" > /dev/null
done
}

main "$@"; exit
