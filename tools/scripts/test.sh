#!/usr/bin/env bash
# Every test: formatting, lints, unit and property tests, end-to-end tests with real
# processes, and the peer check against the Python MCAP reader (installed into .venv-peers).
set -euo pipefail
cd "$(dirname "$0")/../.."
tools/peer/setup-venv.sh
cargo fmt --all -- --check
cargo clippy --workspace --all-targets -- -D warnings
# end-to-end tests also run the workspace's other binaries (a user's exec stage)
cargo build --workspace --bins
cargo nextest run --workspace --no-fail-fast
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
