//! IMU preintegration on the manifold (Forster et al.; seed 000 §4.2.2, eq. 4.4-4.7) and the
//! combined IMU factor that also carries the bias random walk.
//!
//! The preintegrated quantities live in the tangent space `[theta, dp, dv]` at the first state
//! (GTSAM's `TangentPreintegration`, the default of its release builds), with first-order bias
//! correction through `d(preintegrated)/d(bias)`. The factor's residual and noise follow GTSAM
//! 4.3's `CombinedImuFactor` exactly, so the graph error agrees with a GTSAM graph on the same
//! measurements:
//! - residual `[Log_SE2(3)(X_j^-1 X_pred); b_i - b_j]`, `X_pred` the state predicted from `i`;
//! - noise: the preintegration covariance mapped to the residual,
//!   `T Sigma T^T` with `T = diag(Jr(theta), dR^T, dR^T, -I6)`.

use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, SVector, Vector3};

use crate::factor::Factor;
use crate::lie::{Pose3, se3_q_right, skew, so3_exp, so3_right_jacobian, so3_right_jacobian_inv};
use crate::noise::NoiseModel;
use crate::values::{ImuBias, Values, VarId};
use crate::{Error, Result};

type Vector9 = SVector<f64, 9>;
type Matrix9 = SMatrix<f64, 9, 9>;
type Matrix93 = SMatrix<f64, 9, 3>;
type Matrix15 = SMatrix<f64, 15, 15>;

/// IMU noise and gravity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuParams {
    /// Gravity in the world frame (z up: `(0, 0, -9.81)`), m/s^2.
    pub gravity_mps2: Vector3<f64>,
    /// Accelerometer white-noise density, (m/s^2)/sqrt(Hz).
    pub acc_noise_density: f64,
    /// Gyroscope white-noise density, (rad/s)/sqrt(Hz).
    pub gyro_noise_density: f64,
    /// Accelerometer bias random-walk density, (m/s^3)/sqrt(Hz).
    pub acc_bias_random_walk: f64,
    /// Gyroscope bias random-walk density, (rad/s^2)/sqrt(Hz).
    pub gyro_bias_random_walk: f64,
    /// Variance added to the position per second of integration (GTSAM's integration covariance), m^2.
    pub integration_variance: f64,
}

impl Default for ImuParams {
    fn default() -> Self {
        Self {
            gravity_mps2: Vector3::new(0.0, 0.0, -9.81),
            acc_noise_density: 0.01,
            gyro_noise_density: 0.001,
            acc_bias_random_walk: 1e-3,
            gyro_bias_random_walk: 1e-4,
            integration_variance: 1e-8,
        }
    }
}

impl ImuParams {
    /// The thesis rig's XSENS MTi-30 (seed 000; average-axis Allan densities of
    /// `shared/data/imu/xsens_mti30_allan.yaml`), standard gravity, z up.
    #[must_use]
    pub fn xsens_mti30() -> Self {
        Self {
            gravity_mps2: Vector3::new(0.0, 0.0, -9.80665),
            acc_noise_density: 8.27e-3,
            gyro_noise_density: 2.28e-3,
            acc_bias_random_walk: 1.33e-4,
            gyro_bias_random_walk: 5.02e-5,
            ..Self::default()
        }
    }
}

/// Measurements between two states integrated into one relative-motion measurement.
#[derive(Debug, Clone)]
pub struct ImuPreintegration {
    params: ImuParams,
    bias_hat: ImuBias,
    delta_t_s: f64,
    /// `[theta, dp, dv]` in the tangent space at state i.
    preintegrated: Vector9,
    d_preint_d_bias_acc: Matrix93,
    d_preint_d_bias_gyro: Matrix93,
    /// Covariance of `[theta, dp, dv, b_acc, b_gyro]`.
    cov: Matrix15,
}

