"""Golden files for stages/dsp/tests/dsp_peer.rs, computed by the reference implementations:
scipy.signal (firwin, filtfilt), scipy.ndimage (uniform_filter1d, gaussian_filter1d),
PyWavelets and scikit-image (denoise_wavelet).

Inputs are synthetic but CMU-GPR-like and seeded: 201-sample traces at 0.2 ns (int16 counts:
a DC offset, a slow decaying "wow", an inverted 500 MHz Ricker direct wave, a few reflections,
noise) and a 201 x 200 B-scan with hyperbolas, layers and noise scaled into [-1, 1].

usage: .venv-peers/bin/python tools/peer/dsp_fixtures.py            (writes the fixtures)
       .venv-peers/bin/python tools/peer/dsp_fixtures.py --verify   (exit 1 if they changed)

The chain helpers (dewow, zero_time_index, ...) are imported by tools/peer/bench_dsp.py.
"""
import argparse
import json
import pathlib
import sys

import numpy as np
import pywt
import scipy.ndimage as ndi
import scipy.signal as sig
from skimage.restoration import denoise_wavelet
from skimage.restoration._denoise import _bayes_thresh, _sigma_est_dwt

ROOT = pathlib.Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "stages/dsp/tests/fixtures"
SEED = 20_240_607
SAMPLES = 201
DT_NS = 0.2
FC_HZ = 500e6
VERIFY_RTOL = 1e-9
# CMU-GPR dataset tools' per-site SEC gain settings (a, b, threshold on the sample index).
SITES = {
    "nsh_highbay": (0.015, 0.01, 100),
    "nsh_b_level": (0.06, 0.5, 80),
    "nrec": (0.03, 0.0, 110),
    "gates_garage": (0.03, 0.7, 80),
}
# Defaults of gprflow_dsp::chain::ChainParams.
CHAIN = {
    "dewow": {"window_periods": 1.0},
    "zero_time": {"threshold": 0.5},
    "bandpass": {"taps": 31, "low_cutoff_ratio": 0.5, "high_cutoff_ratio": 2.0},
    "sec_gain": {"a": 0.03, "b": 0.7, "threshold": 80},
}


# ---------------------------------------------------------------------------------------------
# Synthetic inputs

def ricker(t_ns, fc_hz):
    a = (np.pi * fc_hz * t_ns * 1e-9) ** 2
    return (1.0 - 2.0 * a) * np.exp(-a)


def make_traces(n, rng, samples=SAMPLES, dt_ns=DT_NS, fc_hz=FC_HZ):
    """n raw traces (int16 counts), shape (n, samples)."""
    t = np.arange(samples) * dt_ns
    t0 = rng.uniform(4.0, 8.0, (n, 1))
    amp = rng.uniform(12_000, 20_000, (n, 1))
    x = -amp * ricker(t - t0, fc_hz)
    for _ in range(3):
        delay = rng.uniform(5.0, 30.0, (n, 1))
        r = rng.uniform(0.05, 0.3, (n, 1)) * rng.choice([-1.0, 1.0], (n, 1))
        x += amp * r * np.exp(-delay / 25.0) * ricker(t - t0 - delay, fc_hz)
    x += rng.uniform(-3000, 3000, (n, 1))  # DC offset
    x += rng.uniform(2000, 5000, (n, 1)) * np.exp(-t / rng.uniform(8.0, 15.0, (n, 1)))  # wow
    x += 500.0 * np.sin(2 * np.pi * 30e6 * t * 1e-9 + rng.uniform(0, 2 * np.pi, (n, 1)))
    x += rng.normal(0.0, 50.0, x.shape)
    return np.clip(np.rint(x), -32768, 32767).astype(np.int16)


def make_image(rng, rows=201, cols=200):
    """A B-scan with two layers, three hyperbolas and noise, as int16 counts (image = q / 32767)."""
    r = np.arange(rows)[:, None].astype(float)
    c = np.arange(cols)[None, :].astype(float)
    img = np.zeros((rows, cols))
    for depth, a in [(40.0, 0.5), (120.0, -0.3)]:
        img += a * ricker((r - depth - 3.0 * np.sin(c / 30.0)) * 0.2, FC_HZ)
    for apex_c, apex_r, width, a in [(50.0, 60.0, 12.0, 0.8), (130.0, 90.0, 18.0, -0.6), (170.0, 150.0, 9.0, 0.5)]:
        hyper = np.sqrt(apex_r**2 + ((c - apex_c) * apex_r / width) ** 2)
        img += a * ricker((r - hyper) * 0.2, FC_HZ) * np.exp(-np.abs(c - apex_c) / 60.0)
    img += rng.normal(0.0, 0.08, img.shape)
    img /= np.abs(img).max()
    return np.rint(img * 32767).astype(np.int16)


def image_from_counts(q):
    """The f32 image both sides use: q / 32767 rounded to float32 (held in float64)."""
    return (q.astype(np.float64) / 32767.0).astype(np.float32).astype(np.float64)


