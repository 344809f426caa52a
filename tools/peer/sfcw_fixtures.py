#!/usr/bin/env python3
"""Golden files of the LGPR's SFCW chain (seed 001 §2.1.3, eq. 2-7), computed with numpy/scipy.

Inputs are synthesised the way tools/sim/src/lgpr.rs builds a sweep: per channel
S_ant = H(f, t) G_k(f) (C_k(f) + P(f) S_scene(f)) + noise, S_cal = H(f, t) K(f) + noise, and a
factory calibration G_k C_k over K (anechoic chamber, no ground). The scene: the ground
bounce, three layer interfaces, two point scatterers passing under the array, two internal
reflections. Everything is seeded; inputs are rounded to float32 as the sweep message carries
them, and both sides start from those float32 values.

Files (stages/lgpr/tests/fixtures/):
  sfcw_chain.json   3 sweeps of 3 channels x 51 tones (100 MHz + m 6 MHz), variable spacing;
                    every stage: self-calibrated (eq. 2), factory-calibrated (eq. 4),
                    delayed+windowed, time domain, IIR output (eq. 5-7), final output; and
                    the final output without a factory calibration.
  sfcw_window.json  scipy.signal.windows.chebwin for odd and even lengths, several
                    attenuations.
  sfcw_iir.json     the IIR high-pass alone: constant spacing (scipy.signal.lfilter) and
                    variable spacing (a numpy loop).

usage: sfcw_fixtures.py            write the files
       sfcw_fixtures.py --verify   regenerate in memory, compare with the committed files to
                                   1e-9 relative (max |new - file| <= 1e-9 max |file|), exit 1
                                   naming file and key on a mismatch
"""

import json
import math
import sys
from pathlib import Path

import warnings

import numpy as np
from scipy.signal import lfilter
from scipy.signal.windows import chebwin

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "stages/lgpr/tests/fixtures"
VERIFY_RTOL = 1e-9
SIGNIFICANT = 12  # digits kept for float64 values

C_M_PER_NS = 0.299792458
F0_HZ, DF_HZ, TONES = 100e6, 6e6, 51
HEIGHT_M = 0.1524
PARAMS = {
    "delay_ns": 8.0,
    "window_attenuation_db": 45.0,
    "time_samples": 1024,
    "keep_samples": 369,
    "iir_distance_m": 5.0,
    "range_gain": {"spreading_exponent": 1.0, "reference_ns": 2.0, "attenuation_db_per_ns": 0.4},
}


# ---------------------------------------------------------------- inputs (as the simulator)


def f32(a):
    return np.asarray(a, dtype=np.float32)


def interleave(z):
    """complex (..., bins) -> float32 (re, im) pairs, flattened channel-major."""
    z = np.asarray(z)
    return f32(np.stack([z.real, z.imag], axis=-1).reshape(-1))


def deinterleave(v, channels, bins):
    v = np.asarray(v, dtype=np.float64).reshape(channels, bins, 2)
    return v[..., 0] + 1j * v[..., 1]


