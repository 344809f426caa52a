#!/usr/bin/env bash
# Memory of reading a long CMU-GPR sequence folder: the `ingest` stage streams its four CSV files
# row by row (merged by stamp); `gprflow convert` reads them whole. The folder is a simulated 30 s
# basement sequence whose rows are repeated COPIES times, each copy stamped after the one before
# (default 40: 20 minutes).
#
# usage: tools/bench/cmu-stream.sh [COPIES (40)]
#   GPRFLOW=path/to/gprflow picks the binary (default: a release build, made here).
# Prints the peak RSS of each, and the folder's size.
set -euo pipefail
cd "$(dirname "$0")/../.."
copies=${1:-40}
if [ -z "${GPRFLOW:-}" ]; then
    cargo build -q --release -p gprflow-cli
    GPRFLOW=${CARGO_TARGET_DIR:-target}/release/gprflow
fi
out=out/bench/cmu-stream
mkdir -p "$out"
[[ -f $out/seed/gpr_meas.csv ]] || "$GPRFLOW" sim tools/sim/scenarios/basement.yaml -o "$out/seed.mcap" \
    --format cmu-gpr --duration 30 > /dev/null
python3 - "$copies" "$out/seed" "$out/long" << 'PY'
import os, sys
from decimal import Decimal
copies, src, dst = int(sys.argv[1]), sys.argv[2], sys.argv[3]
os.makedirs(dst, exist_ok=True)
files = [f for f in sorted(os.listdir(src)) if f.endswith(".csv")]
rows = {f: open(os.path.join(src, f)).read().splitlines() for f in files}
stamps = [Decimal(r.split(",", 1)[0]) for f in files for r in rows[f][1:] if r.strip()]
span = max(stamps) - min(stamps) + Decimal("0.1")
for f in files:
    with open(os.path.join(dst, f), "w") as w:
        w.write(rows[f][0] + "\n")
        for k in range(copies):
            shift = span * k
            for r in rows[f][1:]:
                if not r.strip():
                    continue
                t, rest = r.split(",", 1)
                w.write(f"{Decimal(t) + shift:.9f},{rest}\n")
PY
cat > "$out/ingest.yaml" << YAML
name: cmu-stream
nodes:
  ingest: { stage: ingest, params: { source: "$out/long" } }
  dsp: { stage: dsp, inputs: { trace: ingest/gpr } }
YAML
"$GPRFLOW" launch "$out/ingest.yaml" --report "$out/report.json" --log warn
python3 - "$GPRFLOW" "$out" << 'PY'
import json, os, resource, subprocess, sys
gprflow, out = sys.argv[1], sys.argv[2]
size = sum(os.path.getsize(os.path.join(out, "long", f)) for f in os.listdir(f"{out}/long")) / 2**20
report = json.load(open(f"{out}/report.json"))
ingest = next(n["report"] for n in report["nodes"] if n["node"] == "ingest")
sent = dict((t, n) for t, n in ingest["sent"])
subprocess.run([gprflow, "convert", f"{out}/long", "-o", f"{out}/long.mcap"], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
whole = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(f"CMU-GPR folder: {size:.0f} MiB, {sent.get('ingest/gpr', 0)} traces, {sent.get('ingest/imu', 0)} IMU rows")
print(f"ingest stage (streamed): peak RSS {ingest['peak_rss_bytes'] / 2**20:.0f} MiB, {ingest['wall_s']:.2f} s")
print(f"gprflow convert (read whole): peak RSS {whole:.0f} MiB")
PY
