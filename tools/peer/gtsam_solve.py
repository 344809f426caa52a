"""Solves a problem file written by tools/peer/gtsam_problem.py with GTSAM 4.3, reading the
file (not re-simulating), so that GTSAM and `gprflow bench estimate` solve the same graph:
CombinedImuFactor preintegrated at zero bias, odometry BetweenFactorPose3, Huber(1.345) loop
closures, the format's priors on state 0 (pose 1e-3, velocity 0.01, bias 0.1), batch
Levenberg-Marquardt from the dead-reckoning guess, and optionally iSAM2 one state at a time.
Prints one JSON object.

usage: .venv-gtsam/bin/python tools/peer/gtsam_solve.py problem.txt [--isam2]   (no line factors)
"""
import argparse
import json
import math
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

ap = argparse.ArgumentParser()
ap.add_argument("problem")
ap.add_argument("--isam2", action="store_true", help="also run iSAM2 (QR), one update per state")
args = ap.parse_args()

gt, odo, imu, lcs = {}, {}, {}, []


def pose(v):
    x, y, z, qx, qy, qz, qw = map(float, v)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.array([x, y, z]))


with open(args.problem) as f:
    for line in f:
        t = line.split()
        if not t:
            continue
        if t[0] == "PARAMS":
            n, per = int(t[1]), int(t[2])
            imu_dt, g, acc_nd, gyr_nd, acc_rw, gyr_rw = map(float, t[3:9])
            odo_sig = np.array(list(map(float, t[9:15])))
            lc_sig = np.array(list(map(float, t[15:21])))
        elif t[0] == "GT":
            gt[int(t[1])] = (pose(t[2:9]), np.array(list(map(float, t[9:12]))))
        elif t[0] == "ODO":
            odo[int(t[2])] = pose(t[3:10])
        elif t[0] == "IMU":
            imu.setdefault(int(t[1]), []).append(np.array(list(map(float, t[2:8]))))
        elif t[0] == "LC":
            lcs.append((int(t[1]), int(t[2]), pose(t[3:10])))

params = gtsam.PreintegrationCombinedParams.MakeSharedU(g)
params.setAccelerometerCovariance(np.eye(3) * acc_nd**2)
params.setGyroscopeCovariance(np.eye(3) * gyr_nd**2)
params.setIntegrationCovariance(np.eye(3) * 1e-8)
params.setBiasAccCovariance(np.eye(3) * acc_rw**2)
params.setBiasOmegaCovariance(np.eye(3) * gyr_rw**2)
zero = gtsam.imuBias.ConstantBias()
odo_noise = gtsam.noiseModel.Diagonal.Sigmas(odo_sig)
lc_noise = gtsam.noiseModel.Robust.Create(
    gtsam.noiseModel.mEstimator.Huber.Create(1.345), gtsam.noiseModel.Diagonal.Sigmas(lc_sig))
state_dt = imu_dt * per


def factors_of(i, bias_hat):
    fg = gtsam.NonlinearFactorGraph()
    if i == 0:
        fg.add(gtsam.PriorFactorPose3(X(0), gt[0][0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
        fg.add(gtsam.PriorFactorVector(V(0), gt[0][1], gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
        fg.add(gtsam.PriorFactorConstantBias(B(0), zero, gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
        return fg, None
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias_hat)
    for s in imu[i]:
        pim.integrateMeasurement(s[:3], s[3:], imu_dt)
    fg.add(gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i), pim))
    fg.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), odo[i], odo_noise))
    for j, k, m in lcs:
        if k == i:
            fg.add(gtsam.BetweenFactorPose3(X(j), X(i), m, lc_noise))
    return fg, pim


graph = gtsam.NonlinearFactorGraph()
for i in range(n):
    graph.push_back(factors_of(i, zero)[0])
p = [gt[0][0]]
for i in range(1, n):
    p.append(p[-1].compose(odo[i]))
init = gtsam.Values()
for i in range(n):
    a, b = (i, i + 1) if i + 1 < n else (i - 1, i)
    init.insert(X(i), p[i])
    init.insert(V(i), (p[b].translation() - p[a].translation()) / state_dt)
    init.insert(B(i), zero)


def ate(values):
    e = np.array([values.atPose3(X(i)).translation() - gt[i][0].translation() for i in range(n)])
    d = np.linalg.norm(e, axis=1)
    return math.sqrt((d**2).mean()), d.max()


lmp = gtsam.LevenbergMarquardtParams()
lmp.setMaxIterations(100)
lmp.setRelativeErrorTol(1e-6)
lmp.setAbsoluteErrorTol(1e-6)
t0 = time.perf_counter()
opt = gtsam.LevenbergMarquardtOptimizer(graph, init, lmp)
res = opt.optimize()
t_lm = time.perf_counter() - t0
out = {
    "gtsam": gtsam.__version__ if hasattr(gtsam, "__version__") else "4.3",
    "states": n,
    "factors": graph.size(),
    "loop_closures": len(lcs),
    "initial_error": graph.error(init),
    "batch_error": graph.error(res),
    "batch_iterations": opt.iterations(),
    "batch_seconds": t_lm,
    "batch_ate_rmse_m": ate(res)[0],
    "batch_ate_max_m": ate(res)[1],
    "dead_reckoning_ate_rmse_m": ate(init)[0],
}
# The marginal covariance of the last pose at the batch optimum ([rot x3, trans x3], tangent
# at the pose), for the incremental smoother's newest-state covariance.
marginals = gtsam.Marginals(graph, res)
out["last_pose_marginal_covariance"] = marginals.marginalCovariance(X(n - 1)).tolist()
if args.isam2:
    ip = gtsam.ISAM2Params()
    ip.setRelinearizeThreshold(0.1)
    ip.relinearizeSkip = 10
    ip.setFactorization("QR")
    isam = gtsam.ISAM2(ip)
    times = []
    state = gtsam.NavState(gt[0][0], gt[0][1])
    bias = zero
    full = gtsam.NonlinearFactorGraph()
    for i in range(n):
        fg, pim = factors_of(i, bias)
        vals = gtsam.Values()
        if i == 0:
            vals.insert(X(0), gt[0][0]); vals.insert(V(0), gt[0][1]); vals.insert(B(0), zero)
        else:
            pred = pim.predict(state, bias)
            vals.insert(X(i), pred.pose()); vals.insert(V(i), pred.velocity()); vals.insert(B(i), bias)
        full.push_back(fg)
        t0 = time.perf_counter()
        isam.update(fg, vals)
        state = gtsam.NavState(isam.calculateEstimatePose3(X(i)), isam.calculateEstimateVector(V(i)))
        bias = isam.calculateEstimateConstantBias(B(i))
        times.append((time.perf_counter() - t0) * 1e3)
    est = isam.calculateEstimate()
    t = np.array(times)
    out.update({
        "isam2_update_ms_p50": float(np.median(t)),
        "isam2_update_ms_p99": float(np.percentile(t, 99)),
        "isam2_update_ms_max": float(t.max()),
        "isam2_error": full.error(est),
        "isam2_ate_rmse_m": ate(est)[0],
    })
print(json.dumps(out, indent=1))
