#!/usr/bin/env bash
# Peer check of the estimation library against GTSAM 4.3.
#
# Installs gtsam==4.3.0 and numpy into .venv-gtsam, generates a small problem with our own
# generator (tools/peer/gtsam_problem.py: N=300 states, a 100-state lap so that it has loop
# closures; line records too, so that the fixture holds every record type), solves that same file
# with GTSAM (tools/peer/gtsam_solve.py) and writes the fixture the Rust test compares against:
#   stages/estimate/tests/fixtures/peer_n300.txt         the problem
#   stages/estimate/tests/fixtures/peer_n300.gtsam.json  GTSAM's batch error and ATE on it
# then runs that test (cargo nextest run -p gprflow-estimate --test peer_gtsam).
#
# usage: tools/peer/gtsam_check.sh         regenerate the fixture and run the test
#        tools/peer/gtsam_check.sh --verify  (CI) re-solve the committed problem with GTSAM and check
#                                            that GTSAM still gives the committed figures (the Rust
#                                            test runs in the workspace's nextest run)
set -euo pipefail
cd "$(dirname "$0")/../.."
venv=.venv-gtsam
fixtures=stages/estimate/tests/fixtures
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/python" -c 'import gtsam, numpy' 2>/dev/null || "$venv/bin/pip" install -q gtsam==4.3.0 numpy
mkdir -p "$fixtures"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
if [ "${1:-}" = "--verify" ]; then
    "$venv/bin/python" tools/peer/gtsam_solve.py "$fixtures/peer_n300.txt" > "$tmp/fresh.json"
    "$venv/bin/python" - "$tmp/fresh.json" "$fixtures/peer_n300.gtsam.json" <<'PY'
import json, sys
fresh, committed = (json.load(open(p)) for p in sys.argv[1:3])
for k in ("initial_error", "batch_error", "batch_ate_rmse_m"):
    if abs(fresh[k] - committed[k]) > 1e-9 * abs(committed[k]):
        sys.exit(f"GTSAM now gives {k} = {fresh[k]}, the fixture says {committed[k]}")
print("GTSAM reproduces the committed fixture:", {k: fresh[k] for k in ("batch_error", "batch_ate_rmse_m")})
PY
    exit 0
fi
# Deterministic (fixed seed): the same file comes out until the generator changes.
"$venv/bin/python" tools/peer/gtsam_problem.py 300 --lap 100 --lines -o "$fixtures/peer_n300.txt"
"$venv/bin/python" tools/peer/gtsam_solve.py "$fixtures/peer_n300.txt" > "$fixtures/peer_n300.gtsam.json"
cat "$fixtures/peer_n300.gtsam.json"
cargo nextest run -p gprflow-estimate --test peer_gtsam