# ---------------------------------------------------------------------------------------------
# The trace chain as the Rust crate defines it, on numpy/scipy

def dewow_window(window_periods, dt_ns=DT_NS, fc_hz=FC_HZ):
    raw = window_periods * 1e9 / (fc_hz * dt_ns)
    return 2 * int(np.floor(raw / 2.0)) + 1


def dewow(x, window, axis=-1):
    """DC subtraction, then minus the running mean (uniform_filter1d, mode 'nearest')."""
    x = x - x.mean(axis=axis, keepdims=True)
    return x - ndi.uniform_filter1d(x, window, axis=axis, mode="nearest")


def zero_time_index(x, threshold):
    """First run of samples below -threshold * max|x|; the index of its minimum (or None)."""
    peak = np.abs(x).max()
    if not np.isfinite(peak) or peak == 0:
        return None
    below = x < -threshold * peak
    if not below.any():
        return None
    start = int(np.argmax(below))
    after = np.flatnonzero(~below[start:])
    end = start + int(after[0]) if after.size else x.size
    return start + int(np.argmin(x[start:end]))


def zero_time_indices(x, threshold):
    """zero_time_index over the rows of a batch; -1 where none."""
    n, m = x.shape
    peak = np.abs(x).max(axis=1, keepdims=True)
    below = x < -threshold * peak
    has = below.any(axis=1) & (peak[:, 0] > 0)
    start = np.argmax(below, axis=1)
    k = np.arange(m)[None, :]
    past = ~below & (k > start[:, None])
    end = np.where(past.any(axis=1), np.argmax(past, axis=1), m)
    inside = (k >= start[:, None]) & (k < end[:, None])
    best = np.argmin(np.where(inside, x, np.inf), axis=1)
    return np.where(has, best, -1)


def shift(x, k):
    y = np.zeros_like(x)
    y[: x.size - k] = x[k:]
    return y


def shift_rows(x, ks):
    n, m = x.shape
    ks = np.maximum(ks, 0)
    idx = np.arange(m)[None, :] + ks[:, None]
    return np.where(idx < m, np.take_along_axis(x, np.minimum(idx, m - 1), axis=1), 0.0)


def bandpass_taps(taps, low_ratio, high_ratio, dt_ns=DT_NS, fc_hz=FC_HZ):
    return sig.firwin(taps, [low_ratio * fc_hz, high_ratio * fc_hz], pass_zero=False,
                      window="triang", fs=1e9 / dt_ns)


def sec_gain(samples, a, b, threshold):
    k = np.minimum(np.arange(samples), threshold).astype(np.float64)
    return np.exp(a * k) * k**b


class Chain:
    """Precomputed window, taps and gain of the default chain."""

    def __init__(self, params=CHAIN, samples=SAMPLES):
        self.window = dewow_window(params["dewow"]["window_periods"])
        self.threshold = params["zero_time"]["threshold"]
        bp = params["bandpass"]
        self.b = bandpass_taps(bp["taps"], bp["low_cutoff_ratio"], bp["high_cutoff_ratio"])
        g = params["sec_gain"]
        self.gain = sec_gain(samples, g["a"], g["b"], g["threshold"])

    def trace(self, x):
        """One trace, as a streaming stage would: returns (output, zero-time index or -1)."""
        y = dewow(np.asarray(x, dtype=np.float64), self.window)
        k = zero_time_index(y, self.threshold)
        if k is not None:
            y = shift(y, k)
        y = sig.filtfilt(self.b, [1.0], y)
        return y * self.gain, -1 if k is None else k

    def batch(self, x):
        """All traces at once (axis 1)."""
        y = dewow(np.asarray(x, dtype=np.float64), self.window, axis=1)
        ks = zero_time_indices(y, self.threshold)
        y = shift_rows(y, ks)
        y = sig.filtfilt(self.b, [1.0], y, axis=1)
        return y * self.gain[None, :], ks


# ---------------------------------------------------------------------------------------------
# Fixtures

def f32(a):
    """Floats as the shortest repr of their float32 rounding (what the Rust side holds)."""
    return [float(str(np.float32(v))) for v in np.asarray(a, dtype=np.float64).ravel()]


def f64(a):
    return [float(v) for v in np.asarray(a, dtype=np.float64).ravel()]


def grid(n, step):
    """Every step-th index plus the two first and two last (edge handling lives there)."""
    return sorted(set(range(0, n, step)) | {0, 1, n - 2, n - 1})


