#!/usr/bin/env bash
# Regenerates the simulated sample recordings committed under recordings/sim/ (a few MB
# each), or with --pipes only the pipe-field sample that graphs/slam.yaml reads, which is
# made on demand into out/ (6.7 MB: too big to commit; the tests make their own copy the
# same way). Longer runs are made on demand the same way, e.g.
#   gprflow sim tools/sim/scenarios/basement.yaml -o basement-long.mcap --run long
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release -p gprflow-cli
sim() { ./target/release/gprflow sim "$@"; }
mkdir -p out
sim tools/sim/scenarios/pipes_one_line.yaml -o out/pipes-lawnmower-150s.mcap --run lawnmower --duration 150
[[ "${1:-}" == --pipes ]] && exit 0
sim tools/sim/scenarios/basement.yaml -o recordings/sim/basement-forward_backward.mcap --run forward_backward
sim tools/sim/scenarios/parking_garage.yaml -o recordings/sim/garage-loops-60s.mcap --run loops --duration 60
sim tools/sim/scenarios/highway.yaml -o recordings/sim/highway-map-5s.mcap --run map --duration 5
ls -la recordings/sim out/pipes-lawnmower-150s.mcap
