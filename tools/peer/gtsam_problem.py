"""The synthetic factor-graph problem of the estimation peer check and benchmark, written in the
export format that tools/peer/gtsam_solve.py (GTSAM 4.3) and stages/estimate/src/problem.rs read,
so that GTSAM and gprflow solve the very same file. numpy only.

A vehicle drives a looping, slightly hilly 3-D path (an oval of mean radius R whose size also
breathes slowly, so successive laps do not coincide and loop closures are not identities),
heading along its velocity with a little roll and pitch. States at 10 Hz; a 200 Hz IMU with
white noise and random-walk biases; wheel odometry between consecutive states; a loop closure
from state i - lap to i every 50 states; with --lines, the forward distance to the nearest of
four walls (x, y = +-(R + 10)) per state.

Records, in this order (all whitespace separated):
  PARAMS N imu_per_state imu_dt g acc_nd gyr_nd acc_rw gyr_rw odo_sig[6] lc_sig[6]
  GT i x y z qx qy qz qw vx vy vz                 for every state
  ODO i-1 i x y z qx qy qz qw, then IMU i ax ay az gx gy gz (imu_per_state of them), i = 1..N-1
  LC j i x y z qx qy qz qw
  LINEMAP k rho theta rho0 theta0                 (--lines) true wall and a noisy initial guess
  LINE i k z                                      (--lines) sigma 0.05 m
Sigmas are [rotation rad x3, translation m x3]; IMU samples are body-frame specific force
(gravity reads +g on z at rest) and angular rate.

usage: python tools/peer/gtsam_problem.py N [--lap L] [--radius R] [--seed S] [--lines] -o FILE
"""
import argparse
import math

import numpy as np