def synthesise(channels, sweeps, distances_m, seed):
    rng = np.random.default_rng(seed)
    f_ghz = (F0_HZ + np.arange(TONES) * DF_HZ) * 1e-9
    f_lo, f_hi = f_ghz[0], f_ghz[-1]
    span = f_hi - f_lo
    mismatch, noise, level = 0.1, 1e-4, 0.3
    gain, coupling = [], []
    for _ in range(channels):
        g = 1.0 + mismatch * rng.normal()
        phase0 = rng.uniform(-0.5, 0.5)
        slope = 0.3 * rng.normal()
        c = 1.0 + mismatch * rng.normal()
        ripple_ns = rng.uniform(2.0, 4.0)
        gain.append(g * np.exp(1j * (phase0 + slope * (f_ghz - f_lo) / span)))
        coupling.append(c * (1.0 + 0.05 * np.cos(2 * np.pi * f_ghz * ripple_ns)))
    gain, coupling = np.array(gain), np.array(coupling)
    band = 0.3 + 0.7 * np.sin(np.pi * (f_ghz - f_lo) / span)
    cal_path = np.exp(-2j * np.pi * f_ghz * 1.5)

    # the road: ground bounce, interfaces (depth m, eps above/below), two point scatterers
    t_air = 2 * HEIGHT_M / C_M_PER_NS
    n0 = math.sqrt(5.0)
    interfaces = [(0.12, 5.0, 6.0), (0.45, 6.0, 9.0), (1.4, 9.0, 12.0)]
    points = [(0.25, 0.0, 0.8, 0.4), (0.6, 0.3, 1.3, 0.3)]  # x m, y m, depth m, strength
    spacing_m = 0.127
    x_m = np.concatenate([[0.0], np.cumsum(distances_m[1:])])

    fac_values = interleave(gain * coupling)
    fac_cal = interleave(cal_path)
    values, cals = [], []
    for i in range(sweeps):
        t_s = i / 126.0
        drift = np.deg2rad(2.0) * t_s / 60.0
        chain = (1 + 0.02 * np.sin(2 * np.pi * t_s / 300.0)) * np.exp(1j * drift * f_ghz / (0.5 * (f_lo + f_hi)))
        sweep = []
        for k in range(channels):
            y_m = (k - (channels - 1) / 2) * spacing_m
            echoes = [(t_air, (1 - n0) / (1 + n0) / (2 * HEIGHT_M))]
            t_soil, depth_prev = 0.0, 0.0
            for depth, eps_a, eps_b in interfaces:
                t_soil += 2 * (depth - depth_prev) * math.sqrt(eps_a) / C_M_PER_NS
                depth_prev = depth
                r = (math.sqrt(eps_a) - math.sqrt(eps_b)) / (math.sqrt(eps_a) + math.sqrt(eps_b))
                echoes.append((t_air + t_soil, r * 10 ** (-2 * 4.0 * depth / 20) / (depth + HEIGHT_M)))
            for px, py, depth, strength in points:
                rng_m = math.sqrt((px - x_m[i]) ** 2 + (py - y_m) ** 2 + depth**2)
                t = t_air + 2 * rng_m * 3.0 / C_M_PER_NS
                echoes.append((t, strength * 10 ** (-2 * 4.0 * rng_m / 20) / (rng_m + HEIGHT_M) ** 2))
            scene = sum(level * a * np.exp(-2j * np.pi * f_ghz * d) for d, a in echoes)
            scene = scene + sum(a * np.exp(-2j * np.pi * f_ghz * d) for d, a in [(0.6, 0.08), (2.4, 0.04)])
            z = noise * (rng.normal(size=TONES) + 1j * rng.normal(size=TONES))
            sweep.append(chain * gain[k] * (coupling[k] + band * scene) + z)
        values.append(interleave(np.array(sweep)))
        z = noise * (rng.normal(size=TONES) + 1j * rng.normal(size=TONES))
        cals.append(interleave(chain * cal_path + z))
    return fac_values, fac_cal, values, cals


# ---------------------------------------------------------------- the chain, step by step


def tone_frequencies_hz(bins):
    return F0_HZ + np.arange(bins) * DF_HZ


def delayed_windowed(spectrum, params):
    """Delay exp(-j 2 pi f tau) and the Chebyshev window scaled to unit sum."""
    bins = spectrum.shape[-1]
    w = chebwin(bins, params["window_attenuation_db"], sym=True)
    w = w / w.sum()
    delay = np.exp(-2j * np.pi * tone_frequencies_hz(bins) * params["delay_ns"] * 1e-9)
    return spectrum * delay * w


def to_time(spectrum, params):
    """x_n = Re(exp(j 2 pi f0 n dt) N ifft_N(S zero-padded)[n]), dt = 1 / (N df)."""
    n_fft, keep = params["time_samples"], params["keep_samples"]
    y = np.fft.ifft(spectrum, n=n_fft, axis=-1) * n_fft
    n = np.arange(n_fft)
    ramp = np.exp(2j * np.pi * F0_HZ * n / (n_fft * DF_HZ))
    return (y * ramp).real[..., :keep]


