#!/usr/bin/env python3
"""Were the learned model's refusals right? Each pair the register stage refused (its debug
log names the two anchors' stamps, the shift the model found, and why it refused) against the
ground truth's along-track offset between the two anchors, as `gprflow eval` measures a
registration: the share of refused pairs whose shift was within --tolerance of the truth, per
reason and binned by the anchors' across-track offset and heading difference.

    gprflow --log info,gprflow_register=debug launch graphs/localize.yaml \\
        --set recording=run.mcap --set method=learned --set association=truth > run.log 2>&1
    gprflow convert run.mcap --to tum --topic /truth/pose -o truth.txt
    python3 tools/scripts/refusals.py run.log truth.txt

Needs numpy (the peers' venv has it: .venv-peers/bin/python).
"""
import argparse
import re
import sys

import numpy as np

REFUSAL = re.compile(
    r"not registered: (?P<why>\w+) reference=\d+ query=\d+ reference_stamp_ns=(?P<r>\d+) "
    r"query_stamp_ns=(?P<q>\d+) shift_m=(?P<shift>\S+)")


def rotate(q, v):
    """``v`` rotated by the unit quaternions ``q`` (x, y, z, w), row by row."""
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def truth_at(tum, stamps_s):
    """Positions (interpolated) and orientations (nearest earlier sample) at ``stamps_s``."""
    t = tum[:, 0]
    if np.any(stamps_s < t[0]) or np.any(stamps_s > t[-1]):
        sys.exit("refusals.py: a refused pair's stamp lies outside the truth's time span")
    p = np.stack([np.interp(stamps_s, t, tum[:, k]) for k in (1, 2, 3)], axis=1)
    q = tum[np.clip(np.searchsorted(t, stamps_s, side="right") - 1, 0, len(t) - 1), 4:8]
    return p, q / np.linalg.norm(q, axis=1, keepdims=True)


def main():
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("log", help="the launch's output with gprflow_register=debug")
    a.add_argument("truth", help="the truth as a TUM file (gprflow convert --to tum)")
    a.add_argument("--tolerance", type=float, default=0.05, help="m")
    args = a.parse_args()
    rows = []
    with open(args.log, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = REFUSAL.search(line)
            if m:
                rows.append((m["why"], int(m["r"]) * 1e-9, int(m["q"]) * 1e-9, float(m["shift"])))
    if not rows:
        sys.exit(f"refusals.py: {args.log}: no refused pair (was the log run with gprflow_register=debug?)")
    why = np.array([r[0] for r in rows])
    tum = np.loadtxt(args.truth, ndmin=2)
    pr, qr = truth_at(tum, np.array([r[1] for r in rows]))
    pq, qq = truth_at(tum, np.array([r[2] for r in rows]))
    d = pq - pr
    fwd, left = rotate(qr, np.tile([1.0, 0, 0], (len(rows), 1))), rotate(qr, np.tile([0, 1.0, 0], (len(rows), 1)))
    along, across = np.sum(d * fwd, axis=1), np.sum(d * left, axis=1)
    fq = rotate(qq, np.tile([1.0, 0, 0], (len(rows), 1)))
    heading = np.degrees(np.abs(np.arctan2(fwd[:, 0] * fq[:, 1] - fwd[:, 1] * fq[:, 0], np.sum(fwd * fq, axis=1))))
    right = np.abs(np.array([r[3] for r in rows]) - along) <= args.tolerance

    def line(label, sel):
        n = int(sel.sum())
        share = f"{100 * right[sel].mean():.0f} %" if n else "-"
        print(f"| {label} | {n} | {share} |")

    print(f"Refused pairs whose shift was within {100 * args.tolerance:g} cm of the truth\n")
    print("| refused pairs | n | within |")
    print("|---|---|---|")
    line("all", np.ones(len(rows), bool))
    for w in sorted(set(why)):
        line(w, why == w)
    for lo, hi in [(0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, np.inf)]:
        line(f"across-track offset {lo:g}-{hi:g} m", (np.abs(across) >= lo) & (np.abs(across) < hi))
    for lo, hi in [(0, 2), (2, 4), (4, 8), (8, np.inf)]:
        line(f"heading difference {lo:g}-{hi:g} deg", (heading >= lo) & (heading < hi))


if __name__ == "__main__":
    main()