impl ImuPreintegration {
    /// Starts an integration with the bias estimate `bias_hat` (the linearisation point of the
    /// first-order bias correction).
    #[must_use]
    pub fn new(params: ImuParams, bias_hat: ImuBias) -> Self {
        Self {
            params,
            bias_hat,
            delta_t_s: 0.0,
            preintegrated: Vector9::zeros(),
            d_preint_d_bias_acc: Matrix93::zeros(),
            d_preint_d_bias_gyro: Matrix93::zeros(),
            cov: Matrix15::zeros(),
        }
    }

    /// Integrates one sample: specific force (m/s^2) and angular rate (rad/s) in the body frame,
    /// held for `dt_s`.
    ///
    /// # Errors
    /// [`Error::BadMeasurement`] for a `dt_s` that is not positive and finite.
    pub fn integrate(&mut self, acc_mps2: &Vector3<f64>, gyro_radps: &Vector3<f64>, dt_s: f64) -> Result<()> {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return Err(Error::BadMeasurement(format!("IMU sample interval {dt_s} s")));
        }
        let a = acc_mps2 - self.bias_hat.acc_mps2;
        let w = gyro_radps - self.bias_hat.gyro_radps;
        let theta: Vector3<f64> = self.preintegrated.fixed_rows::<3>(0).into_owned();
        let pos: Vector3<f64> = self.preintegrated.fixed_rows::<3>(3).into_owned();
        let vel: Vector3<f64> = self.preintegrated.fixed_rows::<3>(6).into_owned();

        let jr = so3_right_jacobian(&theta);
        let jr_inv = so3_right_jacobian_inv(&theta);
        let w_tangent = jr_inv * w;
        let w_tangent_d_theta = d_jr_inv_times(&theta, &w);
        let r = so3_exp(&theta);
        let a_nav = r * a;
        let dt22 = 0.5 * dt_s * dt_s;

        let mut next = Vector9::zeros();
        next.fixed_rows_mut::<3>(0).copy_from(&(theta + w_tangent * dt_s));
        next.fixed_rows_mut::<3>(3)
            .copy_from(&(pos + vel * dt_s + a_nav * dt22));
        next.fixed_rows_mut::<3>(6).copy_from(&(vel + a_nav * dt_s));

