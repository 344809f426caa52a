#!/usr/bin/env bash
# Every test: formatting, lints, unit and property tests, end-to-end tests with real
# processes, and the peer checks against the Python MCAP reader, evo, scipy, PyWavelets and
# scikit-image (installed into .venv-peers) and GTSAM (installed into .venv-gtsam).
set -euo pipefail
cd "$(dirname "$0")/../.."
tools/peer/setup-venv.sh
# plot labels (gprflow eval --plot) need a font
tools/scripts/ensure-font.sh
# the learned registration model runs on ONNX Runtime (libonnxruntime from the PyPI wheel)
tools/scripts/ensure-onnxruntime.sh
# the distributed tests run hosts in network namespaces (iproute2) with TLS (openssl)
tools/scripts/ensure-netns-tools.sh
cargo fmt --all -- --check
cargo clippy --workspace --all-targets -- -D warnings
# end-to-end tests also run the workspace's other binaries (a user's exec stage)
cargo build --workspace --bins
# the crate layers (no upward dependency, zenoh only where the launcher is) and no module circles
python3 tools/scripts/check-layers.py
cargo nextest run --workspace --no-fail-fast
# the compile-fail examples: safe code cannot send an unwritten payload buffer (msg::payload)
cargo test -p gprflow-msg --doc --quiet
# peer check of the estimation library: GTSAM 4.3 (installed into .venv-gtsam) re-solves the
# committed problem and must still give the figures our test (peer_gtsam, run above) compares
# against
tools/peer/gtsam_check.sh --verify
# peer checks of the signal processing: scipy.signal, scipy.ndimage, PyWavelets, scikit-image and
# numpy regenerate the committed fixtures the dsp and lgpr peer tests (run above) compare against
.venv-peers/bin/python tools/peer/dsp_fixtures.py --verify
.venv-peers/bin/python tools/peer/sfcw_fixtures.py --verify
# a short soak: the odometry graph again and again for 30 s; nothing may grow, be left behind
# or be lost (tools/bench/soak.sh, 30 minutes of the localisation graph by default)
GPRFLOW="${CARGO_TARGET_DIR:-target}/debug/gprflow" tools/bench/soak.sh 0.5 odometry
# the docs: every link in README.md and docs/ resolves, and every command block marked
# `sh runnable` runs as written (tools/scripts/check-docs.py --list shows them)
python3 tools/scripts/check-docs.py --run --gprflow "${CARGO_TARGET_DIR:-target}/debug/gprflow"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
