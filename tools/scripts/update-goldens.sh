#!/usr/bin/env bash
# Regenerates the golden outputs of the shipped graphs (recordings/golden/GRAPH.mcap) on
# purpose, showing with `gprflow diff` what changed against the previous golden first.
# The test `golden_outputs_still_match` (tests/e2e.rs) reruns each graph and diffs it
# against its golden; run this script when a change of output is intended, and commit the
# new goldens with the change that caused them.
#   tools/scripts/update-goldens.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build -p gprflow-cli
bin=target/debug/gprflow
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# the pipe-field sample of graphs/slam.yaml is made on demand (tools/sim/make-samples.sh)
"$bin" sim tools/sim/scenarios/pipes_one_line.yaml --run lawnmower --duration 150 -o "$tmp/pipes.mcap"
for graph in toy replay-toy odometry slam; do
    set_recording=()
    [[ $graph == slam ]] && set_recording=(--set "recording=$tmp/pipes.mcap")
    "$bin" launch "graphs/$graph.yaml" "${set_recording[@]}" --record "$tmp/$graph.mcap"
    golden="recordings/golden/$graph.mcap"
    if [[ -f "$golden" ]]; then
        echo "== $graph: changes against the previous golden"
        "$bin" diff "$golden" "$tmp/$graph.mcap" || true
    fi
    cp "$tmp/$graph.mcap" "$golden"
done
ls -la recordings/golden