        let a_nav_d_theta = r * skew(&(-a)) * jr;
        let mut big_a = Matrix9::identity();
        big_a
            .fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() + w_tangent_d_theta * dt_s));
        big_a.fixed_view_mut::<3, 3>(3, 0).copy_from(&(a_nav_d_theta * dt22));
        big_a
            .fixed_view_mut::<3, 3>(3, 6)
            .copy_from(&(Matrix3::identity() * dt_s));
        big_a.fixed_view_mut::<3, 3>(6, 0).copy_from(&(a_nav_d_theta * dt_s));
        let mut big_b = Matrix93::zeros();
        big_b.fixed_view_mut::<3, 3>(3, 0).copy_from(&(r * dt22));
        big_b.fixed_view_mut::<3, 3>(6, 0).copy_from(&(r * dt_s));
        let mut big_c = Matrix93::zeros();
        big_c.fixed_view_mut::<3, 3>(0, 0).copy_from(&(jr_inv * dt_s));

        self.delta_t_s += dt_s;
        self.preintegrated = next;
        self.d_preint_d_bias_acc = big_a * self.d_preint_d_bias_acc - big_b;
        self.d_preint_d_bias_gyro = big_a * self.d_preint_d_bias_gyro - big_c;

        // First-order covariance propagation (GTSAM's PreintegratedCombinedMeasurements).
        let mut f = Matrix15::zeros();
        f.fixed_view_mut::<9, 9>(0, 0).copy_from(&big_a);
        f.fixed_view_mut::<9, 3>(0, 9).copy_from(&big_b);
        f.fixed_view_mut::<9, 3>(0, 12).copy_from(&big_c);
        f.fixed_view_mut::<6, 6>(9, 9).fill_with_identity();
        let p = &self.params;
        let acc_cov = p.acc_noise_density * p.acc_noise_density;
        let gyro_cov = p.gyro_noise_density * p.gyro_noise_density;
        let mut q = Matrix15::zeros();
        q.fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&(Matrix3::identity() * (dt_s * p.integration_variance)));
        // Sample noise enters as the bias does: (1/dt) B Sigma_acc B^T + (1/dt) C Sigma_gyro C^T.
        let meas = big_b * big_b.transpose() * (acc_cov / dt_s) + big_c * big_c.transpose() * (gyro_cov / dt_s);
        let mut q9 = q.fixed_view_mut::<9, 9>(0, 0);
        q9 += meas;
        let ba = p.acc_bias_random_walk * p.acc_bias_random_walk * dt_s;
        let bg = p.gyro_bias_random_walk * p.gyro_bias_random_walk * dt_s;
        q.fixed_view_mut::<3, 3>(9, 9).copy_from(&(Matrix3::identity() * ba));
        q.fixed_view_mut::<3, 3>(12, 12).copy_from(&(Matrix3::identity() * bg));
        self.cov = f * self.cov * f.transpose() + q;
        Ok(())
    }

    /// Total integrated time, s.
    #[must_use]
    pub fn delta_t_s(&self) -> f64 {
        self.delta_t_s
    }

    /// The bias the measurements were integrated with.
    #[must_use]
    pub fn bias_hat(&self) -> ImuBias {
        self.bias_hat
    }

    /// Preintegrated rotation `R_i^T R_j` at the integration bias.
    #[must_use]
    pub fn delta_rot(&self) -> Matrix3<f64> {
        so3_exp(&self.preintegrated.fixed_rows::<3>(0).into_owned())
    }

    /// Preintegrated position increment at the integration bias (no gravity, no initial velocity).
    #[must_use]
    pub fn delta_pos_m(&self) -> Vector3<f64> {
        self.preintegrated.fixed_rows::<3>(3).into_owned()
    }

    /// Preintegrated velocity increment at the integration bias.
    #[must_use]
    pub fn delta_vel_mps(&self) -> Vector3<f64> {
        self.preintegrated.fixed_rows::<3>(6).into_owned()
    }

    /// Covariance of `[theta, dp, dv, b_acc, b_gyro]` (GTSAM's `preintMeasCov`).
    #[must_use]
    pub fn preintegration_covariance(&self) -> Matrix15 {
        self.cov
    }

    /// Covariance of the factor residual (GTSAM 4.3's `residualCovariance`).
    #[must_use]
    pub fn residual_covariance(&self) -> Matrix15 {
        let theta: Vector3<f64> = self.preintegrated.fixed_rows::<3>(0).into_owned();
        let rt = so3_exp(&theta).transpose();
        let mut t = Matrix15::identity();
        t.fixed_view_mut::<3, 3>(0, 0).copy_from(&so3_right_jacobian(&theta));
        t.fixed_view_mut::<3, 3>(3, 3).copy_from(&rt);
        t.fixed_view_mut::<3, 3>(6, 6).copy_from(&rt);
        // The bias residual is b_i - b_j: its noise enters with the opposite sign.
        t.fixed_view_mut::<6, 6>(9, 9).fill_with_identity();
        t.fixed_view_mut::<6, 6>(9, 9).neg_mut();
        t * self.cov * t.transpose()
    }

    fn bias_corrected(&self, bias: &ImuBias) -> Vector9 {
        self.preintegrated
            + self.d_preint_d_bias_acc * (bias.acc_mps2 - self.bias_hat.acc_mps2)
            + self.d_preint_d_bias_gyro * (bias.gyro_radps - self.bias_hat.gyro_radps)
    }

    /// The state at j predicted from the state at i and the bias at i.
    #[must_use]
    pub fn predict(&self, pose_i: &Pose3, vel_i: &Vector3<f64>, bias_i: &ImuBias) -> (Pose3, Vector3<f64>) {
        let xi = self.bias_corrected(bias_i);
        self.predict_corrected(pose_i, vel_i, &xi, &so3_exp(&xi.fixed_rows::<3>(0).into_owned()))
    }

    /// [`ImuPreintegration::predict`] from the bias-corrected increment `xi` and the exponential
    /// of its rotation part.
    fn predict_corrected(
        &self,
        pose_i: &Pose3,
        vel_i: &Vector3<f64>,
        xi: &Vector9,
        d_rot: &Matrix3<f64>,
    ) -> (Pose3, Vector3<f64>) {
        let dt = self.delta_t_s;
        let g = self.params.gravity_mps2;
        let rot = pose_i.rot * d_rot;
        let pos = pose_i.trans_m + pose_i.rot * xi.fixed_rows::<3>(3) + vel_i * dt + 0.5 * dt * dt * g;
        let vel = vel_i + pose_i.rot * xi.fixed_rows::<3>(6) + g * dt;
        (Pose3::new(crate::lie::orthonormalise(&rot), pos), vel)
    }
}

