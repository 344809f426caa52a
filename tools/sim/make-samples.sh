#!/usr/bin/env bash
# Regenerates the simulated sample recordings committed under recordings/sim/ (a few MB
# each). Longer runs are made on demand the same way, e.g.
#   gprflow sim tools/sim/scenarios/basement.yaml -o basement-long.mcap --run long
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release -p gprflow-cli
sim() { ./target/release/gprflow sim "$@"; }
sim tools/sim/scenarios/basement.yaml -o recordings/sim/basement-forward_backward.mcap --run forward_backward
sim tools/sim/scenarios/parking_garage.yaml -o recordings/sim/garage-loops-60s.mcap --run loops --duration 60
sim tools/sim/scenarios/highway.yaml -o recordings/sim/highway-map-5s.mcap --run map --duration 5
sim tools/sim/scenarios/pipes_one_line.yaml -o recordings/sim/pipes-lawnmower-150s.mcap --run lawnmower --duration 150
ls -la recordings/sim
