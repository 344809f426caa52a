#!/usr/bin/env bash
# The main job end to end on the embedded sample recording: GPR localisation (seed 000 ch. 4)
# on the simulated basement run (recordings/sim/basement-forward_backward.mcap: IMU, wheel
# encoder, GPR, ground truth; three times forward and back along an 8 m line). The radar
# traces go through the pre-processing chain into submaps, the learned model
# (stages/register/models) registers each new submap against the earlier ones the estimate
# places on the same line, and the factor-graph estimator fuses the registrations with IMU
# preintegration and wheel odometry (graphs/localize.yaml). Prints what was recorded, the
# accuracy against the ground truth beside odometry alone, and draws both (out/demo.png).
set -euo pipefail
cd "$(dirname "$0")/../.."
tools/scripts/ensure-font.sh
tools/scripts/ensure-onnxruntime.sh > /dev/null
cargo build --release -p gprflow-cli
g=./target/release/gprflow
out="${1:-out/demo.mcap}"
recording=recordings/sim/basement-forward_backward.mcap
mkdir -p "$(dirname "$out")"
$g launch graphs/localize.yaml --set recording="$recording" --set method=learned --record "$out"
$g inspect "$out"
# the same recording without GPR: IMU and wheel odometry only
$g launch graphs/odometry.yaml --set recording="$recording" --record "${out%.mcap}-odometry.mcap"
echo "== with learned GPR registration (graphs/localize.yaml), beside odometry alone (graphs/odometry.yaml)"
$g eval "$out" --truth "$recording" --compare odometry="${out%.mcap}-odometry.mcap" --plot "${out%.mcap}.png"
echo "plot: ${out%.mcap}.png (registrations: ${out%.mcap}-registration.png)"
