#!/usr/bin/env python3
"""The SFCW chain in numpy, vectorised over the channels of a sweep, one sweep at a time (as a
stage would run): the same sweeps, parameters and steps as stages/lgpr/examples/bench_sfcw.rs.
Prints one JSON object.

usage: bench_sfcw.py [sweeps (5000)]
"""

import json
import sys
import time

import numpy as np
from scipy.signal.windows import chebwin

CHANNELS, TONES, F0_HZ, DF_HZ = 11, 51, 100e6, 6e6
N, KEEP, DELAY_NS, D_IIR_M = 1024, 369, 8.0, 5.0
DISTINCT = 64
WARM_UP = 4 * DISTINCT
CHECKSUM_SWEEPS = 1000  # the same in bench_sfcw.rs


def sweep(i):
    f_ghz = (F0_HZ + np.arange(TONES) * DF_HZ) * 1e-9
    delay_ns = 10.0 + 0.05 * i + 0.3 * np.arange(CHANNELS)[:, None]
    z = 1.0 + 0.1 * np.exp(-2j * np.pi * f_ghz * delay_ns)
    values = np.stack([z.real, z.imag], axis=-1).astype(np.float32).reshape(-1)
    c = np.exp(-2j * np.pi * f_ghz * 1.5)
    cal = np.stack([c.real, c.imag], axis=-1).astype(np.float32).reshape(-1)
    return values, cal


def tones(v, channels):
    v = v.astype(np.float64).reshape(channels, TONES, 2)
    return v[..., 0] + 1j * v[..., 1]


def main():
    sweeps = int(sys.argv[1]) if len(sys.argv) > 1 else 5000
    fac_v, fac_c = sweep(0)
    factory = tones(fac_v, CHANNELS) / tones(fac_c, 1)
    f_hz = F0_HZ + np.arange(TONES) * DF_HZ
    w = chebwin(TONES, 45.0)
    weights = w / w.sum() * np.exp(-2j * np.pi * f_hz * DELAY_NS * 1e-9)
    dt_ns = 1e9 / (N * DF_HZ)
    ramp = np.exp(2j * np.pi * F0_HZ * np.arange(KEEP) * dt_ns * 1e-9)
    t = np.arange(KEEP) * dt_ns - DELAY_NS
    gain = np.maximum(t, 2.0) / 2.0 * 10 ** (0.4 * np.maximum(t, 0) / 20)
    beta = 2.0 ** (-0.1 / D_IIR_M)
    inputs = [sweep(i) for i in range(1, DISTINCT + 1)]
    mean = None

    def process(values, cal):
        nonlocal mean
        s = (tones(values, CHANNELS) / tones(cal, 1) / factory - 1) * weights
        c = (np.fft.ifft(s, n=N, axis=1)[:, :KEEP] * N * ramp).real
        if mean is None:
            mean = c.copy()
        else:
            mean = beta * mean + (1 - beta) * c
        return ((c - mean) * gain).astype(np.float32)

    for k in range(WARM_UP):
        process(*inputs[k % DISTINCT])
    start = time.perf_counter()
    checksum = 0.0
    for k in range(sweeps):
        out = process(*inputs[k % DISTINCT])
        if k < CHECKSUM_SWEEPS:
            checksum += float(out.reshape(-1)[out.size // 2])
    seconds = time.perf_counter() - start
    print(json.dumps({
        "implementation": f"numpy {np.__version__} (vectorised per sweep, f64)",
        "channels": CHANNELS, "tones": TONES, "time_samples": N, "out_samples": KEEP,
        "sweeps": sweeps, "seconds": seconds, "sweeps_per_s": sweeps / seconds,
        "ns_per_sweep": seconds * 1e9 / sweeps, "realtime_factor_126hz": sweeps / seconds / 126.0,
        "checksum": checksum,
    }))


if __name__ == "__main__":
    main()
