#!/usr/bin/env bash
# Regenerates the golden outputs of the shipped graphs (recordings/golden/GRAPH.mcap) on
# purpose, showing with `gprflow diff` what changed against the previous golden first.
# The golden tests (tests/e2e/golden.rs, `golden_*`) rerun each graph and diff it
# against its golden; run this script when a change of output is intended, and commit the
# new goldens with the change that caused them.
#   tools/scripts/update-goldens.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build -p gprflow-cli
bin=target/debug/gprflow
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# inputs made on demand (as tests/e2e/sim.rs makes them: keep the two alike)
"$bin" sim tools/sim/scenarios/pipes_one_line.yaml --run lawnmower --duration 150 -o "$tmp/pipes.mcap"
"$bin" sim tools/sim/scenarios/parking_garage.yaml --run loops --duration 20 -o "$tmp/garage.mcap"
"$bin" sim tools/sim/scenarios/highway.yaml --run map --duration 1 -o "$tmp/highway.mcap"
for graph in toy replay-toy odometry slam localize submaps lgpr-sweeps; do
    sets=()
    case $graph in
        slam) sets=(--set "recording=$tmp/pipes.mcap") ;;
        submaps) sets=(--set "recording=$tmp/garage.mcap" --set spacing_m=1.0) ;;
        lgpr-sweeps) sets=(--set "recording=$tmp/highway.mcap") ;;
    esac
    "$bin" launch "graphs/$graph.yaml" "${sets[@]}" --record "$tmp/$graph.mcap"
    golden="recordings/golden/$graph.mcap"
    if [[ -f "$golden" ]]; then
        echo "== $graph: changes against the previous golden"
        "$bin" diff "$golden" "$tmp/$graph.mcap" || true
    fi
    cp "$tmp/$graph.mcap" "$golden"
done
ls -la recordings/golden
