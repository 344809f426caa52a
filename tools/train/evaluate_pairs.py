#!/usr/bin/env python3
"""Engineered baseline and learned model on every cross-pass pair of simulated runs (a tool).

Table 4.1 of seed 000 compares the models on validation pairs. ``gprflow experiment tools/experiments/tables.yaml`` does
that through the localisation graph (the register stage's loop candidates, its gates); this
does it on all ground-truth pairs of a run instead, gates off and on, to see where each model
fails. Pairs follow the training rules (tools/train/gprdata.py: anchors within 0.25 m
cross-track and 15 degrees, |shift| <= 1.5 m), only between different legs; the engineered
baseline is eq. 4.2-4.3 at full column resolution, the learned model is SPEC.md with the given
encoder and head. Evaluation worlds may be measured here; they are never trained on.

    .venv-train/bin/python tools/train/evaluate_pairs.py basement:by_hand factory_floor:by_hand \\
        --binary target/release/gprflow --cache-dir /tmp/evaluate
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gprdata  # noqa: E402
import train  # noqa: E402

# the register stage's engineered gate (graphs/localize.yaml: min_score default)
ENGINEERED_MIN_SCORE = 0.3


def rmse_cm(err_m):
    return float(np.sqrt(np.mean(np.square(err_m)))) * 100 if len(err_m) else float("nan")


def without_eigenimages(pixels, count):
    """Each submap minus its ``count`` largest singular components (eigenimage filtering: a
    horizontal band whose strength varies along the track is one such component)."""
    if count == 0:
        return pixels
    out = np.empty_like(pixels)
    for i, x in enumerate(pixels.astype(np.float64)):
        u, s, vt = np.linalg.svd(x, full_matrices=False)
        out[i] = x - (u[:, :count] * s[:count]) @ vt[:count]
    return out


def evaluate(args, head, scenario, run):
    r = gprdata.load_run(args.binary, args.cache_dir, scenario, run, args.spacing_m, wheel_scale=args.wheel_scale)
    pairs = gprdata.truth_pairs([r], np.random.default_rng(args.seed), per_submap=3, apart_per_submap=1)
    cross = (pairs.kind == "truth") & pairs.cross_pass
    apart = pairs.kind == "apart"
    images = [np.stack([gprdata.standardise(x) for x in without_eigenimages(r.pixels, args.remove_eigenimages)])]
    resolution_m = float(r.resolution_m[0])
    eng, eng_peak = train.engineered_baseline(images, pairs, cross, resolution_m)

    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sess = ort.InferenceSession(args.model, so)
    feats = np.stack([gprdata.encode(sess, im) for im in images[0]])
    sel = cross | apart
    k = head["channels"]
    v = np.zeros((len(pairs), 2 * k))
    v[sel] = train.correlation_vectors([feats], pairs.select(sel), resolution_m, head["column_stride"])
    # the register stage's stretch search: the query's rows stretched by each factor, the one
    # with the highest mean channel peak decides
    sub = pairs.select(sel)
    queries = np.unique(sub.query_index)
    for factor in gprdata.stretch_factors(args.stretch_step, args.stretch_steps):
        if factor == 1.0:
            continue
        stretched = feats.copy()
        for i in queries:
            stretched[i] = gprdata.encode(sess, gprdata.standardise(
                gprdata.stretch_rows(without_eigenimages(r.pixels[i:i + 1], args.remove_eigenimages)[0], factor)))
        on_stretched = gprdata.Pairs(np.zeros(len(sub), dtype=np.int64), sub.ref_index, np.ones(len(sub), dtype=np.int64),
                                     sub.query_index, sub.target_m, sub.kind, sub.cross_pass)
        w = train.correlation_vectors([feats, stretched], on_stretched, resolution_m, head["column_stride"])
        better = w[:, k:].mean(-1) > v[sel][:, k:].mean(-1)
        vs = v[sel]
        vs[better] = w[better]
        v[sel] = vs
    learned = train.apply_head(head, v)
    shares, _, registered = train.registration_decision(head, v, learned)
    target = pairs.target_m
    gate = cross & (eng_peak >= ENGINEERED_MIN_SCORE)
    return {
        "world": f"{scenario}/{run}", "pairs": int(cross.sum()),
        "engineered_rmse_cm": rmse_cm(eng[cross] - target[cross]),
        "engineered_over_10cm": float(np.mean(np.abs(eng[cross] - target[cross]) > 0.1)),
        "engineered_gated_pass": float(gate.sum() / max(1, cross.sum())),
        "engineered_gated_rmse_cm": rmse_cm(eng[gate] - target[gate]),
        "learned_rmse_cm": rmse_cm(learned[cross] - target[cross]),
        "learned_over_10cm": float(np.mean(np.abs(learned[cross] - target[cross]) > 0.1)),
        "learned_shared_pass": float((cross & shares).sum() / max(1, cross.sum())),
        "learned_shared_rmse_cm": rmse_cm(learned[cross & shares] - target[cross & shares]),
        "learned_registered_pass": float((cross & registered).sum() / max(1, cross.sum())),
        "learned_registered_rmse_cm": rmse_cm(learned[cross & registered] - target[cross & registered]),
        "learned_registered_max_cm": float(np.abs(learned[cross & registered] - target[cross & registered]).max() * 100)
        if (cross & registered).any() else float("nan"),
        "apart_rejected": float((~registered[apart]).mean()) if apart.any() else float("nan"),
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="SCENARIO:RUN, e.g. basement:by_hand (tools/sim/scenarios/SCENARIO.yaml)")
    p.add_argument("--binary", default="target/release/gprflow")
    p.add_argument("--cache-dir", default="/tmp/evaluate")
    p.add_argument("--spacing-m", type=float, default=0.1)
    p.add_argument("--model", default=os.path.join(train.MODELS_DIR, train.ONNX_NAME))
    p.add_argument("--head", default=os.path.join(train.MODELS_DIR, "ground_encoding.head.json"))
    p.add_argument("--wheel-scale", type=float, default=None,
                   help="the wheel calibration the submaps are laid on (default: the one the head was trained "
                        "with, its training block; 1 if it names none)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--remove-eigenimages", type=int, default=0, metavar="N",
                   help="take each submap's N largest singular components out first (both models; a test of "
                        "what the banding costs, not part of the pipeline)")
    p.add_argument("--stretch-steps", type=int, default=0, metavar="N",
                   help="the learned model with the register stage's travel-time stretch search: the query also "
                        "at 1 +- k * STEP, k = 1..N (graphs/localize.yaml: 1; default 0, off)")
    p.add_argument("--stretch-step", type=float, default=0.015, metavar="STEP")
    p.add_argument("--json", action="store_true", help="one JSON object per run instead of a table")
    args = p.parse_args()
    head = json.load(open(args.head))
    train.check_encoder(head, args.head, args.model)
    if args.wheel_scale is None:
        args.wheel_scale = float(head.get("training", {}).get("submaps", {}).get("wheel_scale", 1.0))
    os.makedirs(args.cache_dir, exist_ok=True)
    rows = []
    for spec in args.runs:
        scenario, _, run = spec.partition(":")
        rows.append(evaluate(args, head, scenario, run or "by_hand"))
        if args.json:
            print(json.dumps(rows[-1]), flush=True)
    if args.json:
        return
    print("| run | pairs | engineered | engineered >10 cm | engineered, peak >= 0.3 | learned | learned >10 cm "
          "| learned, shared | learned, shared and agreeing (max) | non-overlapping rejected |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['world']} | {r['pairs']} | {r['engineered_rmse_cm']:.1f} | {100 * r['engineered_over_10cm']:.0f} % "
              f"| {r['engineered_gated_rmse_cm']:.1f} ({100 * r['engineered_gated_pass']:.0f} %) "
              f"| {r['learned_rmse_cm']:.1f} | {100 * r['learned_over_10cm']:.0f} % "
              f"| {r['learned_shared_rmse_cm']:.1f} ({100 * r['learned_shared_pass']:.0f} %) "
              f"| {r['learned_registered_rmse_cm']:.1f} ({100 * r['learned_registered_pass']:.0f} %, "
              f"{r['learned_registered_max_cm']:.1f}) "
              f"| {100 * r['apart_rejected']:.0f} % |")


if __name__ == "__main__":
    main()
