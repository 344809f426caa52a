#!/usr/bin/env bash
# The estimation benchmark, side by side in one run: GTSAM 4.3 and gprflow solve the same
# problem file, made by our generator (tools/peer/gtsam_problem.py: N states at 10 Hz, 200 Hz IMU,
# wheel odometry, a loop closure every 50 states, one wall-distance record per state).
#   1. GTSAM: batch Levenberg-Marquardt, then iSAM2 (QR) one update per state, as fast as it goes;
#   2. gprflow: batch LM, then the incremental smoother one update per state, as fast as it goes;
#   3. gprflow: the same with the older fixed-lag smoother (window plus background re-solves);
#   4. gprflow: batch LM with one known-line factor per state (the cost of line factors);
#   5. gprflow: batch LM with its linearisation split between two threads (reported apart: the
#      benchmark's batch figure is single-threaded).
# Further arguments go to the problem generator (--seed S, --lap L, --radius R): problems
# other than the default one, on which the smoother's thresholds were chosen.
# Results: out/bench-estimate/*.json.
#
# usage: tools/peer/bench_estimate.sh [N (2000)] [generator options]
set -euo pipefail
cd "$(dirname "$0")/../.."
n=${1:-2000}
shift || true
venv=.venv-gtsam
out=out/bench-estimate
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/python" -c 'import gtsam, numpy' 2>/dev/null || "$venv/bin/pip" install -q gtsam==4.3.0 numpy
mkdir -p "$out"
problem="$out/p$n.txt"
# Made afresh each run (about 2 s at N=2000, fixed seed), so a file left by an older generator
# is never benchmarked by mistake.
"$venv/bin/python" tools/peer/gtsam_problem.py "$n" --lines "$@" -o "$problem"
cargo build --release -p gprflow-cli
gprflow=./target/release/gprflow
echo "== GTSAM 4.3: batch LM and iSAM2"
"$venv/bin/python" tools/peer/gtsam_solve.py "$problem" --isam2 | tee "$out/gtsam.json"
echo "== gprflow: batch LM and the incremental smoother, unpaced"
"$gprflow" bench estimate "$problem" --json | tee "$out/ours.json"
echo "== gprflow: the fixed-lag smoother, unpaced"
"$gprflow" bench estimate "$problem" --smoother fixed-lag --json | tee "$out/ours-fixed-lag.json"
echo "== gprflow: batch LM with one known-line factor per state"
"$gprflow" bench estimate "$problem" --lines known --batch-only --json | tee "$out/ours-lines.json"
echo "== gprflow: batch LM, linearising on two threads"
"$gprflow" bench estimate "$problem" --batch-only --threads 2 --json | tee "$out/ours-threads2.json"
