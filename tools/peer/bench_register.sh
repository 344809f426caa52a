#!/usr/bin/env bash
# The learned registration model's benchmark, side by side in one run, one thread each: the
# encoder per 201 x 200 submap in Rust (gprflow-register: standardisation + the model's front end
# + ONNX Runtime through ort + copy-out) and in Python onnxruntime (run alone, and with the standardisation),
# and the correlation + head per pair in Rust (next to the correlation of one pair in numpy).
# Checks that the Rust features agree with Python's to 1e-5 relative. Targets: encoder
# <= 0.5 ms/submap, correlation + head <= 0.2 ms/pair.
# Results: out/bench-register/{submaps.f32,ours.json,python.json,table.txt}.
#
# usage: tools/peer/bench_register.sh [ITERATIONS (2000)] [MODEL.onnx HEAD.json]
#        (default: the committed stages/register/models/ground_encoding.{onnx,head.json})
set -euo pipefail
cd "$(dirname "$0")/../.."
iterations=${1:-2000}
model=${2:-stages/register/models/ground_encoding.onnx}
head=${3:-stages/register/models/ground_encoding.head.json}
py=${PYTHON:-.venv-train/bin/python}
out=out/bench-register
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
for f in "$model" "$head"; do
    [[ -f $f ]] || { echo "bench_register: $f not found (tools/train/train.py writes it)" >&2; exit 1; }
done
"$py" -c "import onnxruntime, numpy" 2>/dev/null ||
    { echo "bench_register: $py lacks onnxruntime/numpy (python3 -m venv .venv-train && .venv-train/bin/pip install -r tools/train/requirements.txt)" >&2; exit 1; }
lib=$(tools/scripts/ensure-onnxruntime.sh | tail -1)
mkdir -p "$out"
"$py" tools/peer/bench_register.py generate "$out/submaps.f32" 8
cargo build -q --release -p gprflow-register --no-default-features --example bench_register
"$CARGO_TARGET_DIR/release/examples/bench_register" "$out/submaps.f32" --model "$model" --head "$head" \
    --ort-library "$lib" --iterations "$iterations" --output "$out/ours.f32" | tee "$out/ours.json"
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
    "$py" tools/peer/bench_register.py run "$out/submaps.f32" --model "$model" --head "$head" \
    --ours "$out/ours.f32" --iterations "$iterations" | tee "$out/python.json"
"$py" - "$out" <<'PY' | tee "$out/table.txt"
import json, sys
d = sys.argv[1]
ours = json.load(open(f"{d}/ours.json"))
py = json.load(open(f"{d}/python.json"))
k, h, w = ours["features"]
print(f"{ours['submap'][0]} x {ours['submap'][1]} submaps -> features {k} x {h} x {w} ({k * h * w} values), "
      f"{ours['shifts_tried']} shifts; one thread; {ours['encoder']['iterations']} iterations")
print(f"front end {ours['front_end']}")
print(f"{'':56} {'median ms':>10} {'p90 ms':>8} {'min ms':>8}")
rows = [("encoder, Rust (standardise + front end + ort run + copy)", ours["encoder"]),
        ("  of which the front end, Rust", ours["front_end_only"]),
        ("encoder, Python onnxruntime (graph run only)", py["encoder_run"]),
        ("encoder, Python (standardise + numpy front end + run)", py["encoder_standardise_and_run"]),
        ("correlation + head, Rust (Model::register)", ours["correlation_and_head"]),
        ("correlation only, Rust", ours["correlation_only"])]
if isinstance(py.get("numpy_correlation_batched_fft_one_pair"), dict):
    rows.append(("correlation, numpy (train.py batched FFT, one pair)", py["numpy_correlation_batched_fft_one_pair"]))
for name, s in rows:
    print(f"{name:56} {s['median_ms']:10.4f} {s['p90_ms']:8.4f} {s['min_ms']:8.4f}")
print(f"targets: encoder <= 0.5 ms/submap: {ours['encoder']['median_ms'] <= 0.5}; "
      f"correlation + head <= 0.2 ms/pair: {ours['correlation_and_head']['median_ms'] <= 0.2}")
print(f"Rust vs Python features max relative error {py['ours_vs_python_rel']:.2e}; agree: {py['agree_to_1e-5']}")
PY
