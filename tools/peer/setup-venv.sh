#!/usr/bin/env bash
# Create (or reuse) the peer-check virtualenv at <repo>/.venv-peers.
#
# Installs the exact versions pinned in tools/peer/requirements.txt
# (mcap, mcap-ros2-support and their compression deps) from PyPI.
# Idempotent: a stamp file in the venv records the sha256 of
# requirements.txt; when it matches, nothing is done.
#
# Usage: tools/peer/setup-venv.sh      (prints the venv path on the last line)
# Env:   PYTHON=python3.11 to pick the interpreter (default: python3).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="$root/.venv-peers"
reqs="$here/requirements.txt"
stamp="$venv/.peer-requirements.sha256"
python="${PYTHON:-python3}"

want="$(sha256sum "$reqs" | cut -d' ' -f1)"
if [[ -x "$venv/bin/python" && -f "$stamp" && "$(cat "$stamp")" == "$want" ]]; then
    echo "peer venv up to date: $venv"
    exit 0
fi

if [[ ! -x "$venv/bin/python" ]]; then
    echo "creating peer venv: $venv" >&2
    rm -rf "$venv"
    "$python" -m venv "$venv"
fi
rm -f "$stamp"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    --requirement "$reqs"
"$venv/bin/python" -c "import mcap, mcap_ros2.decoder, lz4, zstandard, evo, scipy.signal, pywt, skimage.restoration"
echo "$want" > "$stamp"
echo "peer venv ready: $venv"
