#!/usr/bin/env bash
# The registration gate's data (graphs/localize.yaml `gate_sigmas`, and the older `gate_m`,
# `gate_growth_mps`): the learned model localises the training scenarios' runs that pass ground
# twice (forward_backward and by_hand of training_1, _2 and the held-out _3; never the evaluation
# worlds), with the gates off, oracle association and the estimate's own, recording the
# estimator's registration checks with each residual's predicted sigma (graphs/localize.yaml
# `diagnostics=true`); `gprflow eval` checks each against the truth and gives the smallest gate
# that keeps every right registration (in sigmas, and in metres per growth rate), and this script
# takes the largest over the runs.
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
out=out/residuals
mkdir -p "$out"
reports=()
for scenario in training_1 training_2 training_3; do
    for run in forward_backward by_hand; do
        rec=$out/$scenario-$run.mcap
        [[ -f $rec ]] || $g sim "tools/sim/scenarios/$scenario.yaml" -o "$rec" --run "$run" > /dev/null
        for association in truth estimate; do
            base=$out/$scenario-$run-$association
            $g launch graphs/localize.yaml --set recording="$rec" --set method=learned \
                --set association="$association" --set gate_m=0 --set gate_sigmas=0 --set diagnostics=true "${sets[@]}" \
                --record "$base.run.mcap" > "$base.log" 2>&1
            $g eval "$base.run.mcap" --truth "$rec" --format json > "$base.json"
            reports+=("$base.json")
        done
        echo "$scenario $run done" >&2
    done
done
python3 - "${reports[@]}" <<'PY' | tee "$out/residuals.md"
import json, sys
checks = [json.load(open(f))["registration_checks"] for f in sys.argv[1:]]
checks = [c for c in checks if c]
count = lambda k: sum(c["accepted"][k] + c["gated"][k] for c in checks)
print(f"{count('count')} registrations in {len(checks)} runs: {count('right')} right, {count('wrong')} wrong "
      f"(> {100 * checks[0]['tolerance_m']:g} cm)")
wrong = sorted((r for c in checks for r in c["wrong_residuals_m"]), reverse=True)
if wrong:
    print("wrong ones, |residual| m: " + ", ".join(f"{r:.3f}" for r in wrong))
right_sigmas = [c["right_sigmas_max"] for c in checks if c.get("right_sigmas_max") is not None]
if right_sigmas:
    print(f"smallest Mahalanobis gate under which every right registration fell: {max(right_sigmas):.2f} sigma")
    wrong_sigmas = sorted((w for c in checks for w in c["wrong_sigmas"]), reverse=True)
    if wrong_sigmas:
        print("wrong ones, |residual| / sigma: " + ", ".join(f"{w:.2f}" for w in wrong_sigmas))
print("| growth (m/s) | smallest base under which every right registration fell (m) |")
print("|---|---|")
for k, g in enumerate(checks[0]["gate_bases"]):
    print(f"| {g['growth_mps']:g} | {max(c['gate_bases'][k]['base_m'] for c in checks):.3f} |")
PY