/// `d(Jr(theta)^-1 w) / d theta`.
fn d_jr_inv_times(theta: &Vector3<f64>, w: &Vector3<f64>) -> Matrix3<f64> {
    // Jr^-1 w = w + 0.5 theta x w + c(t) theta x (theta x w), t = |theta|.
    let t = theta.norm();
    let (c, dc_dt) = if t < 1e-3 {
        (1.0 / 12.0 + t * t / 720.0, t / 360.0)
    } else {
        let half = 0.5 * t;
        let cot = half.cos() / half.sin();
        let csc2 = 1.0 / (half.sin() * half.sin());
        (
            1.0 / (t * t) - cot / (2.0 * t),
            -2.0 / (t * t * t) + csc2 / (4.0 * t) + cot / (2.0 * t * t),
        )
    };
    let txtxw = theta.cross(&theta.cross(w));
    let d_txtxw = theta * w.transpose() + Matrix3::identity() * theta.dot(w) - 2.0 * w * theta.transpose();
    let dc = if t > 0.0 {
        theta.transpose() * (dc_dt / t)
    } else {
        nalgebra::RowVector3::zeros()
    };
    -0.5 * skew(w) + txtxw * dc + c * d_txtxw
}

/// SE_2(3) logarithm of `(R, p, v)`: `[w, Jl^-1 p, Jl^-1 v]`.
fn log_se23(rot: &Matrix3<f64>, p: &Vector3<f64>, v: &Vector3<f64>) -> Vector9 {
    let w = crate::lie::so3_log(rot);
    let jl_inv = so3_right_jacobian_inv(&(-w));
    let mut out = Vector9::zeros();
    out.fixed_rows_mut::<3>(0).copy_from(&w);
    out.fixed_rows_mut::<3>(3).copy_from(&(jl_inv * p));
    out.fixed_rows_mut::<3>(6).copy_from(&(jl_inv * v));
    out
}

/// The combined IMU factor on `(pose_i, vel_i, pose_j, vel_j, bias_i, bias_j)`
/// (seed 000 eq. 4.5 and 4.7).
#[derive(Debug, Clone)]
pub struct CombinedImuFactor {
    keys: [VarId; 6],
    pim: ImuPreintegration,
    noise: NoiseModel,
}

/// The variables one navigation state is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NavKeys {
    /// Pose `world_from_body`.
    pub pose: VarId,
    /// Velocity in the world.
    pub velocity: VarId,
    /// IMU bias.
    pub bias: VarId,
}

impl CombinedImuFactor {
    /// # Errors
    /// [`Error::BadNoise`] when the residual covariance is not positive definite (no samples).
    pub fn new(i: NavKeys, j: NavKeys, pim: ImuPreintegration) -> Result<Self> {
        let cov = pim.residual_covariance();
        let noise = NoiseModel::from_covariance(&DMatrix::from_column_slice(15, 15, cov.as_slice()))?;
        Ok(Self {
            keys: [i.pose, i.velocity, j.pose, j.velocity, i.bias, j.bias],
            pim,
            noise,
        })
    }

    /// The preintegrated measurement.
    #[must_use]
    pub fn preintegration(&self) -> &ImuPreintegration {
        &self.pim
    }
}

