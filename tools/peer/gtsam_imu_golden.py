"""Golden values for the IMU preintegration test in stages/estimate/src/imu.rs, from GTSAM 4.3.

usage: .venv-gtsam/bin/python tools/peer/gtsam_imu_golden.py   (prints the Rust constants)
"""
import gtsam
import numpy as np

p = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
p.setAccelerometerCovariance(np.eye(3) * 0.01**2)
p.setGyroscopeCovariance(np.eye(3) * 0.001**2)
p.setIntegrationCovariance(np.eye(3) * 1e-8)
p.setBiasAccCovariance(np.eye(3) * 1e-3**2)
p.setBiasOmegaCovariance(np.eye(3) * 1e-4**2)
bias_hat = gtsam.imuBias.ConstantBias(np.array([0.05, -0.03, 0.08]), np.array([0.002, -0.001, 0.003]))
pim = gtsam.PreintegratedCombinedMeasurements(p, bias_hat)
for k in range(20):
    f = np.array([0.3 + 0.01 * k, -0.2, 9.81 + 0.05 * np.sin(k)])
    w = np.array([0.1, -0.05 + 0.002 * k, 0.3])
    pim.integrateMeasurement(f, w, 0.005)
fac = gtsam.CombinedImuFactor(1, 2, 3, 4, 5, 6, pim)
v = gtsam.Values()
v.insert(1, gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.1, -0.2), np.array([1.0, 2, 3])))
v.insert(2, np.array([1.0, 0.5, -0.1]))
v.insert(3, gtsam.Pose3(gtsam.Rot3.Ypr(0.35, 0.12, -0.18), np.array([1.12, 2.05, 3.0])))
v.insert(4, np.array([1.1, 0.4, -0.05]))
v.insert(5, gtsam.imuBias.ConstantBias(np.array([0.06, -0.02, 0.07]), np.array([0.0025, -0.0012, 0.0031])))
v.insert(6, gtsam.imuBias.ConstantBias(np.array([0.061, -0.021, 0.071]), np.array([0.0026, -0.0011, 0.0032])))


def arr(name, a):
    a = np.asarray(a).flatten()
    print(f"const {name}: [f64; {len(a)}] = [{', '.join(repr(float(x)) for x in a)}];")


for key in (1, 3):
    arr(f"ROT_{key}", v.atPose3(key).rotation().matrix().flatten())
arr("DELTA_ROT", pim.deltaRij().matrix().flatten())
arr("DELTA_POS", pim.deltaPij())
arr("DELTA_VEL", pim.deltaVij())
arr("PREINT_COV", pim.preintMeasCov())
arr("RESIDUAL_COV", fac.noiseModel().covariance())
arr("RESIDUAL", fac.unwhitenedError(v))
print(f"const ERROR: f64 = {fac.error(v)!r};")
