#!/usr/bin/env bash
# The LGPR tracker's benchmark (seed 001 §2.2), side by side in one run, one core each: the
# 5-DOF particle swarm registration of sweeps against a 50 m local grid of a real map store
# in Rust (gprflow-lgpr) and the same correlation + swarm in numpy (vectorised over the
# particles), on the same grid, sweeps, seeds and schedule; the correlations of the two at
# 200 poses compared; the gridding of 50 m grids timed; and a whole highway lap replayed through
# graphs/lgpr-track.yaml as fast as it goes (real-time factor). Targets: >= 1000 sweeps/s on one
# core, a grid within 0.9 s (25 m at 97 km/h), the lap faster than real time.
# Results: out/bench-track/{ours.json,numpy.json,table.txt}.
#
# usage: tools/peer/bench_track.sh [sweeps for Rust (4000)] [sweeps for numpy (300)]
set -euo pipefail
cd "$(dirname "$0")/../.."
ours_n=${1:-4000}
numpy_n=${2:-300}
out=out/bench-track
target=${CARGO_TARGET_DIR:-target}
python=.venv-peers/bin/python
[[ -x $python ]] || tools/peer/setup-venv.sh >/dev/null
mkdir -p "$out"
cargo build -q -p gprflow-cli
cargo build -q --release -p gprflow-lgpr --no-default-features --example bench_track
gprflow="$target/debug/gprflow"
sim=tools/sim/scenarios/highway.yaml
[[ -f $out/map.mcap ]] || "$gprflow" sim "$sim" -o "$out/map.mcap" --run map >/dev/null
if [[ ! -f $out/map.lgprmap/manifest.json ]]; then
    "$gprflow" launch graphs/lgpr-map.yaml --set recording="$out/map.mcap" --set map="$out/map.lgprmap" 2>&1 | grep "map written"
fi
pin=""
if command -v taskset >/dev/null; then pin="taskset -c 0"; fi
echo "== gprflow-lgpr ($ours_n sweeps)"
$pin "$target/release/examples/bench_track" "$out/map.lgprmap" "$out/dump" "$ours_n" > "$out/ours.json"
echo "== numpy ($numpy_n sweeps)"
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $pin "$python" tools/peer/bench_track.py "$out/dump" "$numpy_n" > "$out/numpy.json"
OMP_NUM_THREADS=1 "$python" tools/peer/bench_track.py "$out/dump" --check > "$out/numpy_check.json"
echo "== a highway lap at 97 km/h through graphs/lgpr-track.yaml"
[[ -f $out/track_97.mcap ]] || "$gprflow" sim "$sim" -o "$out/track_97.mcap" --run track_97 >/dev/null
"$gprflow" launch graphs/lgpr-track.yaml --set recording="$out/track_97.mcap" --set map="$out/map.lgprmap" \
    --record "$out/track_97-fix.mcap" > "$out/lap.log" 2>&1
"$python" - "$out" <<'PY' | tee "$out/table.txt"
import json, re, sys
out = sys.argv[1]
ours = json.load(open(f"{out}/ours.json"))
numpy = json.load(open(f"{out}/numpy.json"))
check_ours = json.load(open(f"{out}/dump/ours_check.json"))
check_np = json.load(open(f"{out}/numpy_check.json"))
first = ours["configs"][0]
print(f"{'implementation':<44} {'particles x it':>14} {'sweeps/s':>9} {'p50 us':>8} {'p99 us':>8} {'xy RMS cm':>9} {'<=5 cm':>7}")
for c in ours["configs"]:
    print(f"{'gprflow-lgpr (Rust)':<44} {c['particles']:>6} x {c['iterations']:<5} {c['sweeps_per_s']:>9.0f} {c['p50_us']:>8.0f} {c['p99_us']:>8.0f} "
          f"{100 * c['position_rms_m']:>9.2f} {100 * c['found_xy_within_5cm']:>6.1f}%")
print(f"{numpy['implementation']:<44} {numpy['particles']:>6} x {numpy['iterations']:<5} {numpy['sweeps_per_s']:>9.0f} {numpy['p50_us']:>8.0f} "
      f"{numpy['p99_us']:>8.0f} {100 * numpy['position_rms_m']:>9.2f} {100 * numpy['found_xy_within_5cm']:>6.1f}%")
diff = max(abs(a["correlation"] - b) for a, b in zip(check_ours, check_np["correlations"]))
same = all(a["overlap"] == b for a, b in zip(check_ours, check_np["overlaps"]))
print(f"eq. 8 at {len(check_ours)} poses, Rust vs numpy: max |difference| {diff:.2e}, overlaps " + ("agree" if same else "DIFFER"))
print(f"speed-up over numpy at {first['particles']} x {first['iterations']}: {first['sweeps_per_s'] / numpy['sweeps_per_s']:.1f}x; "
      f"target 1000 sweeps/s per core: " + ("met" if first["sweeps_per_s"] >= 1000 else "NOT met"))
g = ours["grid"]
print(f"gridding a 50 m grid ({g['grids_timed']} grids along the lap): p50 {g['gridding_ms_p50']:.0f} ms, max {g['gridding_ms_max']:.0f} ms "
      f"(budget 900 ms); {g['occupied_points']} points with data, {g['bytes'] / 1e6:.0f} MB")
log = open(f"{out}/lap.log").read()
wall = float(re.search(r"finished in ([0-9.]+) s", log).group(1))
sweeps = int(re.search(r"lgpr_track: done sweeps=(\d+)", log).group(1))
sensor_s = sweeps / 126.0
print(f"highway lap at 97 km/h ({sweeps} sweeps, {sensor_s:.0f} s of sensor time) through graphs/lgpr-track.yaml in {wall:.1f} s: "
      f"{sensor_s / wall:.1f}x real time")
PY
