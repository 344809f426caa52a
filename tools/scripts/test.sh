#!/usr/bin/env bash
# Every test: formatting, lints, unit and property tests, end-to-end tests with real
# processes, and the peer checks against the Python MCAP reader and evo (installed into .venv-peers).
set -euo pipefail
cd "$(dirname "$0")/../.."
tools/peer/setup-venv.sh
# plot labels (gprflow eval --plot) need a font: Debian's DejaVu Sans
if [[ ! -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ]] && command -v apt-get >/dev/null && [[ $(id -u) == 0 ]]; then
    apt-get install -y --no-install-recommends fonts-dejavu-core >/dev/null
fi
cargo fmt --all -- --check
cargo clippy --workspace --all-targets -- -D warnings
# end-to-end tests also run the workspace's other binaries (a user's exec stage)
cargo build --workspace --bins
cargo nextest run --workspace --no-fail-fast
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
