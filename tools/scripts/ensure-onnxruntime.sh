#!/usr/bin/env bash
# The ONNX Runtime library the learned registration model runs on (gprflow-register, `ort`
# with load-dynamic): libonnxruntime.so.1.31.1 from the PyPI wheel onnxruntime==1.31.1, put at
# <repo>/.onnxruntime/libonnxruntime.so.1.31.1. Idempotent: when the library is there nothing
# is downloaded. Prints the library's path on the last line.
#
# usage: tools/scripts/ensure-onnxruntime.sh
# env:   PYTHON (default python3), GPRFLOW_ORT_CACHE (where the wheel is kept, default
#        <repo>/.onnxruntime/wheels)
set -euo pipefail

version=1.31.1
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
dest="$root/.onnxruntime"
lib="$dest/libonnxruntime.so.$version"
member="onnxruntime/capi/libonnxruntime.so.$version"
python="${PYTHON:-python3}"
cache="${GPRFLOW_ORT_CACHE:-$dest/wheels}"

if [[ -s "$lib" ]]; then
    echo "$lib"
    exit 0
fi

mkdir -p "$dest" "$cache"
shopt -s nullglob
wheels=("$cache"/onnxruntime-"$version"-*.whl)
if (( ${#wheels[@]} == 0 )); then
    echo "downloading onnxruntime==$version (PyPI wheel) into $cache" >&2
    "$python" -m pip download --quiet --no-deps --only-binary=:all: "onnxruntime==$version" -d "$cache" >&2
    wheels=("$cache"/onnxruntime-"$version"-*.whl)
fi
if (( ${#wheels[@]} == 0 )); then
    echo "ensure-onnxruntime: no onnxruntime-$version wheel in $cache after pip download" >&2
    exit 1
fi

# Extract the one library, atomically (a half-written file must never pass for the library).
"$python" - "${wheels[0]}" "$member" "$lib" <<'PY'
import os, sys, zipfile
wheel, member, lib = sys.argv[1:]
with zipfile.ZipFile(wheel) as z:
    try:
        data = z.read(member)
    except KeyError:
        sys.exit(f"ensure-onnxruntime: {wheel} has no {member}")
tmp = lib + ".part"
with open(tmp, "wb") as f:
    f.write(data)
os.chmod(tmp, 0o755)
os.replace(tmp, lib)
PY
echo "$lib"
