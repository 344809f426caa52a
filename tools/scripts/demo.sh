#!/usr/bin/env bash
# The main job end to end on the embedded sample recording: replay the simulated parking-garage
# loop (recordings/sim/garage-loops-60s.mcap: IMU, wheel encoder, GPR, ground truth) through
# the factor-graph estimator (graphs/odometry.yaml), record the estimate, and show what was
# recorded, its accuracy against the ground truth and a plot of both (out/demo.png); then the
# GPR traces into submaps and the most salient one drawn (out/demo-submap.png).
set -euo pipefail
cd "$(dirname "$0")/../.."
tools/scripts/ensure-font.sh
cargo build --release -p gprflow-cli
out="${1:-out/demo.mcap}"
recording=recordings/sim/garage-loops-60s.mcap
mkdir -p "$(dirname "$out")"
./target/release/gprflow launch graphs/odometry.yaml --set recording="$recording" --record "$out"
./target/release/gprflow inspect "$out"
./target/release/gprflow eval "$out" --truth "$recording" --plot "${out%.mcap}.png"
echo "plot: ${out%.mcap}.png"
# the same recording's GPR through the pre-processing chain into submaps (graphs/submaps.yaml,
# one every 0.1 m here), and the most salient submap drawn
./target/release/gprflow launch graphs/submaps.yaml --set recording="$recording" --set spacing_m=0.1 \
    --record "${out%.mcap}-submaps.mcap"
./target/release/gprflow radargram "${out%.mcap}-submaps.mcap" --topic /filter/submap -o "${out%.mcap}-submap.png"
