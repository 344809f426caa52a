#!/usr/bin/env bash
# The registration gate's data (graphs/localize.yaml `gate_m`, `gate_growth_mps`): the learned
# model localises the training scenarios' runs that pass ground twice (forward_backward and
# by_hand of training_1, _2 and the held-out _3; never the evaluation worlds), with the gate
# off, oracle association and the estimate's own, and tools/scripts/residuals.py reports how
# far the registrations were from the estimate when they arrived.
#
#   tools/scripts/residuals.sh                  # out/residuals: recordings, logs, the table
#   tools/scripts/residuals.sh --set stretch_steps=0   # without the stretch search (on by default)
#   GPRFLOW=target/debug/gprflow tools/scripts/residuals.sh
# About 6 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/../.."
source tools/scripts/lib/worlds.sh
script=residuals.sh
sets=()
while [[ $# -gt 0 ]]; do
    take_common_arg "$@"
    if [[ $took -gt 0 ]]; then shift "$took"; continue; fi
    echo "residuals.sh: unknown argument $1" >&2
    exit 2
done
choose_gprflow
tools/peer/setup-venv.sh > /dev/null
out=out/residuals
mkdir -p "$out"
pairs=()
for scenario in training_1 training_2 training_3; do
    for run in forward_backward by_hand; do
        rec=$out/$scenario-$run.mcap
        [[ -f $rec ]] || $g sim "tools/sim/scenarios/$scenario.yaml" -o "$rec" --run "$run" > /dev/null
        $g convert "$rec" --to tum --topic /truth/pose -o "$out/$scenario-$run.truth.txt" > /dev/null
        for association in truth estimate; do
            base=$out/$scenario-$run-$association
            $g launch graphs/localize.yaml --set recording="$rec" --set method=learned \
                --set association="$association" --set gate_m=0 "${sets[@]}" \
                --log info,gprflow_estimate=debug > "$base.log" 2>&1
            pairs+=("$base.log" "$out/$scenario-$run.truth.txt")
        done
        echo "$scenario $run done" >&2
    done
done
.venv-peers/bin/python tools/scripts/residuals.py "${pairs[@]}" | tee "$out/residuals.md"
