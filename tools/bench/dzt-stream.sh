#!/usr/bin/env bash
# Memory of reading a long DZT file: the `ingest` stage streams it scan by scan; `gprflow
# convert` reads it whole. The file is the
# committed GSSI_FILE____032.DZT with its scans repeated COPIES times (default 60: 64 MB).
#
# usage: tools/bench/dzt-stream.sh [COPIES (60)]
#   GPRFLOW=path/to/gprflow picks the binary (default: a release build, made here).
# Prints the peak RSS of each, and the file's size.
set -euo pipefail
cd "$(dirname "$0")/../.."
copies=${1:-60}
if [ -z "${GPRFLOW:-}" ]; then
    cargo build -q --release -p gprflow-cli
    GPRFLOW=${CARGO_TARGET_DIR:-target}/release/gprflow
fi
out=out/bench/dzt-stream
mkdir -p "$out"
python3 - "$copies" "$out/long.DZT" << 'PY'
import struct, sys
copies, path = int(sys.argv[1]), sys.argv[2]
b = open("recordings/real-gpr/GSSI_FILE____032.DZT", "rb").read()
channels = struct.unpack_from("<H", b, 52)[0]
field = struct.unpack_from("<H", b, 2)[0]
offset = field if field >= 1024 else 1024 * channels
open(path, "wb").write(b[:offset] + b[offset:] * copies)
PY
cat > "$out/ingest.yaml" << YAML
name: dzt-stream
nodes:
  ingest: { stage: ingest, params: { source: "$out/long.DZT" } }
  dsp: { stage: dsp, inputs: { trace: ingest/gpr }, params: { hold_first_samples: 2 } }
YAML
"$GPRFLOW" launch "$out/ingest.yaml" --report "$out/report.json" --log warn
python3 - "$GPRFLOW" "$out" << 'PY'
import json, os, resource, subprocess, sys
gprflow, out = sys.argv[1], sys.argv[2]
size = os.path.getsize(f"{out}/long.DZT") / 2**20
report = json.load(open(f"{out}/report.json"))
ingest = next(n["report"] for n in report["nodes"] if n["node"] == "ingest")
subprocess.run([gprflow, "convert", f"{out}/long.DZT", "-o", f"{out}/long.mcap"], check=True, stderr=subprocess.DEVNULL)
whole = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(f"DZT file: {size:.0f} MiB, {ingest['sent'][0][1]} traces")
print(f"ingest stage (streamed): peak RSS {ingest['peak_rss_bytes'] / 2**20:.0f} MiB, {ingest['wall_s']:.2f} s")
print(f"gprflow convert (read whole): peak RSS {whole:.0f} MiB")
PY
