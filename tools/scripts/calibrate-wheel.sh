#!/usr/bin/env bash
# The simulated rig's wheel calibration (the graphs' `wheel_scale`): simulates every run of
# the training scenarios (tools/sim/scenarios/training_*.yaml, the ones the learned model is
# trained on; never the evaluation worlds) and fits the wheel's scale against their ground
# truth with `gprflow calibrate-wheel`. About a minute on 2 cores.
#   tools/scripts/calibrate-wheel.sh
#   GPRFLOW=target/debug/gprflow tools/scripts/calibrate-wheel.sh   # with the test build
set -euo pipefail
cd "$(dirname "$0")/../.."
if [[ -z "${GPRFLOW:-}" ]]; then
    cargo build --release -p gprflow-cli
fi
g=${GPRFLOW:-./target/release/gprflow}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for scenario in tools/sim/scenarios/training_*.yaml; do
    name=$(basename "$scenario" .yaml)
    for run in lawnmower long_drive forward_backward by_hand; do
        $g sim "$scenario" --run "$run" -o "$tmp/$name-$run.mcap" > /dev/null
    done
done
$g calibrate-wheel "$tmp"/*.mcap
