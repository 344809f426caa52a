# Shared by tools/scripts/tables.sh and tools/scripts/repeats.sh (sourced, not run): their
# common arguments, the gprflow binary, the evaluation worlds, the output folders and the
# localisation and repeat runs they all make.
# The caller sets `script` (its name, for messages), `by_hand=0` and `sets=()` first.

# Takes `--by-hand` or `--set KEY=VALUE` off the front of "$@": sets `took` to how many
# arguments that was (0 when the first is neither).
take_common_arg() {
    took=0
    case $1 in
        --by-hand) by_hand=1; took=1 ;;
        --set)
            [[ $# -ge 2 && $2 == *=* ]] || { echo "$script: --set needs KEY=VALUE" >&2; exit 2; }
            sets+=(--set "$2")
            took=2 ;;
    esac
}

# Sets `g` to the gprflow binary: $GPRFLOW when set (e.g. target/debug/gprflow, the test
# build), else a release build made here. ONNX Runtime is fetched first.
choose_gprflow() {
    tools/scripts/ensure-onnxruntime.sh > /dev/null
    if [[ -z "${GPRFLOW:-}" ]]; then
        cargo build --release -p gprflow-cli
    fi
    g=${GPRFLOW:-./target/release/gprflow}
}

# Sets `worlds` to the evaluation worlds, one "name scenario run" per entry: each world's
# plain run, or its `by_hand` run when by_hand=1.
eval_worlds() {
    worlds=(
        "basement tools/sim/scenarios/basement.yaml forward_backward"
        "factory_floor tools/sim/scenarios/factory_floor.yaml forward_backward"
        "parking_garage tools/sim/scenarios/parking_garage.yaml loops"
    )
    if [[ $by_hand == 1 ]]; then
        for i in "${!worlds[@]}"; do worlds[i]="${worlds[i]% *} by_hand"; done
    fi
}

# Prints the output folder for base folder $1 and the graph variables in `sets`: the base
# itself, or "base-key=value..." (the recordings stay in the base, shared by all).
sets_folder() {
    local folder=$1 i
    for ((i = 1; i < ${#sets[@]}; i += 2)); do folder+="-${sets[i]//[^A-Za-z0-9_.=]/_}"; done
    echo "$folder"
}

# Sets `odometry_sets` to the `sets` that graphs/odometry.yaml declares a variable for (as
# `gprflow check` says; the wheel's calibration is one), so that its runs ride on the same
# wheel as the localisation runs. Needs `g` (choose_gprflow).
odometry_only_sets() {
    odometry_sets=()
    local i
    for ((i = 1; i < ${#sets[@]}; i += 2)); do
        if $g check graphs/odometry.yaml --set "${sets[i]}" > /dev/null 2>&1; then
            odometry_sets+=(--set "${sets[i]}")
        fi
    done
    return 0
}

# Localises recording $1 with method $2 (graphs/localize.yaml, oracle association: the
# candidate pairs from the truth, as every table here uses) and evaluates it against the
# recording's truth: $3.mcap, $3.log and $3.json. Further arguments go to the launch (e.g.
# "${sets[@]}"). Needs `g` (choose_gprflow).
localise() {
    local rec=$1 method=$2 base=$3
    shift 3
    $g launch graphs/localize.yaml --set recording="$rec" --set method="$method" --set association=truth \
        "$@" --record "$base.mcap" > "$base.log" 2>&1
    $g eval "$base.mcap" --truth "$rec" --format json > "$base.json"
}

# Runs recording $1 with odometry alone (graphs/odometry.yaml, on the wheel of `odometry_sets`)
# and evaluates it against the recording's truth: $2.mcap, $2.log and $2.json. Needs `g` and
# `odometry_sets` (odometry_only_sets).
odometry_run() {
    local rec=$1 base=$2
    $g launch graphs/odometry.yaml --set recording="$rec" "${odometry_sets[@]}" --record "$base.mcap" > "$base.log" 2>&1
    $g eval "$base.mcap" --truth "$rec" --format json > "$base.json"
}

# Simulates repeat $4 of world $1's run ($2 scenario, $3 run; `gprflow sim --repeat`: fresh
# sensor noise and vibration, the same world and path) into $recs when it is not there, and
# runs it with each model after the fourth argument (odometry: `odometry_run`; else
# `localise`) into $out/<world>-<repeat>-<model>.json and .log, keeping no run recording.
# With REUSE=1 a model whose JSON is there is skipped. Needs `g`, `recs`, `out`,
# `odometry_sets` and `sets`.
repeat_runs() {
    local name=$1 scenario=$2 run=$3 k=$4 m base
    shift 4
    local rec="$recs/$name-$run-$k.mcap"
    [[ -f "$rec" ]] || $g sim "$scenario" -o "$rec" --run "$run" --repeat "$k" > /dev/null
    for m in "$@"; do
        base="$out/$name-$k-$m"
        [[ "${REUSE:-0}" == 1 && -s "$base.json" ]] && continue
        if [[ $m == odometry ]]; then
            odometry_run "$rec" "$base"
        else
            localise "$rec" "$m" "$base" "${sets[@]}"
        fi
        rm -f "$base.mcap"
    done
}
