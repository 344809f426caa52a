#!/usr/bin/env bash
# The main job end to end on the embedded sample recording: replay recordings/toy.mcap
# through the graph, record the result, and show what was recorded.
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release -p gprflow-cli
out="${1:-out/demo.mcap}"
mkdir -p "$(dirname "$out")"
./target/release/gprflow launch graphs/replay-toy.yaml --set recording=recordings/toy.mcap --record "$out"
./target/release/gprflow inspect "$out"
