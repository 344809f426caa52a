#!/usr/bin/env bash
# Throughput and memory at scale: shipped graphs replay long simulated recordings as fast as
# they go. For each run: the real-time factor (sensor time / wall time), and for every process
# its share of the run's CPU time, its callback p50/p99 and its peak RSS (from the reports the
# stages hand to `gprflow launch --report`). Recordings of 5, 20 and 60 minutes of sensor time
# are made on demand by the simulator (basement world; `long` is its 20.9-minute run, `hour`
# its 62.7-minute run, the 5-minute one is `long` cut with --duration). The LGPR graph
# (`lgpr`: graphs/lgpr-track.yaml) tracks laps of the highway world at 97 km/h (`long_97`,
# `long_97_20`, `long_97_60`: 5, 20 and 57 laps) against a map built first from its `map`
# run with graphs/lgpr-map.yaml (all made on demand; the 20-minute recording is about 0.7 GB).
# `slam_pipes` runs the line-SLAM graph on the two-pipe field (pipes_two_lines: its lawnmower cut
# to 5 minutes, `long` and `hour` for 20 and 60), where every row crosses both pipes.
#
# usage: tools/bench/scale.sh [GRAPH:MINUTES[:VAR=VALUE,...] ...]
#   default: submaps:5 submaps:20 submaps:60 odometry:5 odometry:20 odometry:60 localize:5 localize:20
#   GRAPH is a file of graphs/ (submaps, odometry, localize, slam), lgpr or slam_pipes; MINUTES is
#   5, 20 or 60;
#   VAR=VALUE pairs are graph variables set for that run (e.g. localize:60:resolve_window=4000).
#   submaps runs with a submap every 0.5 m (its default 0.02 m is for pictures). The
#   localisation graph's 20-minute run takes about 9 minutes (its loop-closure re-solves).
# Results: out/bench/scale/{GRAPH}-{MINUTES}min[-VAR=VALUE,...].json (launch reports), .recording
# (the recording it replayed) and table.md.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=out/bench/scale
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
gprflow="$CARGO_TARGET_DIR/release/gprflow"
runs=("$@")
if [ ${#runs[@]} -eq 0 ]; then
    runs=(submaps:5 submaps:20 submaps:60 odometry:5 odometry:20 odometry:60 localize:5 localize:20)
fi
mkdir -p "$out"
cargo build -q --release -p gprflow-cli

# the recording of a world (a scenario of tools/sim/scenarios) and length, made on demand
recording() {
    local world=$1 minutes=$2 file="$out/$1-${2}min.mcap" args
    case $world:$minutes in
        basement:5) args=(--run long --duration 300) ;;
        basement:20) args=(--run long) ;;
        basement:60) args=(--run hour) ;;
        highway:5) args=(--run long_97) ;;
        highway:20) args=(--run long_97_20) ;;
        highway:60) args=(--run long_97_60) ;;
        pipes_two_lines:5) args=(--run lawnmower --duration 300) ;;
        pipes_two_lines:20) args=(--run long) ;;
        pipes_two_lines:60) args=(--run hour) ;;
        *) echo "no recording of $minutes minutes (5, 20 or 60)" >&2; exit 2 ;;
    esac
    if [ ! -f "$file" ]; then
        "$gprflow" sim "tools/sim/scenarios/$world.yaml" "${args[@]}" -o "$file.part" --json > "$file.json"
        mv "$file.part" "$file"
    fi
    echo "$file"
}

# the highway map the LGPR runs track against, made on demand from the world's mapping run
lgpr_map() {
    local map="$out/highway.lgprmap"
    if [ ! -e "$map" ]; then
        [ -f "$out/highway-map.mcap" ] ||
            "$gprflow" sim tools/sim/scenarios/highway.yaml --run map -o "$out/highway-map.mcap" > /dev/null
        "$gprflow" launch graphs/lgpr-map.yaml --set recording="$out/highway-map.mcap" --set map="$map.part" \
            --log warn > /dev/null
        mv "$map.part" "$map"
    fi
    echo "$map"
}

for run in "${runs[@]}"; do
    IFS=: read -r graph minutes vars <<< "$run"
    name="$graph-${minutes}min${vars:+-$vars}"
    world=basement
    file=$graph
    if [ "$graph" = lgpr ]; then world=highway file=lgpr-track; fi
    if [ "$graph" = slam_pipes ]; then world=pipes_two_lines file=slam; fi
    rec=$(recording "$world" "$minutes")
    # the table reads which recording a run replayed from here
    echo "$rec" > "$out/$name.recording"
    sets=(--set "recording=$rec")
    if [ "$graph" = submaps ]; then sets+=(--set spacing_m=0.5); fi
    if [ "$graph" = lgpr ]; then sets+=(--set "map=$(lgpr_map)"); fi
    IFS=, read -r -a pairs <<< "$vars"
    for pair in "${pairs[@]}"; do sets+=(--set "$pair"); done
    echo "== $graph on $rec ${vars}" >&2
    "$gprflow" launch "graphs/$file.yaml" "${sets[@]}" --log info \
        --report "$out/$name.json" 2> "$out/$name.log" \
        || { echo "$graph on $rec failed: see $out/$name.log" >&2; exit 1; }
done

python3 - "$out" "${runs[@]}" <<'PY' | tee "$out/table.md"
import json, os, sys
out, runs = sys.argv[1], sys.argv[2:]
print("| graph | sensor min | wall s | x real time | process | CPU share | p50 us | p99 us | peak RSS MiB |")
print("|---|---:|---:|---:|---|---:|---:|---:|---:|")
for run in runs:
    graph, minutes, *vars = run.split(":")
    name = f"{out}/{graph}-{minutes}min{''.join('-' + v for v in vars)}"
    rep = json.load(open(f"{name}.json"))
    recording = open(f"{name}.recording").read().strip()
    graph += "".join(f" ({v})" for v in vars)
    sim = json.load(open(f"{recording}.json"))
    sensor_s = sim["duration_s"]
    nodes = [n for n in rep["nodes"] if n["report"]]
    cpu = sum(n["report"]["cpu_s"] for n in nodes) or 1.0
    first = True
    for n in nodes:
        r = n["report"]
        lead = (f"| {graph} | {sensor_s / 60:.1f} | {rep['wall_s']:.1f} | {sensor_s / rep['wall_s']:.1f} "
                if first else "| | | | ")
        first = False
        print(f"{lead}| {n['node']} | {100 * r['cpu_s'] / cpu:.0f}% | {r['callback_us'][0]} | "
              f"{r['callback_us'][1]} | {r['peak_rss_bytes'] / 2**20:.0f} |")
    missing = [n["node"] for n in rep["nodes"] if not n["report"]]
    if missing:
        print(f"| | | | | no report: {', '.join(missing)} | | | | |")
    size = os.path.getsize(recording)
    print(f"| | | | | (recording: {size / 2**20:.0f} MiB) | | | | |")
PY