def trace_fixture(rng):
    raw = make_traces(8, rng)
    x = raw.astype(np.float64)
    out = {"samples": SAMPLES, "sample_interval_ns": DT_NS, "center_frequency_hz": FC_HZ,
           "traces": [int(v) for v in raw.ravel()]}
    out["dewow"] = []
    for periods in (1.0, 2.5):
        w = dewow_window(periods)
        out["dewow"].append({"window_periods": periods, "window_samples": w,
                             "expected": f32(dewow(x, w, axis=1))})
    dw = dewow(x, dewow_window(1.0), axis=1).astype(np.float32).astype(np.float64)
    out["dewowed"] = f32(dw)
    ks = [zero_time_index(t, 0.5) for t in dw]
    out["zero_time"] = {"threshold": 0.5, "index": [-1 if k is None else k for k in ks],
                        "expected": f32(np.stack([t if k is None else shift(t, k) for t, k in zip(dw, ks)]))}
    out["bandpass"] = []
    for taps, lo, hi in ((31, 0.5, 2.0), (21, 0.3, 1.5), (65, 0.6, 3.0)):
        b = bandpass_taps(taps, lo, hi)
        out["bandpass"].append({"taps": taps, "low_cutoff_ratio": lo, "high_cutoff_ratio": hi,
                                "firwin": f64(b),
                                "expected": f32(sig.filtfilt(b, [1.0], dw, axis=1))})
    out["sec_gain"] = [{"site": s, "a": a, "b": b, "threshold": th, "expected": f32(sec_gain(SAMPLES, a, b, th))}
                       for s, (a, b, th) in SITES.items()]
    chain = Chain()
    ys, zs = zip(*(chain.trace(t) for t in x))
    out["chain"] = {"params": CHAIN, "zero_time_index": [int(z) for z in zs], "expected": f32(np.stack(ys))}
    return out


def image_fixtures(rng):
    q = make_image(rng)
    img = image_from_counts(q)
    rows, cols = img.shape
    rs, cs = grid(rows, 3), grid(cols, 3)
    pick = np.ix_(rs, cs)
    inp = {"rows": rows, "cols": cols, "counts": [int(v) for v in q.ravel()]}
    wav = {"rows": rows, "cols": cols, "grid_rows": rs, "grid_cols": cs, "cases": []}
    for name in ("haar", "db1", "db2", "db3", "db4"):
        den = denoise_wavelet(img, wavelet=name, mode="soft", method="BayesShrink", rescale_sigma=True)
        levels = max(pywt.dwtn_max_level(img.shape, name) - 3, 1)
        coeffs = pywt.wavedecn(img, name, mode="symmetric", level=levels)
        sigma = _sigma_est_dwt(coeffs[-1]["dd"], distribution="Gaussian")
        thresholds = [[_bayes_thresh(d[k], sigma**2) for k in ("ad", "da", "dd")] for d in coeffs[1:]]
        wav["cases"].append({"wavelet": name, "levels": levels, "sigma": float(sigma),
                             "thresholds": [f64(t) for t in thresholds],
                             "expected": f32(den[pick])})
    gau = {"rows": rows, "cols": cols, "grid_rows": rs, "grid_cols": cs, "cases": []}
    for sigma_track, sigma_depth in ((1.0, None), (2.5, 1.5)):
        g = ndi.gaussian_filter1d(img, sigma_track, axis=1, mode="reflect", truncate=4.0)
        if sigma_depth is not None:
            g = ndi.gaussian_filter1d(g.astype(np.float32).astype(np.float64), sigma_depth, axis=0,
                                      mode="reflect", truncate=4.0)
        gau["cases"].append({"sigma_along_track_px": sigma_track, "sigma_depth_px": sigma_depth,
                             "truncate": 4.0, "expected": f32(g[pick])})
    return inp, wav, gau


def build():
    rng = np.random.default_rng(SEED)
    trace = trace_fixture(rng)
    inp, wav, gau = image_fixtures(rng)
    return {"dsp_trace.json": trace, "dsp_image_input.json": inp, "dsp_wavelet.json": wav,
            "dsp_gaussian.json": gau}


def compare(a, b, where):
    """None if a and b agree (floats to VERIFY_RTOL of the largest magnitude in their list)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            err = compare(a[k], b[k], f"{where}.{k}")
            if err:
                return err
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{where}: length {len(a)} != {len(b)}"
        if a and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in a + b):
            x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
            scale = max(np.abs(y).max(), 1e-300)
            worst = np.abs(x - y).max() / scale
            return None if worst <= VERIFY_RTOL else f"{where}: differs by {worst:.3g} relative"
        for i, (u, v) in enumerate(zip(a, b)):
            err = compare(u, v, f"{where}[{i}]")
            if err:
                return err
        return None
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        ok = abs(a - b) <= VERIFY_RTOL * max(abs(a), abs(b))
        return None if ok else f"{where}: {a} != {b}"
    return None if a == b else f"{where}: {a!r} != {b!r}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--verify", action="store_true", help="compare with the committed fixtures")
    args = ap.parse_args()
    files = build()
    if args.verify:
        bad = 0
        for name, data in files.items():
            path = FIXTURES / name
            if not path.exists():
                print(f"{path}: missing", file=sys.stderr)
                bad += 1
                continue
            err = compare(json.loads(json.dumps(data)), json.loads(path.read_text()), name)
            if err:
                print(f"{path}: {err}", file=sys.stderr)
                bad += 1
        sys.exit(1 if bad else 0)
    FIXTURES.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        text = json.dumps(data, separators=(",", ":"))
        (FIXTURES / name).write_text(text + "\n")
        print(f"{name}: {len(text) / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
