//! SO(3) and SE(3) on nalgebra: exponential and logarithm maps, their right Jacobians, and
//! the pose type the factors use.
//!
//! Tangent vectors of a pose are ordered `[rotation, translation]` as in GTSAM, so a sigma
//! vector `[rot_rad x3, trans_m x3]` reads the same in both. Poses are perturbed on the right
//! (`world_from_body * Exp(xi)`); the retraction the solvers use is the first-order one
//! (`R Exp(dtheta)`, `t + R dt`), which has the same derivative at zero as the SE(3)
//! exponential, so Jacobians derived for one hold for the other.

use nalgebra::{Matrix3, Matrix6, Rotation3, UnitQuaternion, Vector3, Vector6};

/// Below this angle the series expansions replace the closed forms.
const SMALL_ANGLE_RAD: f64 = 1e-5;

/// `[v]x`, the cross-product matrix.
#[must_use]
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// SO(3) exponential map.
#[must_use]
pub fn so3_exp(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = omega.norm_squared();
    let w = skew(omega);
    if theta2 < SMALL_ANGLE_RAD * SMALL_ANGLE_RAD {
        return Matrix3::identity() + w + 0.5 * w * w;
    }
    let theta = theta2.sqrt();
    Matrix3::identity() + (theta.sin() / theta) * w + ((1.0 - theta.cos()) / theta2) * w * w
}

/// SO(3) logarithm map (the rotation vector of `r`).
#[must_use]
pub fn so3_log(r: &Matrix3<f64>) -> Vector3<f64> {
    let rot = Rotation3::from_matrix_unchecked(*r);
    let q = UnitQuaternion::from_rotation_matrix(&rot);
    // The quaternion route is accurate near 0 and pi alike.
    let (w, v) = (q.scalar(), q.vector().into_owned());
    let (w, v) = if w < 0.0 { (-w, -v) } else { (w, v) };
    let s = v.norm();
    if s < 1e-12 {
        return 2.0 * v / w;
    }
    let angle = 2.0 * s.atan2(w);
    v * (angle / s)
}

/// Right Jacobian of SO(3): `Exp(w + dw) ~= Exp(w) Exp(Jr(w) dw)`.
#[must_use]
pub fn so3_right_jacobian(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = omega.norm_squared();
    let w = skew(omega);
    if theta2 < SMALL_ANGLE_RAD * SMALL_ANGLE_RAD {
        return Matrix3::identity() - 0.5 * w + (1.0 / 6.0) * w * w;
    }
    let theta = theta2.sqrt();
    Matrix3::identity() - ((1.0 - theta.cos()) / theta2) * w + ((theta - theta.sin()) / (theta2 * theta)) * w * w
}

/// Inverse of [`so3_right_jacobian`]: `Log(R Exp(d)) ~= Log(R) + Jr^-1(Log R) d`.
#[must_use]
pub fn so3_right_jacobian_inv(omega: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = omega.norm_squared();
    let w = skew(omega);
    if theta2 < SMALL_ANGLE_RAD * SMALL_ANGLE_RAD {
        return Matrix3::identity() + 0.5 * w + (1.0 / 12.0) * w * w;
    }
    let theta = theta2.sqrt();
    let coeff = 1.0 / theta2 - (1.0 + theta.cos()) / (2.0 * theta * theta.sin());
    Matrix3::identity() + 0.5 * w + coeff * w * w
}

/// The `Q` block of the SE(3) right Jacobian (GTSAM's `computeQforExpmapDerivative`).
pub(crate) fn se3_q_right(xi: &Vector6<f64>) -> Matrix3<f64> {
    let w = skew(&xi.fixed_rows::<3>(0).into_owned());
    let v = skew(&xi.fixed_rows::<3>(3).into_owned());
    let phi = xi.fixed_rows::<3>(0).norm();
    let wv = w * v;
    let vw = v * w;
    let wvw = w * v * w;
    let t1 = wv + vw - wvw;
    let t2 = w * wv + vw * w - 3.0 * wvw;
    let t3 = wvw * w + w * wvw;
    if phi < 1e-3 {
        return -0.5 * v + (1.0 / 6.0) * t1 - (1.0 / 24.0) * t2 + (1.0 / 120.0) * t3;
    }
    let (s, c) = phi.sin_cos();
    let phi2 = phi * phi;
    let phi3 = phi2 * phi;
    let phi4 = phi3 * phi;
    let phi5 = phi4 * phi;
    let a = (phi - s) / phi3;
    let b = (1.0 - phi2 / 2.0 - c) / phi4;
    let d = 0.5 * ((1.0 - phi2 / 2.0 - c) / phi4 - 3.0 * (phi - s - phi3 / 6.0) / phi5);
    -0.5 * v + a * t1 + b * t2 - d * t3
}

