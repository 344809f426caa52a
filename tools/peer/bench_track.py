#!/usr/bin/env python3
"""LGPR registration (Cornick et al. 2015) in numpy: the 5-DOF (x, y, dh, yaw, roll) particle
swarm of eq. 9-10 maximising the eq. 8 correlation between a radar sweep and a gridded prior
map, vectorised over the particles (every particle's correlation at once, the map windows
gathered with fancy indexing), one sweep at a time as a stage would run. It reads a problem
dumped by the Rust side, so the two can be timed side by side and our correlation values
cross-checked. Prints one JSON object.

usage: OMP_NUM_THREADS=1 bench_track.py DUMP [max_sweeps]    (bench: PSO per sweep, timed)
       OMP_NUM_THREADS=1 bench_track.py DUMP --check         (correlation at each pose of poses.f64)

DUMP holds problem.json, index.i32 (ny x nx slot or -1, cell (i, j) at j*nx + i),
columns.f32 (slots x samples), sweeps.f32 (sweeps x channels x samples), seeds.f64 and
truth.f64 (sweeps x 5: x, y, dh, yaw, roll) and, for --check, poses.f64 (m x 5; pose k is
evaluated against sweep k % sweeps).
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

C_M_PER_NS = 0.299792458
SEED = 20150  # fixed; the Rust side's random stream differs anyway
WITHIN_M = 0.05


class Problem:
    """The dumped problem: map, sweeps, search boxes and the PSO parameters."""

    def __init__(self, dump):
        d = pathlib.Path(dump)
        p = json.loads((d / "problem.json").read_text())
        self.nx, self.ny = int(p["nx"]), int(p["ny"])
        self.spacing = float(p["spacing_m"])
        self.x0, self.y0 = (float(v) for v in p["origin_m"])
        self.samples = int(p["samples"])
        self.corr_start, self.corr_len = int(p["corr_start"]), int(p["corr_len"])
        self.dt_ns = float(p["sample_interval_ns"])
        self.channels = int(p["channels"])
        self.offsets = np.asarray(p["offsets_m"], dtype=np.float64)
        self.mount_x = float(p["mount_x_m"])
        self.n_sweeps = int(p["sweeps"])
        self.pso = {k: float(v) for k, v in p["pso"].items()}
        self.particles, self.iterations = int(p["pso"]["particles"]), int(p["pso"]["iterations"])
        self.half = np.asarray(p["half_width"], dtype=np.float64)
        if self.offsets.shape != (self.channels,) or self.half.shape != (5,):
            raise SystemExit("problem.json: offsets_m needs `channels` values, half_width 5")
        if not (0 <= self.corr_start and 0 < self.corr_len
                and self.corr_start + self.corr_len <= self.samples):
            raise SystemExit("problem.json: corr_start + corr_len must lie within samples")

        self.index = np.fromfile(d / "index.i32", dtype="<i4").astype(np.int64)
        if self.index.size != self.nx * self.ny:
            raise SystemExit("index.i32: expected ny*nx values")
        cols = np.fromfile(d / "columns.f32", dtype="<f4")
        if cols.size % self.samples:
            raise SystemExit("columns.f32: size is not a multiple of samples")
        self.columns = cols.reshape(-1, self.samples)
        if self.index.max(initial=-1) >= len(self.columns):
            raise SystemExit("index.i32 names a slot past the end of columns.f32")
        sw = np.fromfile(d / "sweeps.f32", dtype="<f4")
        self.sweeps = sw.reshape(self.n_sweeps, self.channels, self.samples)
        self.seeds = np.fromfile(d / "seeds.f64", dtype="<f8").reshape(self.n_sweeps, 5)
        self.truth = np.fromfile(d / "truth.f64", dtype="<f8").reshape(self.n_sweeps, 5)
        poses = d / "poses.f64"
        self.poses = np.fromfile(poses, dtype="<f8").reshape(-1, 5) if poses.exists() else None

        # The sweep's own window and its energy per channel do not depend on the pose.
        win = slice(self.corr_start, self.corr_start + self.corr_len)
        self.a_win = self.sweeps[:, :, win].astype(np.float64)  # sweeps x channels x L
        self.a_energy = np.einsum("nkl,nkl->nk", self.a_win, self.a_win)  # sweeps x channels
        self.taps = np.arange(self.corr_len, dtype=np.int64)

    def correlation(self, poses, n):
        """Eq. 8 of sweep ``n`` at each row of ``poses`` (P x 5): (correlation, overlap), each P."""
        x, y, dh, yaw, roll = (poses[:, c:c + 1] for c in range(5))  # P x 1 each
        o = self.offsets[None, :]  # 1 x K
        cy, sy = np.cos(yaw), np.sin(yaw)
        wx = x + cy * self.mount_x - sy * o  # P x K
        wy = y + sy * self.mount_x + cy * o
        fi = np.floor((wx - self.x0) / self.spacing + 0.5)
        fj = np.floor((wy - self.y0) / self.spacing + 0.5)
        valid = (fi >= 0) & (fi < self.nx) & (fj >= 0) & (fj < self.ny)  # NaN -> invalid
        cell = np.where(valid, fj, 0).astype(np.int64) * self.nx + np.where(valid, fi, 0).astype(np.int64)
        slot = np.where(valid, self.index[cell], -1)
        valid &= slot >= 0
        slot = np.where(valid, slot, 0)

        dz = dh + o * np.sin(roll)  # P x K
        shift = np.floor(2.0 * dz / C_M_PER_NS / self.dt_ns + 0.5)
        b0 = np.clip(self.corr_start - shift, 0, self.samples - self.corr_len).astype(np.int64)

        b = self.columns[slot[:, :, None], b0[:, :, None] + self.taps].astype(np.float64)  # P x K x L
        ab = np.where(valid, np.einsum("pkl,kl->pk", b, self.a_win[n]), 0.0).sum(axis=1)
        bb = np.where(valid, np.einsum("pkl,pkl->pk", b, b), 0.0).sum(axis=1)
        aa = np.where(valid, self.a_energy[n][None, :], 0.0).sum(axis=1)
        den = aa * bb
        corr = np.where(den > 0, ab / np.sqrt(np.where(den > 0, den, 1.0)), 0.0)
        return corr, valid.sum(axis=1)

    def register(self, n, rng):
        """The eq. 9-10 swarm for sweep ``n`` in the box seeds[n] +- half: (best pose, its correlation)."""
        pso, h, P, iters = self.pso, self.half, self.particles, self.iterations
        c = self.seeds[n]
        lo, hi = c - h, c + h
        p = rng.uniform(lo, hi, size=(P, 5))
        p[0] = c
        v = rng.uniform(-0.2 * h, 0.2 * h, size=(P, 5))
        pbest, pbest_val = p.copy(), np.full(P, -np.inf)
        gbest, gbest_val = c.copy(), -np.inf
        for it in range(iters):
            w = pso["inertia_start"] + (pso["inertia_end"] - pso["inertia_start"]) * it / max(iters - 1, 1)
            val, _ = self.correlation(p, n)
            better = val > pbest_val
            pbest[better] = p[better]
            pbest_val[better] = val[better]
            k = int(np.argmax(pbest_val))
            if pbest_val[k] > gbest_val:
                gbest, gbest_val = pbest[k].copy(), float(pbest_val[k])
            if it < iters - 1:
                r1, r2 = rng.random((P, 5)), rng.random((P, 5))
                v = w * v + pso["cognitive"] * r1 * (pbest - p) + pso["social"] * r2 * (gbest - p)
                np.clip(v, -h, h, out=v)
                p = np.clip(p + v, lo, hi)
        return gbest, gbest_val


def bench(prob, max_sweeps):
    n_run = prob.n_sweeps if max_sweeps is None else max(0, min(max_sweeps, prob.n_sweeps))
    if n_run == 0:
        raise SystemExit("no sweeps to run")
    rng = np.random.default_rng(SEED)
    prob.correlation(prob.seeds[:1], 0)  # warm-up (first-call overheads), untimed
    found, best, times = np.empty((n_run, 5)), np.empty(n_run), np.empty(n_run)
    for n in range(n_run):
        t = time.perf_counter()
        found[n], best[n] = prob.register(n, rng)
        times[n] = time.perf_counter() - t
    err = np.hypot(found[:, 0] - prob.truth[:n_run, 0], found[:, 1] - prob.truth[:n_run, 1])
    return {
        "implementation": "numpy PSO, vectorised over particles",
        "sweeps": n_run, "particles": prob.particles, "iterations": prob.iterations,
        "sweeps_per_s": n_run / float(times.sum()),
        "p50_us": float(np.percentile(times, 50) * 1e6),
        "p99_us": float(np.percentile(times, 99) * 1e6),
        "position_rms_m": float(np.sqrt(np.mean(err ** 2))),
        "mean_correlation": float(best.mean()),
        "found_xy_within_5cm": float(np.mean(err <= WITHIN_M)),
    }


def check(prob):
    if prob.poses is None:
        raise SystemExit("--check needs poses.f64 in the dump")
    m = len(prob.poses)
    corr, overlap = np.zeros(m), np.zeros(m, dtype=np.int64)
    which = np.arange(m) % prob.n_sweeps
    for n in np.unique(which):
        rows = np.nonzero(which == n)[0]
        corr[rows], overlap[rows] = prob.correlation(prob.poses[rows], int(n))
    return {"correlations": [float(v) for v in corr], "overlaps": [int(v) for v in overlap]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dump", help="directory written by the Rust side")
    ap.add_argument("max_sweeps", nargs="?", type=int, default=None,
                    help="bench the first N sweeps (default all)")
    ap.add_argument("--check", action="store_true",
                    help="print the correlation and overlap at every pose of poses.f64")
    args = ap.parse_args()
    prob = Problem(args.dump)
    print(json.dumps(check(prob) if args.check else bench(prob, args.max_sweeps)))


if __name__ == "__main__":
    main()