impl Factor for CombinedImuFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let pose_i = values.pose(self.keys[0])?;
        let vel_i = values.velocity(self.keys[1])?;
        let pose_j = values.pose(self.keys[2])?;
        let vel_j = values.velocity(self.keys[3])?;
        let bias_i = values.bias(self.keys[4])?;
        let bias_j = values.bias(self.keys[5])?;
        let xi = self.pim.bias_corrected(bias_i);
        let theta: Vector3<f64> = xi.fixed_rows::<3>(0).into_owned();
        let d_rot = so3_exp(&theta);
        let (pred, vel_pred) = self.pim.predict_corrected(pose_i, vel_i, &xi, &d_rot);
        // E = X_j^-1 X_pred.
        let rjt = pose_j.rot.transpose();
        let e_rot = rjt * pred.rot;
        let e_p = rjt * (pred.trans_m - pose_j.trans_m);
        let e_v = rjt * (vel_pred - vel_j);
        let r9 = log_se23(&e_rot, &e_p, &e_v);
        let rb = bias_i.vector() - bias_j.vector();

        if let Some(jac) = jacobians {
            // Jr^-1 of SE_2(3) at r9 is block lower-triangular, [A 0 0; Qp A 0; Qv 0 A], and so
            // are the other 9x9 factors below: the products are taken by 3x3 blocks.
            let w: Vector3<f64> = r9.fixed_rows::<3>(0).into_owned();
            let a = so3_right_jacobian_inv(&w);
            let q = |rho: Vector3<f64>| {
                let mut x6 = nalgebra::Vector6::zeros();
                x6.fixed_rows_mut::<3>(0).copy_from(&w);
                x6.fixed_rows_mut::<3>(3).copy_from(&rho);
                -a * se3_q_right(&x6) * a
            };
            let (qp, qv) = (
                q(r9.fixed_rows::<3>(3).into_owned()),
                q(r9.fixed_rows::<3>(6).into_owned()),
            );
            // Rows [top; mid; bottom] of Jr^-1 times a 9-row matrix given by its three 3-row blocks.
            let jinv_times = |top: &Matrix3<f64>, mid: &Matrix3<f64>, bottom: &Matrix3<f64>| {
                (a * top, qp * top + a * mid, qv * top + a * bottom)
            };
            for m in jac.iter_mut() {
                m.as_mut_slice().fill(0.0);
            }

            // -Jr^-1 Ad(E^-1); E^-1 = (R^T, -R^T p, -R^T v): Ad(E^-1) = [R^T 0 0; S_p R^T 0;
            // S_v 0 R^T] with S = skew(-R^T p) R^T.
            let ert = e_rot.transpose();
            let a_ert = a * ert;
            let (_, mid, bottom) = jinv_times(&ert, &(skew(&(-ert * e_p)) * ert), &(skew(&(-ert * e_v)) * ert));
            // pose_j: body perturbation [rot, pos]; vel_j world additive -> body R_j^T.
            jac[2].view_mut((0, 0), (3, 3)).copy_from(&-a_ert);
            jac[2].view_mut((3, 0), (3, 3)).copy_from(&-mid);
            jac[2].view_mut((6, 0), (3, 3)).copy_from(&-bottom);
            jac[2].view_mut((3, 3), (3, 3)).copy_from(&-a_ert);
            jac[3].view_mut((6, 0), (3, 3)).copy_from(&(-a_ert * rjt));

            // Body-tangent perturbation of X_pred per state-i variable: columns d rot_i, d pos_i,
            // d vel_i; [drt 0 0; -drt [dp]x drt rpt dt; -drt [dv]x 0 rpt].
            let dp: Vector3<f64> = xi.fixed_rows::<3>(3).into_owned();
            let dv: Vector3<f64> = xi.fixed_rows::<3>(6).into_owned();
            let drt = d_rot.transpose();
            let rpt = pred.rot.transpose();
            let dt = self.pim.delta_t_s;
            let a_drt = a * drt;
            let (top, mid, bottom) = jinv_times(&drt, &(-drt * skew(&dp)), &(-drt * skew(&dv)));
            jac[0].view_mut((0, 0), (3, 3)).copy_from(&top);
            jac[0].view_mut((3, 0), (3, 3)).copy_from(&mid);
            jac[0].view_mut((6, 0), (3, 3)).copy_from(&bottom);
            jac[0].view_mut((3, 3), (3, 3)).copy_from(&a_drt);
            let a_rpt = a * rpt;
            jac[1].view_mut((3, 0), (3, 3)).copy_from(&(a_rpt * dt));
            jac[1].view_mut((6, 0), (3, 3)).copy_from(&a_rpt);

            // The bias at i, through the preintegrated increment's first-order correction.
            let jr_theta = so3_right_jacobian(&theta);
            let (ha, hg) = (&self.pim.d_preint_d_bias_acc, &self.pim.d_preint_d_bias_gyro);
            for (col, h) in [(0, ha), (3, hg)] {
                let (top, mid, bottom) = jinv_times(
                    &(jr_theta * h.fixed_view::<3, 3>(0, 0)),
                    &(drt * h.fixed_view::<3, 3>(3, 0)),
                    &(drt * h.fixed_view::<3, 3>(6, 0)),
                );
                jac[4].view_mut((0, col), (3, 3)).copy_from(&top);
                jac[4].view_mut((3, col), (3, 3)).copy_from(&mid);
                jac[4].view_mut((6, col), (3, 3)).copy_from(&bottom);
            }
            jac[4].view_mut((9, 0), (6, 6)).fill_with_identity();
            jac[5].view_mut((9, 0), (6, 6)).fill_with_identity();
            jac[5].view_mut((9, 0), (6, 6)).neg_mut();
        }
        let mut r = DVector::zeros(15);
        r.rows_mut(0, 9).copy_from(&r9);
        r.rows_mut(9, 6).copy_from(&rb);
        Ok(r)
    }
}