/// Right Jacobian of SE(3) for `xi = [w, v]`.
#[must_use]
pub fn se3_right_jacobian(xi: &Vector6<f64>) -> Matrix6<f64> {
    let jw = so3_right_jacobian(&xi.fixed_rows::<3>(0).into_owned());
    let q = se3_q_right(xi);
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jw);
    j.fixed_view_mut::<3, 3>(3, 0).copy_from(&q);
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jw);
    j
}

/// Inverse of [`se3_right_jacobian`].
#[must_use]
pub fn se3_right_jacobian_inv(xi: &Vector6<f64>) -> Matrix6<f64> {
    let jw_inv = so3_right_jacobian_inv(&xi.fixed_rows::<3>(0).into_owned());
    let q = se3_q_right(xi);
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jw_inv);
    j.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-jw_inv * q * jw_inv));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jw_inv);
    j
}

/// A rigid transform `world_from_body`: rotation matrix and translation in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose3 {
    /// Rotation, body to world.
    pub rot: Matrix3<f64>,
    /// Position of the body origin in the world, metres.
    pub trans_m: Vector3<f64>,
}

impl Default for Pose3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose3 {
    /// The identity transform.
    #[must_use]
    pub fn identity() -> Self {
        Self {
            rot: Matrix3::identity(),
            trans_m: Vector3::zeros(),
        }
    }

    /// From a rotation matrix and a translation.
    #[must_use]
    pub fn new(rot: Matrix3<f64>, trans_m: Vector3<f64>) -> Self {
        Self { rot, trans_m }
    }

    /// From a unit quaternion `(x, y, z, w)` (normalised here) and a translation.
    #[must_use]
    pub fn from_quaternion(q_xyzw: [f64; 4], trans_m: Vector3<f64>) -> Self {
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]));
        Self {
            rot: q.to_rotation_matrix().into_inner(),
            trans_m,
        }
    }

    /// The rotation as a unit quaternion.
    #[must_use]
    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(self.rot))
    }

    /// `self * other`.
    #[must_use]
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            rot: self.rot * other.rot,
            trans_m: self.trans_m + self.rot * other.trans_m,
        }
    }

    /// The inverse transform.
    #[must_use]
    pub fn inverse(&self) -> Self {
        let rt = self.rot.transpose();
        Self {
            rot: rt,
            trans_m: -(rt * self.trans_m),
        }
    }

    /// `self^-1 * other`.
    #[must_use]
    pub fn between(&self, other: &Self) -> Self {
        let rt = self.rot.transpose();
        Self {
            rot: rt * other.rot,
            trans_m: rt * (other.trans_m - self.trans_m),
        }
    }

    /// SE(3) exponential of `[w, v]`.
    #[must_use]
    pub fn exp(xi: &Vector6<f64>) -> Self {
        let w = xi.fixed_rows::<3>(0).into_owned();
        let v = xi.fixed_rows::<3>(3).into_owned();
        let rot = so3_exp(&w);
        // Left Jacobian of SO(3) is Jr(-w).
        let jl = so3_right_jacobian(&(-w));
        Self { rot, trans_m: jl * v }
    }

    /// SE(3) logarithm `[w, v]`.
    #[must_use]
    pub fn log(&self) -> Vector6<f64> {
        let w = so3_log(&self.rot);
        let jl_inv = so3_right_jacobian_inv(&(-w));
        let v = jl_inv * self.trans_m;
        Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
    }

    /// The solvers' retraction: `(R Exp(d_rot), t + R d_trans)`.
    #[must_use]
    pub fn retract(&self, delta: &Vector6<f64>) -> Self {
        let dr = so3_exp(&delta.fixed_rows::<3>(0).into_owned());
        let dt = delta.fixed_rows::<3>(3).into_owned();
        Self {
            rot: orthonormalise(&(self.rot * dr)),
            trans_m: self.trans_m + self.rot * dt,
        }
    }

    /// The inverse of [`Pose3::retract`]: `delta` with `self.retract(delta) = other`.
    #[must_use]
    pub fn local(&self, other: &Self) -> Vector6<f64> {
        let w = so3_log(&(self.rot.transpose() * other.rot));
        let t = self.rot.transpose() * (other.trans_m - self.trans_m);
        Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z)
    }

    /// Adjoint for `[w, v]` tangent ordering: `Exp(Ad(T) xi) = T Exp(xi) T^-1`.
    #[must_use]
    pub fn adjoint(&self) -> Matrix6<f64> {
        let mut ad = Matrix6::zeros();
        ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.rot);
        ad.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(skew(&self.trans_m) * self.rot));
        ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&self.rot);
        ad
    }

    /// Heading (yaw) of the body x axis in the world xy plane, radians.
    #[must_use]
    pub fn yaw_rad(&self) -> f64 {
        self.rot[(1, 0)].atan2(self.rot[(0, 0)])
    }
}

