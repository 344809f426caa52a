# Shared by tools/scripts/residuals.sh and tools/scripts/by-hand-factors.sh (sourced, not
# run): their common arguments, the gprflow binary and the localisation run. The tables over
# the evaluation worlds are `gprflow experiment` (tools/experiments/tables.yaml, repeats.yaml).
# The caller sets `script` (its name, for messages) and `sets=()` first.

# Takes `--set KEY=VALUE` off the front of "$@": sets `took` to how many arguments that was
# (0 when the first is something else).
take_common_arg() {
    took=0
    case $1 in
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

# Localises recording $1 with method $2 (graphs/localize.yaml, oracle association: the
# candidate pairs from the truth, as the experiments' tables use) and evaluates it against the
# recording's truth: $3.mcap, $3.log and $3.json (as tools/experiments/tables.yaml's models).
# Further arguments go to the launch (e.g. "${sets[@]}"). Needs `g` (choose_gprflow).
localise() {
    local rec=$1 method=$2 base=$3
    shift 3
    $g launch graphs/localize.yaml --set recording="$rec" --set method="$method" --set association=truth \
        "$@" --record "$base.mcap" > "$base.log" 2>&1
    $g eval "$base.mcap" --truth "$rec" --format json > "$base.json"
}
