#!/usr/bin/env bash
# The trace-chain benchmark, side by side in one run: gprflow-dsp (Rust, one trace at a time,
# one thread) and the same chain in numpy/scipy, per trace and vectorised over the batch, on
# the same N seeded CMU-GPR-like traces (201 samples at 0.2 ns, int16). Checks that the
# outputs agree to 1e-5 relative. Results: out/bench-dsp/{input.i16,ours.json,python.json,table.txt}.
#
# usage: tools/peer/bench_dsp.sh [N (20000)]
set -euo pipefail
cd "$(dirname "$0")/../.."
n=${1:-20000}
py=.venv-peers/bin/python
out=out/bench-dsp
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
mkdir -p "$out"
"$py" tools/peer/bench_dsp.py generate "$out/input.i16" "$n"
cargo build -q --release -p gprflow-dsp --no-default-features --example bench_dsp
"$CARGO_TARGET_DIR/release/examples/bench_dsp" "$out/input.i16" --repeat 5 --output "$out/ours.f32" | tee "$out/ours.json"
# Single-threaded BLAS/OpenMP for the Python side too: traces per second per core.
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
    "$py" tools/peer/bench_dsp.py run "$out/input.i16" --ours "$out/ours.f32" --out "$out" | tee "$out/python.json"
"$py" - "$out" <<'PY' | tee "$out/table.txt"
import json, sys
d = sys.argv[1]
ours = json.load(open(f"{d}/ours.json"))
py = json.load(open(f"{d}/python.json"))
rows = [("gprflow-dsp (Rust, per trace)", ours["traces_per_s"]),
        ("python per trace (scipy)", py["per_trace"]["traces_per_s"]),
        ("python vectorised (scipy, axis=1)", py["vectorised"]["traces_per_s"])]
print(f"{py['traces']} traces x {py['samples']} samples, one core")
print(f"{'chain':36} {'traces/s':>12} {'us/trace':>9} {'ours/x':>8}")
for name, tps in rows:
    print(f"{name:36} {tps:12.0f} {1e6 / tps:9.2f} {ours['traces_per_s'] / tps:8.1f}")
print(f"ours vs python max relative error (per trace): {py['ours_vs_python_rel']:.2e}; "
      f"python per trace vs vectorised: {py['per_trace_vs_vectorised_rel']:.2e}; agree: {py['agree_to_1e-5']}")
PY