#[cfg(test)]
#[allow(clippy::excessive_precision, clippy::unreadable_literal)]
mod tests {
    use super::*;
    use crate::factor::analytic_and_numeric_jacobians;
    use crate::values::Variable;

    const JAC_TOL: f64 = 1e-5;
    /// Relative agreement with the GTSAM golden values.
    const GOLDEN_REL_TOL: f64 = 1e-9;

    include!("imu_golden.rs");

    fn golden_pim() -> ImuPreintegration {
        let bias_hat = ImuBias {
            acc_mps2: Vector3::new(0.05, -0.03, 0.08),
            gyro_radps: Vector3::new(0.002, -0.001, 0.003),
        };
        let mut pim = ImuPreintegration::new(ImuParams::default(), bias_hat);
        for k in 0..20 {
            let kf = f64::from(k);
            let f = Vector3::new(0.3 + 0.01 * kf, -0.2, 9.81 + 0.05 * kf.sin());
            let w = Vector3::new(0.1, -0.05 + 0.002 * kf, 0.3);
            pim.integrate(&f, &w, 0.005).expect("dt");
        }
        pim
    }

    fn golden_values() -> (Values, NavKeys, NavKeys) {
        let mut v = Values::new();
        let rot = |a: &[f64; 9]| Matrix3::from_row_slice(a);
        let bias = |a: [f64; 3], g: [f64; 3]| ImuBias {
            acc_mps2: Vector3::from(a),
            gyro_radps: Vector3::from(g),
        };
        let i = NavKeys {
            pose: v.push(Variable::Pose(Pose3::new(rot(&ROT_1), Vector3::new(1.0, 2.0, 3.0)))),
            velocity: v.push(Variable::Velocity(Vector3::new(1.0, 0.5, -0.1))),
            bias: v.push(Variable::Bias(bias([0.06, -0.02, 0.07], [0.0025, -0.0012, 0.0031]))),
        };
        let j = NavKeys {
            pose: v.push(Variable::Pose(Pose3::new(rot(&ROT_3), Vector3::new(1.12, 2.05, 3.0)))),
            velocity: v.push(Variable::Velocity(Vector3::new(1.1, 0.4, -0.05))),
            bias: v.push(Variable::Bias(bias([0.061, -0.021, 0.071], [0.0026, -0.0011, 0.0032]))),
        };
        (v, i, j)
    }