IMU_PER_STATE = 20
IMU_DT = 0.005                       # 200 Hz
STATE_DT = IMU_PER_STATE * IMU_DT    # 10 Hz, computed as the readers do
G = 9.81
GRAVITY = np.array([0.0, 0.0, -G])
LC_EVERY = 50
# Noise: the figures the committed fixture and the GTSAM solver have always used.
ACC_ND, GYR_ND = 0.01, 0.001         # white noise densities, per sqrt(Hz)
ACC_RW, GYR_RW = 1e-3, 1e-4          # bias random walks, per sqrt(s)
ODO_SIG = [0.005] * 3 + [0.02] * 3   # per 0.1 s step
LC_SIG = [0.01] * 3 + [0.05] * 3
LINE_SIG = 0.05
# Biases the solver has to find (its prior on them is 0.1 around zero).
ACC_BIAS0 = np.array([0.04, -0.06, 0.05])
GYR_BIAS0 = np.array([0.0025, -0.0015, 0.002])


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_so3(w):
    th = np.linalg.norm(w)
    K = hat(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + math.sin(th) / th * K + (1 - math.cos(th)) / th**2 * K @ K


def log_so3(R):
    c = min(1.0, max(-1.0, (np.trace(R) - 1) / 2))
    th = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # Angles here are small (at most a few degrees per step); no need for the near-pi branch.
    return 0.5 * v if th < 1e-8 else th / (2 * math.sin(th)) * v


def quat(R):
    """(qx, qy, qz, qw) of a rotation matrix, branch on the largest component for accuracy."""
    t = np.trace(R)
    if t > 0:
        s = 2 * math.sqrt(1 + t)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        k = int(np.argmax(np.diag(R)))
        i, j = (k + 1) % 3, (k + 2) % 3
        s = 2 * math.sqrt(1 + R[k, k] - R[i, i] - R[j, j])
        q = [0.0] * 4
        q[k], q[i], q[j] = s / 4, (R[i, k] + R[k, i]) / s, (R[j, k] + R[k, j]) / s
        q[3] = (R[j, i] - R[i, j]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


class Path:
    """Position, velocity (analytic derivative) and attitude of the vehicle at time t."""

    def __init__(self, radius, lap_states):
        self.R = radius
        self.W = 2 * math.pi / (lap_states * STATE_DT)   # lap rate, rad/s

    def pv(self, t):
        R, W = self.R, self.W
        phi = W * t
        # Oval (2 phi term) that breathes slowly (0.045 rad/s, not a multiple of the lap rate).
        r = R + 0.10 * R * math.sin(2 * phi) + 0.12 * R * math.sin(0.045 * t)
        dr = 0.20 * R * W * math.cos(2 * phi) + 0.12 * R * 0.045 * math.cos(0.045 * t)
        z = 0.35 * math.sin(2 * math.pi * t / 13.0) + 0.25 * math.sin(phi + 0.5)
        dz = 0.35 * 2 * math.pi / 13.0 * math.cos(2 * math.pi * t / 13.0) + 0.25 * W * math.cos(phi + 0.5)
        c, s = math.cos(phi), math.sin(phi)
        p = np.array([r * c, r * s, z])
        v = np.array([dr * c - r * W * s, dr * s + r * W * c, dz])
        return p, v

    def rot(self, t):
        """Nose along the velocity (yaw and pitch follow the path), plus a small sway."""
        _, v = self.pv(t)
        yaw = math.atan2(v[1], v[0])
        pitch = -math.atan2(v[2], math.hypot(v[0], v[1])) + 0.015 * math.sin(0.8 * t)
        roll = 0.025 * math.sin(1.1 * t + 0.3)
        cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                                  math.cos(roll), math.sin(roll))
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        return Rz @ Ry @ Rx


def true_imu(path, t):
    """The sample over [t, t + dt] as a strapdown IMU reports it (increments over the interval):
    rate = Log(R(t)^T R(t+dt)) / dt, specific force = R(t)^T (dv/dt - gravity). The integrator of
    GTSAM and of gprflow (constant sample over dt, body frame at the start of the interval)
    then lands exactly on the path's attitude and velocity at every sample instant; position
    follows by the trapezoid rule (error ~ dt^2)."""
    R0, R1 = path.rot(t), path.rot(t + IMU_DT)
    v0, v1 = path.pv(t)[1], path.pv(t + IMU_DT)[1]
    w = log_so3(R0.T @ R1) / IMU_DT
    f = R0.T @ ((v1 - v0) / IMU_DT - GRAVITY)
    return f, w


def noisy_between(Ta, Tb, sig, rng):
    """Relative pose a^-1 b, perturbed on the right by N(0, sig) in rotation and translation."""
    (Ra, ta), (Rb, tb) = Ta, Tb
    R, t = Ra.T @ Rb, Ra.T @ (tb - ta)
    n = rng.normal(0.0, 1.0, 6) * sig
    return R @ exp_so3(n[:3]), t + R @ n[3:]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("N", type=int, help="number of states (10 Hz)")
    ap.add_argument("--lap", type=int, default=500, help="states per lap (default 500)")
    ap.add_argument("--radius", type=float, default=15.0, help="mean loop radius, m (default 15)")
    ap.add_argument("--seed", type=int, default=1, help="seed of all the noise (default 1)")
    ap.add_argument("--lines", action="store_true", help="also write the wall map and LINE records")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    if a.N < 2 or a.lap < 1 or a.radius <= 0:
        ap.error("need N >= 2, lap >= 1, radius > 0")
    n = a.N
    # One stream per kind of noise, so that e.g. --lines leaves the IMU and odometry unchanged.
    imu_rng, odo_rng, lc_rng, line_rng = (np.random.default_rng(s)
                                          for s in np.random.SeedSequence(a.seed).spawn(4))
    path = Path(a.radius, a.lap)

    gt = []  # (R, p, v) per state
    for i in range(n):
        p, v = path.pv(i * STATE_DT)
        gt.append((path.rot(i * STATE_DT), p, v))

    imu = np.zeros((n, IMU_PER_STATE, 6))
    ba, bg = ACC_BIAS0.copy(), GYR_BIAS0.copy()
    for i in range(1, n):
        for k in range(IMU_PER_STATE):
            f, w = true_imu(path, (i - 1) * STATE_DT + k * IMU_DT)
            ba += imu_rng.normal(0.0, ACC_RW * math.sqrt(IMU_DT), 3)
            bg += imu_rng.normal(0.0, GYR_RW * math.sqrt(IMU_DT), 3)
            imu[i, k, :3] = f + ba + imu_rng.normal(0.0, ACC_ND / math.sqrt(IMU_DT), 3)
            imu[i, k, 3:] = w + bg + imu_rng.normal(0.0, GYR_ND / math.sqrt(IMU_DT), 3)

    pose = [(R, p) for R, p, _ in gt]
    odo = [None] + [noisy_between(pose[i - 1], pose[i], ODO_SIG, odo_rng) for i in range(1, n)]
    lcs = [(i - a.lap, i, noisy_between(pose[i - a.lap], pose[i], LC_SIG, lc_rng))
           for i in range(a.lap, n, LC_EVERY)]

    def pstr(R, t):
        return " ".join(f"{x:.12g}" for x in (*t, *quat(R)))

    def nums(xs):
        return " ".join(f"{x:.12g}" for x in xs)

    with open(a.output, "w") as out:
        w = out.write
        w(f"PARAMS {n} {IMU_PER_STATE} {IMU_DT} {G} {ACC_ND} {GYR_ND} {ACC_RW} {GYR_RW} "
          + " ".join(map(str, ODO_SIG + LC_SIG)) + "\n")
        for i, (R, p, v) in enumerate(gt):
            w(f"GT {i} {pstr(R, p)} {nums(v)}\n")
        for i in range(1, n):
            w(f"ODO {i - 1} {i} {pstr(*odo[i])}\n")
            for s in imu[i]:
                w(f"IMU {i} {nums(s)}\n")
        for j, i, m in lcs:
            w(f"LC {j} {i} {pstr(*m)}\n")
        if a.lines:
            # Walls around the loop; each state sees the one it faces most squarely.
            walls = [(a.radius + 10.0, k * math.pi / 2) for k in range(4)]
            for k, (rho, th) in enumerate(walls):
                w(f"LINEMAP {k} {rho!r} {th!r} {nums([rho + line_rng.normal(0, 0.1), th + line_rng.normal(0, 0.01)])}\n")
            for i, (R, p, _) in enumerate(gt):
                psi = math.atan2(R[1, 0], R[0, 0])
                k = max(range(4), key=lambda k: math.cos(psi - walls[k][1]))
                rho, th = walls[k]
                d = (rho - (p[0] * math.cos(th) + p[1] * math.sin(th))) / math.cos(psi - th)
                w(f"LINE {i} {k} {d + line_rng.normal(0, LINE_SIG):.12g}\n")


if __name__ == "__main__":
    main()
