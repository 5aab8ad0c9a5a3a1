# The two commands of the README are `make run` and `make test`; both set up first.
CARGO ?= cargo

.PHONY: setup run test bench viewer
setup:
	@./scripts/setup.sh

# The main job: the live viewer on the bundled encoder checkpoint (with a display), else the same
# models recorded headlessly to recordings/latest.rrd (see scripts/run.sh).
run: setup
	@CARGO=$(CARGO) ./scripts/run.sh

# Every test, in the release profile (the one `run` builds, so CI compiles dependencies once).
test:
	@./scripts/setup.sh --test
	$(CARGO) test --release

bench: setup
	$(CARGO) run --release -- bench env

# The stock Rerun 0.36.3 viewer binary (from PyPI's rerun-sdk wheel), for `rerun FILE.rrd`.
viewer:
	@./scripts/setup.sh --viewer