def to_time_direct(spectrum, params):
    """The same sum taken tone by tone (cross-check of to_time)."""
    n_fft, keep = params["time_samples"], params["keep_samples"]
    t_s = np.arange(keep) / (n_fft * DF_HZ)
    f = tone_frequencies_hz(spectrum.shape[-1])
    return (spectrum @ np.exp(2j * np.pi * np.outer(f, t_s))).real


def high_pass(sweeps, distances_m, d_iir):
    """Eq. 5-7, M_0 = C_0, one sweep at a time (any spacing)."""
    out, mean = [], None
    for c, d in zip(sweeps, distances_m):
        if mean is None:
            mean = c.copy()
        else:
            beta = 2.0 ** (-d / d_iir)
            mean = beta * mean + (1 - beta) * c
        out.append(c - mean)
    return np.array(out)


def high_pass_lfilter(sweeps, distance_m, d_iir):
    """Eq. 5-7 with constant spacing as a first-order IIR along the sweep axis: y = C - M,
    M = lfilter([1 - beta], [1, -beta], C) started at M_{-1} = C_0 (so M_0 = C_0)."""
    beta = 2.0 ** (-distance_m / d_iir)
    zi = beta * sweeps[0:1]
    mean, _ = lfilter([1 - beta], [1, -beta], sweeps, axis=0, zi=zi)
    return sweeps - mean


def range_gain(params):
    g = params["range_gain"]
    dt_ns = 1e9 / (params["time_samples"] * DF_HZ)
    t = np.arange(params["keep_samples"]) * dt_ns - params["delay_ns"]
    spreading = (np.maximum(t, g["reference_ns"]) / g["reference_ns"]) ** g["spreading_exponent"]
    return spreading * 10 ** (g["attenuation_db_per_ns"] * np.maximum(t, 0) / 20)


# ---------------------------------------------------------------- fixtures


def rounded(a):
    return [float(f"{v:.{SIGNIFICANT}g}") for v in np.asarray(a, dtype=np.float64).reshape(-1)]


def f32_list(a):
    return [float(np.format_float_scientific(v, unique=True)) for v in f32(a).reshape(-1)]


def pairs(z):
    """complex -> interleaved (re, im) float64 list, channel-major."""
    z = np.asarray(z)
    return rounded(np.stack([z.real, z.imag], axis=-1))


def chain_fixture():
    channels, sweeps = 3, 3
    distances = np.array([0.0, 0.106, 0.35])
    fac_values, fac_cal, values, cals = synthesise(channels, sweeps, distances, seed=1)
    bins = TONES
    factory = deinterleave(fac_values, channels, bins) / deinterleave(fac_cal, 1, bins)
    stages = {k: [] for k in ["self_calibrated", "factory_calibrated", "windowed", "time", "high_passed", "out", "out_self_only"]}
    times, times_self = [], []
    for v, c in zip(values, cals):
        s_hat = deinterleave(v, channels, bins) / deinterleave(c, 1, bins)  # eq. 2
        s_hathat = s_hat / factory - 1  # eq. 3-4
        windowed = delayed_windowed(s_hathat, PARAMS)
        t = to_time(windowed, PARAMS)
        check = to_time_direct(windowed, PARAMS)
        assert np.max(np.abs(t - check)) <= 1e-10 * np.max(np.abs(check)), "ifft vs direct sum"
        stages["self_calibrated"].append(pairs(s_hat))
        stages["factory_calibrated"].append(pairs(s_hathat))
        stages["windowed"].append(pairs(windowed))
        stages["time"].append(rounded(t))
        times.append(t)
        times_self.append(to_time(delayed_windowed(s_hat, PARAMS), PARAMS))
    gain = range_gain(PARAMS)
    hp = high_pass(np.array(times), distances, PARAMS["iir_distance_m"])
    hp_self = high_pass(np.array(times_self), distances, PARAMS["iir_distance_m"])
    for h, hs in zip(hp, hp_self):
        stages["high_passed"].append(rounded(h))
        stages["out"].append(f32_list(h * gain))
        stages["out_self_only"].append(f32_list(hs * gain))
    return {
        "about": "tools/peer/sfcw_fixtures.py (numpy/scipy) - do not edit by hand",
        "params": PARAMS,
        "channels": channels,
        "bins": bins,
        "start_frequency_hz": F0_HZ,
        "frequency_step_hz": DF_HZ,
        "sample_interval_ns": 1e9 / (PARAMS["time_samples"] * DF_HZ),
        "factory_values": f32_list(fac_values),
        "factory_calibration": f32_list(fac_cal),
        "range_gain": rounded(gain),
        "sweeps": [
            {
                "values": f32_list(v),
                "calibration": f32_list(c),
                "distance_since_last_m": float(d),
                **{k: stages[k][i] for k in stages},
            }
            for i, (v, c, d) in enumerate(zip(values, cals, distances))
        ],
    }


