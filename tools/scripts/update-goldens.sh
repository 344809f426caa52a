#!/usr/bin/env bash
# Regenerates the golden outputs of the shipped graphs (recordings/golden/GRAPH.mcap) on
# purpose, showing with `gprflow diff` what changed against the previous golden first.
# The golden tests (tests/e2e/golden.rs, `golden_*`) rerun each graph of
# recordings/golden/inputs.txt and diff it against its golden; run this script when a change of output is intended, and commit the
# new goldens with the change that caused them.
#   tools/scripts/update-goldens.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build -p gprflow-cli
bin=target/debug/gprflow
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# every golden run as recordings/golden/inputs.txt lists it (tests/e2e/golden.rs reads the same
# list); simulator inputs made on demand
while read -r graph input sets_text; do
    [[ -z "$graph" || "$graph" == \#* ]] && continue
    sets=()
    if [[ "$input" != "-" ]]; then
        IFS=: read -r scenario run seconds <<< "$input"
        sample="$tmp/${scenario%.yaml}-$run-${seconds}s.mcap"
        [[ -f "$sample" ]] || "$bin" sim "tools/sim/scenarios/$scenario" --run "$run" --duration "$seconds" -o "$sample"
        sets+=(--set "recording=$sample")
    fi
    for set in $sets_text; do
        sets+=(--set "$set")
    done
    "$bin" launch "graphs/$graph.yaml" "${sets[@]}" --record "$tmp/$graph.mcap" < /dev/null
    golden="recordings/golden/$graph.mcap"
    if [[ -f "$golden" ]]; then
        echo "== $graph: changes against the previous golden"
        "$bin" diff "$golden" "$tmp/$graph.mcap" < /dev/null || true
    fi
    cp "$tmp/$graph.mcap" "$golden"
done < recordings/golden/inputs.txt
ls -la recordings/golden
