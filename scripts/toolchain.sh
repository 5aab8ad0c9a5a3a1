#!/usr/bin/env bash
# Installs the Rust toolchain rust-toolchain.toml pins (Rust 1.98, which Rerun 0.41's crates need),
# with its components, when rustup lacks it. Current rustup (1.28 on) no longer installs a pinned
# toolchain on first use: cargo fails with "toolchain '1.98.0-…' is not installed" instead.
# Idempotent; honours RUSTUP_HOME (.ci/run proves the install into a throwaway one).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
channel=$(sed -n 's/^channel *= *"\([^"]*\)".*/\1/p' rust-toolchain.toml)
[ -n "$channel" ] || { echo "toolchain: no channel in rust-toolchain.toml" >&2; exit 1; }

if ! command -v rustup >/dev/null 2>&1; then
  # Without rustup the toolchain file means nothing; a cargo that is new enough still builds.
  have=$(cargo --version 2>/dev/null || true)
  want_minor=$(echo "$channel" | cut -d. -f2)
  if [[ "$have" =~ ^cargo\ 1\.([0-9]+) ]] && [ "${BASH_REMATCH[1]}" -ge "$want_minor" ]; then
    echo "toolchain: no rustup; using ${have%% (*} (rust-toolchain.toml asks for $channel)"
    exit 0
  fi
  echo "toolchain: gaitscope needs Rust $channel (rust-toolchain.toml) and rustup to install it;" >&2
  echo "toolchain: found ${have:-no cargo}. Install rustup (https://rustup.rs), then rerun this." >&2
  exit 1
fi

# `rustup run` fails at once, without installing, when the toolchain is missing.
if rustup run "$channel" rustc --version >/dev/null 2>&1 &&
   rustup component list --toolchain "$channel" --installed 2>/dev/null | grep -q '^rustfmt' &&
   rustup component list --toolchain "$channel" --installed 2>/dev/null | grep -q '^clippy'; then
  exit 0
fi
echo "toolchain: installing Rust $channel with rustup (pinned by rust-toolchain.toml)"
# With no argument rustup installs the directory's toolchain as the file describes it: profile
# and components too.
rustup toolchain install --no-self-update
rustup run "$channel" rustc --version
