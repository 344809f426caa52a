"""How far the learned model's registrations were from the estimate when they arrived, to
choose the estimator's registration gate (`registration_gate_m`, `registration_gate_growth_mps`).

Each registration the estimate stage took or gated (its debug log names the two stamps, the
measured along-track distance and the residual: the estimate's distance minus the measured
one) is checked against the truth, and timed against the newest earlier query the estimate
had taken (or the run's start): the gap the gate widens over. Prints, over all the logs, how
many registrations were right (within --tolerance of the truth) and wrong, and for each
growth rate the smallest base under which every right registration fell,
`max(|residual| - rate * gap)`.

    python3 tools/scripts/residuals.py run.log truth.txt [run2.log truth2.txt ...]

Needs numpy (the peers' venv has it: .venv-peers/bin/python).
"""
import argparse
import os
import re
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from refusals import rotate, truth_at  # noqa: E402

TAKEN = re.compile(
    r"registration (?P<what>added|gated).*reference_stamp_ns=(?P<r>\d+) query_stamp_ns=(?P<q>\d+) "
    r"along_track_m=(?P<along>\S+) residual_m=(?P<res>\S+)")
RATES = (0.0, 0.005, 0.01, 0.02)


def read(log, truth, tolerance):
    """``(right, |residual|, gap s, gated)`` per registration of ``log``."""
    rows = []
    with open(log, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = TAKEN.search(line)
            if m:
                rows.append((m["what"] == "gated", int(m["r"]), int(m["q"]), float(m["along"]), float(m["res"])))
    if not rows:
        return np.zeros((0, 4))
    tum = np.loadtxt(truth, ndmin=2)
    ref_s = np.array([r[1] for r in rows]) * 1e-9
    qry_s = np.array([r[2] for r in rows]) * 1e-9
    pr, qr = truth_at(tum, ref_s)
    pq, _ = truth_at(tum, qry_s)
    along = np.sum((pq - pr) * rotate(qr, np.tile([1.0, 0, 0], (len(rows), 1))), axis=1)
    right = np.abs(np.array([r[3] for r in rows]) - along) <= tolerance
    gated = np.array([r[0] for r in rows])
    gaps = np.empty(len(rows))
    taken = tum[0, 0]
    for k in range(len(rows)):
        # the newest query the estimate took before this one's (queries of one batch arrive
        # together and are solved with together)
        earlier = [qry_s[i] for i in range(k) if not gated[i] and qry_s[i] < qry_s[k]]
        gaps[k] = qry_s[k] - max(earlier, default=taken)
    return np.c_[right, np.abs([r[4] for r in rows]), gaps, gated]


def main():
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("pairs", nargs="+", help="LOG TRUTH.tum, ... (LOG: the launch's output with "
                   "gprflow_estimate=debug; TRUTH: gprflow convert --to tum)")
    a.add_argument("--tolerance", type=float, default=0.1, help="a right registration's largest error, m")
    args = a.parse_args()
    if len(args.pairs) % 2:
        sys.exit("residuals.py: give a truth file after each log")
    runs = [read(args.pairs[i], args.pairs[i + 1], args.tolerance) for i in range(0, len(args.pairs), 2)]
    rows = np.concatenate(runs)
    if not len(rows):
        sys.exit("residuals.py: no registration in the logs (were they run with gprflow_estimate=debug?)")
    right = rows[:, 0] == 1
    print(f"{len(rows)} registrations in {len(runs)} runs: {int(right.sum())} right, {int((~right).sum())} wrong "
          f"(> {100 * args.tolerance:g} cm), {int(rows[:, 3].sum())} gated")
    if (~right).any():
        print("wrong ones, |residual| m: " + ", ".join(f"{r:.3f}" for r in np.sort(rows[~right, 1])[::-1]))
    print("| growth (m/s) | smallest base under which every right registration fell (m) |")
    print("|---|---|")
    for rate in RATES:
        print(f"| {rate:g} | {np.max(rows[right, 1] - rate * rows[right, 2]):.3f} |")


if __name__ == "__main__":
    main()
