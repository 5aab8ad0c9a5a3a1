#!/usr/bin/env bash
# Writes the import-sb3 fixtures (tests/fixtures/sb3_*.zip and sb3_reference.json) with
# Stable-Baselines3 itself, in the peer benchmark's venv with the pinned versions
# (scripts/peers-venv.sh). Not part of `make test`; the files are committed.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
python=$("$root/scripts/peers-venv.sh")
exec "$python" "$root/tests/fixtures/make_sb3_fixtures.py" "$@"
