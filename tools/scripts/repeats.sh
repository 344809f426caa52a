#!/usr/bin/env bash
# How much a single run's ATE says: each world's run simulated again with fresh sensor noise
# and vibration (`gprflow sim --repeat K`, the same world and path), localised with
# odometry only, the learned model and the oracle (graphs/localize.yaml, oracle
# association, as tools/scripts/tables.sh), and summarised per world: the ATE's mean and
# range, and in how many repeats the learned model is within 15 % of the oracle.
#
#   tools/scripts/repeats.sh                # repeats 1..4 of the plain runs: out/repeats
#   tools/scripts/repeats.sh --by-hand -n 6 # repeats 1..6 of the by_hand runs: out/repeats-by-hand
#   tools/scripts/repeats.sh --set stamps=overlap  # localisation with that graph variable too:
#                                           # out/repeats-stamps=overlap (same recordings)
#   tools/scripts/repeats.sh --set wheel_scale=1   # uncalibrated wheel (the odometry runs too)
#   GPRFLOW=target/debug/gprflow tools/scripts/repeats.sh   # with the test build
#   REUSE=1 tools/scripts/repeats.sh        # keep the runs already there (their JSON)
set -euo pipefail
cd "$(dirname "$0")/../.."
source tools/scripts/lib/worlds.sh
script=repeats.sh
n=4
by_hand=0
sets=()
while [[ $# -gt 0 ]]; do
    take_common_arg "$@"
    if [[ $took -gt 0 ]]; then shift "$took"; continue; fi
    case $1 in
        -n)
            [[ $# -ge 2 && $2 =~ ^[1-9][0-9]*$ ]] || { echo "repeats.sh: -n needs a count" >&2; exit 2; }
            n=$2
            shift ;;
        *) echo "repeats.sh: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
choose_gprflow
eval_worlds
out=out/repeats
[[ $by_hand == 1 ]] && out=out/repeats-by-hand
recs=$out
out=$(sets_folder "$out")
mkdir -p "$out" "$recs"
odometry_only_sets

for w in "${worlds[@]}"; do
    read -r name scenario run <<< "$w"
    for ((k = 1; k <= n; k++)); do
        repeat_runs "$name" "$scenario" "$run" "$k" odometry learned oracle
        echo "$name repeat $k done" >&2
    done
done

python3 - "$out" "$n" <<'EOF'
import json, pathlib, statistics, sys
out, n = pathlib.Path(sys.argv[1]), int(sys.argv[2])
worlds = ["basement", "factory_floor", "parking_garage"]
def ate(w, k, m):
    return json.loads((out / f"{w}-{k}-{m}.json").read_text())["ate"]["rmse"]
print(f"ATE over {n} repeats (fresh sensor noise, same world and path; m, no alignment): mean [min, max]")
print()
print("| run | " + " | ".join(worlds) + " |")
print("|---|" + "---|" * len(worlds))
for m in ["odometry", "learned", "oracle"]:
    cells = []
    for w in worlds:
        v = [ate(w, k, m) for k in range(1, n + 1)]
        cells.append(f"{statistics.mean(v):.3f} [{min(v):.3f}, {max(v):.3f}]")
    print(f"| {m} | " + " | ".join(cells) + " |")
cells = []
for w in worlds:
    r = [ate(w, k, "learned") / ate(w, k, "oracle") for k in range(1, n + 1)]
    within = sum(x <= 1.15 for x in r)
    cells.append(f"{statistics.mean(r):.2f} [{min(r):.2f}, {max(r):.2f}], within 15 %: {within} of {n}")
print("| learned / oracle | " + " | ".join(cells) + " |")
EOF
