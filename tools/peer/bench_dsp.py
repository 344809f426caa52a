"""The single-channel trace chain (dewow, zero time, FIR band-pass, SEC gain; the defaults of
gprflow_dsp::chain::ChainParams) in numpy/scipy, timed two ways on the same input as the Rust
benchmark (stages/dsp/examples/bench_dsp.rs):
  per trace   -- one scipy.signal.filtfilt etc. call per trace, as a streaming stage would;
  vectorised  -- each step once over the whole batch (axis=1), the fastest numpy can do.
Checks that both agree and, with --ours, that the Rust output agrees, to 1e-5 relative
(max |ours - ref| <= 1e-5 max |ref|, per trace).

usage: bench_dsp.py generate OUT.i16 [N]                (N seeded traces x 201 int16)
       bench_dsp.py run IN.i16 [--ours OURS.f32] [--out DIR] [--repeat R]
"""
import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import dsp_fixtures as fx  # noqa: E402

RTOL = 1e-5


def per_trace_error(ours, ref):
    """max over traces of max |ours - ref| / max |ref|."""
    scale = np.maximum(np.abs(ref).max(axis=1), 1e-300)
    return float((np.abs(ours - ref).max(axis=1) / scale).max())


def best_of(repeat, fn):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate")
    g.add_argument("out")
    g.add_argument("n", type=int, nargs="?", default=20_000)
    r = sub.add_parser("run")
    r.add_argument("input")
    r.add_argument("--ours", help="the Rust chain's output (float32 LE, row-major)")
    r.add_argument("--out", help="directory for python_per_trace.f64 / python_vectorised.f64")
    r.add_argument("--repeat", type=int, default=3, help="best of R runs (vectorised)")
    args = ap.parse_args()

    if args.cmd == "generate":
        traces = fx.make_traces(args.n, np.random.default_rng(fx.SEED + 1))
        traces.astype("<i2").tofile(args.out)
        return 0

    raw = np.fromfile(args.input, dtype="<i2").reshape(-1, fx.SAMPLES)
    n = raw.shape[0]
    chain = fx.Chain()
    # Per trace: one pass (it is slow; the repeat would only cost time).
    t_trace, results = best_of(1, lambda: [chain.trace(t) for t in raw])
    per_trace = np.stack([y for y, _ in results])
    k_trace = np.array([k for _, k in results])
    t_vec, (vectorised, k_vec) = best_of(args.repeat, lambda: chain.batch(raw))
    report = {
        "traces": n,
        "samples": fx.SAMPLES,
        "per_trace": {"elapsed_s": t_trace, "traces_per_s": n / t_trace},
        "vectorised": {"elapsed_s": t_vec, "traces_per_s": n / t_vec},
        "per_trace_vs_vectorised_rel": per_trace_error(vectorised, per_trace),
        "zero_time_mismatches": int((k_trace != k_vec).sum()),
        "checksum_abs": float(np.abs(per_trace).sum()),
    }
    ok = report["per_trace_vs_vectorised_rel"] <= RTOL and report["zero_time_mismatches"] == 0
    if args.ours:
        ours = np.fromfile(args.ours, dtype="<f4").reshape(n, fx.SAMPLES).astype(np.float64)
        report["ours_vs_python_rel"] = per_trace_error(ours, per_trace)
        ok &= report["ours_vs_python_rel"] <= RTOL
    if args.out:
        out = pathlib.Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        per_trace.astype("<f8").tofile(out / "python_per_trace.f64")
        vectorised.astype("<f8").tofile(out / "python_vectorised.f64")
    report["agree_to_1e-5"] = bool(ok)
    print(json.dumps(report))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
