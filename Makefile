# The two commands of the README are `make run` and `make test`; both set up first.
CARGO ?= cargo

.PHONY: setup run test bench viewer
setup:
	@./scripts/setup.sh

# The main job: a headless demo rollout (random policy, randomised damage) with per-episode summaries.
run: setup
	$(CARGO) run --release -- rollout --policy random --episodes 5 --seed 0

# Every test, in the release profile (the one `run` builds, so CI compiles dependencies once).
test: setup
	$(CARGO) test --release

bench: setup
	$(CARGO) run --release -- bench env

# The stock Rerun 0.36.3 viewer binary (from PyPI's rerun-sdk wheel), for `rerun FILE.rrd`.
viewer:
	@./scripts/setup.sh --viewer
