# The two commands of the README are `make run` and `make test`; both set up first.
CARGO ?= cargo

.PHONY: setup run test test-sweeps bench viewer sweep
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

# The stock Rerun 0.41.0 viewer binary (from PyPI's rerun-sdk wheel), for `rerun FILE.rrd`.
viewer:
	@./scripts/setup.sh --viewer

# A sweep on Ray Tune (its own venv in .deps/sweep-venv): make sweep SPEC=sweeps/seeds.toml
# [STORAGE=DIR] [ADDRESS=auto] [RESUME=1]; exits 0 only when every trial finished (docs/sweeps.md).
sweep: setup
	@test -n "$(SPEC)" || { echo "usage: make sweep SPEC=sweeps/FILE.toml [STORAGE=DIR] [ADDRESS=auto] [RESUME=1]"; exit 2; }
	$(CARGO) build --release
	py=$$(./sweeps/venv.sh) && $$py sweeps/sweep.py $(SPEC) $(if $(STORAGE),--storage $(STORAGE)) $(if $(ADDRESS),--address $(ADDRESS)) $(if $(RESUME),--resume) --gaitscope $${CARGO_TARGET_DIR:-target}/release/gaitscope

# The launcher's tests on real Ray (a smoke sweep, a killed trial, an interrupted sweep, a two-node
# cluster on loopback, bad specs); CI runs them after `make test`.
test-sweeps:
	@# The binary `cargo test` builds (dev-dependency features unify into it), so after `make test`
	@# nothing compiles again.
	$(CARGO) test --release --no-run
	py=$$(./sweeps/venv.sh) && $$py sweeps/test_sweep.py --gaitscope $${CARGO_TARGET_DIR:-target}/release/gaitscope
