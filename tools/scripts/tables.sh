#!/usr/bin/env bash
# Reproduces seed 000 Table 4.1 (registration error per model and environment, cm) and
# Fig. 4.14 (ATE per environment for odometry, engineered, learned and oracle) on the
# simulator's evaluation worlds, and writes both tables into docs/localisation.md between the
# `tables:begin` / `tables:end` markers. Table 4.1 comes from each world's run. Fig. 4.14 is
# over several sequences per environment (15 in all in the thesis), so its table here is over
# each world's run and its repeats 1..n (`gprflow sim --repeat`: fresh sensor noise and
# vibration, the same world and path), as tools/scripts/repeats.sh makes them.
#
# Every localisation run uses graphs/localize.yaml with the oracle association (ground-truth
# loop candidates), so that all models see the same pairs (§4.8.4), and the same
# registration sigma. Registration errors come from `gprflow eval` (each registration
# against the truth's relative pose between its two anchor stamps).
#
#   tools/scripts/tables.sh            # about 20 minutes on 2 cores (8 repeats)
#   tools/scripts/tables.sh --no-readme  # print only
#   tools/scripts/tables.sh -n 0       # Fig. 4.14 from each world's run alone (5 minutes)
#   tools/scripts/tables.sh --by-hand  # each world's `by_hand` run instead (the rig wanders
#                                      # off its path, the soil dries): out/tables-by-hand,
#                                      # markers tables-by-hand:begin / :end
#   tools/scripts/tables.sh --set stamps=overlap  # every localisation run with that graph
#                                      # variable too: out/tables-stamps=overlap, docs untouched
#   tools/scripts/tables.sh --set wheel_scale=1   # uncalibrated wheel (the odometry runs too)
#   REUSE=1 tools/scripts/tables.sh      # keep the runs already in out/tables (their JSON)
#   GPRFLOW=target/debug/gprflow tools/scripts/tables.sh   # with the test build
set -euo pipefail
cd "$(dirname "$0")/../.."
source tools/scripts/lib/worlds.sh
script=tables.sh
write_readme=1
by_hand=0
n=8
sets=()
while [[ $# -gt 0 ]]; do
    take_common_arg "$@"
    if [[ $took -gt 0 ]]; then shift "$took"; continue; fi
    case $1 in
        --no-readme) write_readme=0 ;;
        -n)
            [[ $# -ge 2 && $2 =~ ^[0-9]+$ ]] || { echo "tables.sh: -n needs a count" >&2; exit 2; }
            n=$2
            shift ;;
        *) echo "tables.sh: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
choose_gprflow
eval_worlds
out=out/tables
marker=tables
if [[ $by_hand == 1 ]]; then
    out=out/tables-by-hand
    marker=tables-by-hand
fi
recs=$out
if [[ ${#sets[@]} -gt 0 ]]; then
    write_readme=0
    out=$(sets_folder "$out")
fi
mkdir -p "$out" "$recs"
odometry_only_sets
models=(engineered zeroth learned nonlinear oracle)

for w in "${worlds[@]}"; do
    read -r name scenario run <<< "$w"
    rec="$recs/$name-$run.mcap"
    [[ -f "$rec" ]] || $g sim "$scenario" -o "$rec" --run "$run" > /dev/null
    if [[ "${REUSE:-0}" != 1 || ! -s "$out/$name-odometry.json" ]]; then
        odometry_run "$rec" "$out/$name-odometry"
    fi
    for m in "${models[@]}"; do
        [[ "${REUSE:-0}" == 1 && -s "$out/$name-$m.json" ]] && continue
        method=$m
        extra=()
        if [[ $m == nonlinear ]]; then
            method=learned
            extra=(--set head=stages/register/models/ground_encoding.nonlinear.json)
        fi
        localise "$rec" "$method" "$out/$name-$m" "${extra[@]}" "${sets[@]}"
        echo "$name $m done" >&2
    done
    for ((k = 1; k <= n; k++)); do
        repeat_runs "$name" "$scenario" "$run" "$k" odometry engineered learned oracle
        echo "$name repeat $k done" >&2
    done
done

python3 - "$out" "$write_readme" "$marker" "$n" <<'EOF'
import functools, json, math, pathlib, re, statistics, sys
out, write, marker, repeats = pathlib.Path(sys.argv[1]), sys.argv[2] == "1", sys.argv[3], int(sys.argv[4])
worlds = ["basement", "factory_floor", "parking_garage"]
models = ["engineered", "zeroth", "learned", "nonlinear", "oracle"]
@functools.cache
def load(w, m):
    return json.loads((out / f"{w}-{m}.json").read_text())
lines = ["Registration error (RMSE of the along-track error against the truth, cm; pairs from the oracle association; n = registrations):", "",
         "| model | " + " | ".join(worlds) + " | combined |", "|---|" + "---|" * (len(worlds) + 1)]
for m in models:
    cells, sq, n = [], 0.0, 0
    for w in worlds:
        r = load(w, m).get("registration")
        if not r:
            cells.append("-")
            continue
        a = r["along_track"]
        cells.append(f"{100 * a['rmse']:.2f} (n={a['count']})")
        sq += a["rmse"] ** 2 * a["count"]
        n += a["count"]
    comb = f"{100 * math.sqrt(sq / n):.2f}" if n else "-"
    label = {"learned": "learned linear", "nonlinear": "learned nonlinear"}.get(m, m)
    lines.append(f"| {label} | " + " | ".join(cells) + f" | {comb} |")
def ates(w, m):
    """The ATE of model m over world w's sequences: its run, then its repeats 1..repeats."""
    return [load(s, m)["ate"]["rmse"] for s in [w] + [f"{w}-{k}" for k in range(1, repeats + 1)]]
if repeats == 0:
    over, cell = "each world's run", lambda v: f"{v[0]:.3f}"
else:
    over = f"over {repeats + 1} sequences per world, the world's run and its repeats 1-{repeats} with fresh sensor noise: mean [min, max]"
    cell = lambda v: f"{statistics.mean(v):.3f} [{min(v):.3f}, {max(v):.3f}]"
lines += ["", f"ATE (RMSE of the final trajectory against the truth, m, no alignment) {over}:", "",
          "| run | " + " | ".join(worlds) + " |", "|---|" + "---|" * len(worlds)]
for m in ["odometry", "engineered", "learned", "oracle"]:
    lines.append(f"| {m} | " + " | ".join(cell(ates(w, m)) for w in worlds) + " |")
cells = []
for w in worlds:
    learned, oracle = ates(w, "learned"), ates(w, "oracle")
    within = sum(a <= 1.15 * b for a, b in zip(learned, oracle))
    cells.append(f"{statistics.mean(learned) / statistics.mean(oracle):.2f}; within 15 % in {within} of {repeats + 1}")
lines.append("| learned / oracle (of the means; per sequence) | " + " | ".join(cells) + " |")
table = "\n".join(lines)
print(table)
if write:
    readme = pathlib.Path("docs/localisation.md")
    text = readme.read_text()
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    if begin not in text:
        sys.exit(f"docs/localisation.md has no {marker}:begin marker")
    text = re.sub(re.escape(begin) + ".*?" + re.escape(end), begin + "\n" + table + "\n" + end, text, flags=re.S)
    readme.write_text(text)
    print("docs/localisation.md updated", file=sys.stderr)
EOF