def window_fixture():
    warnings.filterwarnings("ignore", message="This window is not suitable")
    cases = []
    for at in [45.0, 30.0, 80.0]:
        for m in [1, 2, 3, 4, 5, 8, 11, 50, 51, 64, 101]:
            cases.append({"len": m, "attenuation_db": at, "taps": rounded(chebwin(m, at, sym=True))})
    return {"about": "scipy.signal.windows.chebwin(len, attenuation_db, sym=True)", "cases": cases}


def iir_fixture():
    rng = np.random.default_rng(7)
    sweeps, samples, d_iir = 60, 8, 5.0
    ground = rng.normal(size=samples)
    c = ground + 0.05 * rng.normal(size=(sweeps, samples))
    c[20:25, 3] += 1.0  # a feature a few sweeps long
    spacing = 0.1
    constant = high_pass_lfilter(c, spacing, d_iir)
    loop = high_pass(c, np.full(sweeps, spacing), d_iir)
    assert np.max(np.abs(constant - loop)) <= 1e-12, "lfilter vs loop"
    distances = rng.uniform(0.0, 0.4, size=sweeps)
    distances[[5, 6]] = 0.0  # stopped
    variable = high_pass(c, distances, d_iir)
    return {
        "about": "eq. 5-7, M_0 = C_0: scipy.signal.lfilter (constant spacing), numpy loop (variable)",
        "iir_distance_m": d_iir,
        "samples": samples,
        "input": rounded(c),
        "constant": {"distance_since_last_m": spacing, "output": rounded(constant)},
        "variable": {"distances_since_last_m": rounded(distances), "output": rounded(variable)},
    }


FILES = {"sfcw_chain.json": chain_fixture, "sfcw_window.json": window_fixture, "sfcw_iir.json": iir_fixture}


def compare(new, old, key):
    """First key (dotted path) where new and old differ, or None."""
    if isinstance(old, dict):
        if not isinstance(new, dict) or new.keys() != old.keys():
            return key or "(top)"
        return next((k for n in old if (k := compare(new[n], old[n], f"{key}.{n}" if key else n))), None)
    if isinstance(old, list) and old and isinstance(old[0], (dict, list)):
        if not isinstance(new, list) or len(new) != len(old):
            return key
        return next((k for i, (a, b) in enumerate(zip(new, old)) if (k := compare(a, b, f"{key}[{i}]"))), None)
    if isinstance(old, list):
        a, b = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
        if a.shape != b.shape or np.max(np.abs(a - b), initial=0.0) > VERIFY_RTOL * np.max(np.abs(b), initial=0.0):
            return key
        return None
    if isinstance(old, float) and isinstance(new, (int, float)):
        return None if abs(new - old) <= VERIFY_RTOL * abs(old) else key
    return None if new == old else key


def main():
    verify = "--verify" in sys.argv[1:]
    failed = False
    for name, make in FILES.items():
        data = make()
        path = FIXTURES / name
        if verify:
            bad = compare(data, json.loads(path.read_text()), "")
            if bad:
                print(f"{path.relative_to(ROOT)}: {bad} differs from the regenerated values")
                failed = True
            else:
                print(f"{path.relative_to(ROOT)}: ok")
        else:
            path.write_text(json.dumps(data, separators=(",", ":")) + "\n")
            print(f"wrote {path.relative_to(ROOT)} ({path.stat().st_size // 1024} KiB)")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
