"""The learned registration model's encoder in Python onnxruntime (one intra-op and one
inter-op thread; the model's front end in numpy before the graph), timed on the same submaps as the Rust benchmark
(stages/register/examples/bench_register.rs), and the Rust features checked against it to 1e-5
relative (max |ours - ref| <= 1e-5 max |ref|, per submap). Also times the correlation of one
pair in numpy (tools/train/train.py's batched FFT version, the fastest Python one) for
reference.

usage: bench_register.py generate OUT.f32 [N] [--rows 201] [--cols 200]
       bench_register.py run IN.f32 --model M.onnx --head H.json [--ours OURS.f32]
                         [--iterations N] [--rows 201] [--cols 200] [--resolution-m 0.015]
"""
import argparse
import json
import math
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
RTOL = 1e-5
SEED = 20260


def ground_strip(rows, cols, rng):
    """A GPR-like strip of ground: hyperbolas of buried points, two layers, noise; ``rows x cols``."""
    x = np.arange(cols)[None, :]
    r = np.arange(rows)[:, None].astype(np.float64)
    img = np.zeros((rows, cols))
    for _ in range(cols // 40):
        x0, r0, a = rng.uniform(0, cols), rng.uniform(20, rows - 20), rng.uniform(0.5, 2.0)
        t = np.sqrt(r0 ** 2 + ((x - x0) * 0.6) ** 2)
        img += a * np.exp(-((r - t) ** 2) / 4.0) * np.cos((r - t) * 1.3)
    for depth in (40.0, 120.0):
        wave = depth + 6.0 * np.sin(x / rng.uniform(60, 120) + rng.uniform(0, 6))
        img += 0.6 * np.exp(-((r - wave) ** 2) / 3.0)
    return img + 0.05 * rng.standard_normal(img.shape)


def generate(out, n, rows, cols):
    """``n`` submaps cut from one strip, each 40 columns on from the last (overlapping pairs)."""
    rng = np.random.default_rng(SEED)
    strip = ground_strip(rows, cols + 40 * n, rng)
    subs = np.stack([strip[:, 40 * i:40 * i + cols] for i in range(n)])
    (30.0 * subs + 5.0).astype("<f4").tofile(out)


def timed(fn, iterations, warmup=50):
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(iterations):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    ts = np.asarray(ts)
    return {"median_ms": round(float(np.median(ts)), 4), "p90_ms": round(float(np.percentile(ts, 90)), 4),
            "min_ms": round(float(ts.min()), 4), "iterations": iterations}


def run(args):
    import onnxruntime as ort

    subs = np.fromfile(args.input, dtype="<f4").reshape(-1, args.rows, args.cols)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    sess = ort.InferenceSession(args.model, so, providers=["CPUExecutionProvider"])
    sys.path.insert(0, str(ROOT / "tools/train"))
    import gprdata  # numpy only: the model's front end (SPEC "Front end")

    front = gprdata.front_end_of(sess)
    inputs = [gprdata.apply_front_end(front, gprdata.standardise(s))[None, None] for s in subs]
    feats = [sess.run(None, {"submap": x})[0][0] for x in inputs]
    it = iter(range(10 ** 9))
    run_only = timed(lambda: sess.run(None, {"submap": inputs[next(it) % len(inputs)]}), args.iterations)
    with_std = timed(lambda: sess.run(None, {"submap": gprdata.apply_front_end(
        front, gprdata.standardise(subs[next(it) % len(subs)]))[None, None]}), args.iterations)
    report = {"onnxruntime": ort.__version__, "threads": 1, "features": list(feats[0].shape),
              "front_end": list(front), "encoder_run": run_only, "encoder_standardise_and_run": with_std}
    if args.ours:
        ours = np.fromfile(args.ours, dtype="<f4").reshape((len(subs),) + feats[0].shape)
        err = max(float(np.abs(o - f).max() / max(np.abs(f).max(), 1e-30)) for o, f in zip(ours, feats))
        report["ours_vs_python_rel"] = err
        report["agree_to_1e-5"] = err <= RTOL
    # the correlation of one pair in numpy, for reference (the training side's fastest version)
    try:
        import train
    except ImportError as e:  # train.py needs only numpy at import; say why if it cannot load
        report["numpy_correlation"] = f"not timed: {e}"
    else:
        head = json.loads(pathlib.Path(args.head).read_text())
        ts, d = train.shifts_tried(feats[0].shape[-1], args.resolution_m, head["column_stride"],
                                   head["max_shift_m"], head["min_overlap"])
        pair = (feats[0][None], feats[1][None])
        report["numpy_correlation_batched_fft_one_pair"] = timed(
            lambda: train.peaks(train.correlation_curves_batched(*pair, ts), ts, d), max(args.iterations // 10, 20), 5)
    return report


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate")
    g.add_argument("out")
    g.add_argument("n", type=int, nargs="?", default=8)
    r = sub.add_parser("run")
    r.add_argument("input")
    r.add_argument("--model", required=True)
    r.add_argument("--head", required=True)
    r.add_argument("--ours", help="the Rust encoder's features of every submap (float32 LE)")
    r.add_argument("--iterations", type=int, default=2000)
    r.add_argument("--resolution-m", type=float, default=0.015)
    for p in (g, r):
        p.add_argument("--rows", type=int, default=201)
        p.add_argument("--cols", type=int, default=200)
    args = ap.parse_args()
    if args.cmd == "generate":
        generate(args.out, args.n, args.rows, args.cols)
        return 0
    print(json.dumps(run(args)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