    fn assert_close(name: &str, ours: &[f64], gtsam: &[f64], scale: f64) {
        assert_eq!(ours.len(), gtsam.len());
        for (k, (a, b)) in ours.iter().zip(gtsam).enumerate() {
            assert!(
                (a - b).abs() <= GOLDEN_REL_TOL * scale,
                "{name}[{k}]: ours {a:e} gtsam {b:e}"
            );
        }
    }

    fn max_abs(a: &[f64]) -> f64 {
        a.iter().fold(0.0, |m, x| m.max(x.abs()))
    }

    #[test]
    fn preintegration_matches_gtsam() {
        let pim = golden_pim();
        let r = pim.delta_rot().transpose();
        assert_close("delta_rot", r.as_slice(), &DELTA_ROT, 1.0);
        assert_close("delta_pos", pim.delta_pos_m().as_slice(), &DELTA_POS, 1.0);
        assert_close("delta_vel", pim.delta_vel_mps().as_slice(), &DELTA_VEL, 1.0);
        let cov = pim.preintegration_covariance();
        assert_close("preint_cov", cov.as_slice(), &PREINT_COV, max_abs(&PREINT_COV));
        let rc = pim.residual_covariance();
        assert_close("residual_cov", rc.as_slice(), &RESIDUAL_COV, max_abs(&RESIDUAL_COV));
    }

    #[test]
    fn factor_error_matches_gtsam() {
        let (v, i, j) = golden_values();
        let f = CombinedImuFactor::new(i, j, golden_pim()).expect("factor");
        let r = f.evaluate(&v, None).expect("evaluate");
        assert_close("residual", r.as_slice(), &RESIDUAL, 1.0);
        let e = f.error(&v).expect("error");
        assert!((e - ERROR).abs() < 1e-8 * ERROR, "error ours {e} gtsam {ERROR}");
    }

    #[test]
    fn factor_jacobians_match_numerical() {
        let (v, i, j) = golden_values();
        let f = CombinedImuFactor::new(i, j, golden_pim()).expect("factor");
        for (k, (a, n)) in analytic_and_numeric_jacobians(&f, &v, 1e-6)
            .expect("jac")
            .into_iter()
            .enumerate()
        {
            let err = (&a - &n).abs().max();
            assert!(err < JAC_TOL, "key {k}: {err:e}\n{a}\n{n}");
        }
    }

    #[test]
    fn preintegration_bias_jacobians_match_numerical() {
        // Re-integrating with a perturbed bias_hat moves the preintegrated vector by ~ -H db.
        let base = golden_pim();
        let step = 1e-6;
        for k in 0..6 {
            let mut b = base.bias_hat();
            let mut v = b.vector();
            v[k] += step;
            b = ImuBias::from_vector(&v);
            let mut moved = ImuPreintegration::new(ImuParams::default(), b);
            for s in 0..20 {
                let sf = f64::from(s);
                let f = Vector3::new(0.3 + 0.01 * sf, -0.2, 9.81 + 0.05 * sf.sin());
                let w = Vector3::new(0.1, -0.05 + 0.002 * sf, 0.3);
                moved.integrate(&f, &w, 0.005).expect("dt");
            }
            let num = (moved.preintegrated - base.preintegrated) / step;
            let ana = if k < 3 {
                base.d_preint_d_bias_acc.column(k).into_owned()
            } else {
                base.d_preint_d_bias_gyro.column(k - 3).into_owned()
            };
            assert!((num - ana).norm() < 1e-6, "bias {k}: {num} vs {ana}");
        }
    }

    #[test]
    fn d_jr_inv_matches_numerical() {
        let theta = Vector3::new(0.3, -0.2, 0.5);
        let w = Vector3::new(0.1, 0.7, -0.4);
        let ana = d_jr_inv_times(&theta, &w);
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = 1e-6;
            let num = (so3_right_jacobian_inv(&(theta + d)) * w - so3_right_jacobian_inv(&(theta - d)) * w) / 2e-6;
            assert!((num - ana.column(k)).norm() < 1e-8);
        }
    }
}