/// Projects a nearly orthonormal matrix back onto SO(3) (keeps retractions from drifting).
#[must_use]
pub fn orthonormalise(r: &Matrix3<f64>) -> Matrix3<f64> {
    // The quaternion of a nearly orthonormal matrix, renormalised, is its closest rotation to
    // first order; exact rotations pass through unchanged up to rounding.
    // (nalgebra's `from_rotation_matrix` does not normalise the quaternion it reads off.)
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    UnitQuaternion::new_normalize(q.into_inner())
        .to_rotation_matrix()
        .into_inner()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOL: f64 = 1e-7;
    const STEP: f64 = 1e-6;

    fn sample_xi() -> Vector6<f64> {
        Vector6::new(0.3, -0.7, 1.1, 1.5, -0.4, 2.0)
    }

    #[test]
    fn so3_exp_log_round_trip() {
        for w in [
            Vector3::new(0.1, -0.2, 0.3),
            Vector3::new(1e-9, 0.0, 2e-9),
            Vector3::new(0.0, 3.1, 0.0),
        ] {
            assert!((so3_log(&so3_exp(&w)) - w).norm() < 1e-9, "{w:?}");
        }
    }

    #[test]
    fn orthonormalise_projects_onto_so3() {
        let r = so3_exp(&Vector3::new(0.3, -2.0, 1.0)) * Matrix3::from_diagonal(&Vector3::new(1.001, 0.999, 1.0005));
        let o = orthonormalise(&r);
        assert!((o.transpose() * o - Matrix3::identity()).norm() < 1e-14);
        assert!((o - r).norm() < 2e-3);
        let exact = so3_exp(&Vector3::new(0.1, 0.2, 3.0));
        assert!((orthonormalise(&exact) - exact).norm() < 1e-14);
    }

    #[test]
    fn se3_exp_log_round_trip() {
        let xi = sample_xi();
        assert!((Pose3::exp(&xi).log() - xi).norm() < 1e-9);
    }

    #[test]
    fn so3_right_jacobian_matches_numerical() {
        let w = Vector3::new(0.4, -0.3, 0.8);
        let jr = so3_right_jacobian(&w);
        let r = so3_exp(&w);
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = STEP;
            let num = so3_log(&(r.transpose() * so3_exp(&(w + d)))) / STEP;
            assert!((num - jr.column(k)).norm() < 1e-5);
        }
        assert!((so3_right_jacobian_inv(&w) * jr - Matrix3::identity()).norm() < 1e-12);
    }

    #[test]
    fn se3_right_jacobian_matches_numerical() {
        let xi = sample_xi();
        let j = se3_right_jacobian(&xi);
        let t = Pose3::exp(&xi);
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = STEP;
            let num = t.between(&Pose3::exp(&(xi + d))).log() / STEP;
            assert!((num - j.column(k)).norm() < 1e-5, "column {k}");
        }
        assert!((se3_right_jacobian_inv(&xi) * j - Matrix6::identity()).norm() < TOL);
    }

    #[test]
    fn adjoint_moves_a_perturbation_across() {
        let t = Pose3::exp(&sample_xi());
        let xi = Vector6::new(0.01, 0.02, -0.03, 0.1, 0.0, 0.2);
        let lhs = t.compose(&Pose3::exp(&xi)).compose(&t.inverse());
        let rhs = Pose3::exp(&(t.adjoint() * xi));
        assert!((lhs.log() - rhs.log()).norm() < 1e-9);
    }
}
