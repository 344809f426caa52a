#!/usr/bin/env bash
# Throughput of the LGPR's SFCW chain (11 channels x 51 tones -> 1024-point inverse transform,
# 369 samples kept), one thread, side by side in one run: gprflow-lgpr (release build) and the
# same chain in numpy, vectorised per sweep. Results: out/bench-sfcw/{ours,numpy}.json and
# out/bench-sfcw/table.txt.
#
# usage: tools/peer/bench_sfcw.sh [sweeps for Rust (20000)] [sweeps for numpy (5000)]
set -euo pipefail
cd "$(dirname "$0")/../.."
ours_n=${1:-20000}
numpy_n=${2:-5000}
python=.venv-peers/bin/python
out=out/bench-sfcw
mkdir -p "$out"
target=${CARGO_TARGET_DIR:-target}
cargo build --release -q -p gprflow-lgpr --no-default-features --example bench_sfcw
# one core each: the per-core figure is what the target is about
pin=""
if command -v taskset >/dev/null; then pin="taskset -c 0"; fi
echo "== gprflow-lgpr ($ours_n sweeps)"
$pin "$target/release/examples/bench_sfcw" "$ours_n" | tee "$out/ours.json"
echo "== numpy ($numpy_n sweeps)"
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $pin "$python" tools/peer/bench_sfcw.py "$numpy_n" | tee "$out/numpy.json"
"$python" - "$out" <<'PY' | tee "$out/table.txt"
import json, sys
out = sys.argv[1]
rows = [json.load(open(f"{out}/{name}.json")) for name in ("ours", "numpy")]
print(f"{'implementation':<48} {'sweeps/s':>10} {'us/sweep':>9} {'x 126 Hz':>9}")
for r in rows:
    print(f"{r['implementation']:<48} {r['sweeps_per_s']:>10.0f} {r['ns_per_sweep'] / 1e3:>9.1f} {r['realtime_factor_126hz']:>9.0f}")
a, b = rows[0]["checksum"], rows[1]["checksum"]
print(f"checksums (first 1000 sweeps, one sample each): {a:.6g} vs {b:.6g}: " + ("agree" if abs(a - b) <= 1e-5 * max(abs(b), 1e-30) else "DIFFER"))
print(f"speed-up over numpy: {rows[0]['sweeps_per_s'] / rows[1]['sweeps_per_s']:.1f}x; target 10000 sweeps/s per core: "
      + ("met" if rows[0]['sweeps_per_s'] >= 10000 else "NOT met"))
PY
