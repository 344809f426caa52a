//! Priors, relative-pose, along-track, position, line and ground-vehicle factors.
//!
//! Residual conventions follow GTSAM where GTSAM has the factor (prior and between factors
//! use the SE(3) logarithm, so errors agree with a GTSAM graph on the same data).

use nalgebra::{DMatrix, DVector, Matrix3, Matrix6, Vector3, Vector6};

use crate::factor::Factor;
use crate::lie::{Pose3, se3_right_jacobian_inv, skew};
use crate::noise::NoiseModel;
use crate::values::{HoughLine, ImuBias, Values, VarId};
use crate::{Error, Result};

fn check_dim(noise: &NoiseModel, dim: usize, what: &str) -> Result<()> {
    if noise.dim() == dim {
        Ok(())
    } else {
        Err(Error::BadNoise(format!(
            "{what} needs a {dim}-dimensional noise model, got {}",
            noise.dim()
        )))
    }
}

fn put(j: &mut [DMatrix<f64>], k: usize, row: usize, col: usize, block: &DMatrix<f64>) {
    j[k].view_mut((row, col), (block.nrows(), block.ncols()))
        .copy_from(block);
}

fn dm<const R: usize, const C: usize>(m: &nalgebra::SMatrix<f64, R, C>) -> DMatrix<f64> {
    DMatrix::from_column_slice(R, C, m.as_slice())
}

/// Prior on a pose: `Log(prior^-1 x)`.
#[derive(Debug, Clone)]
pub struct PosePrior {
    keys: [VarId; 1],
    prior: Pose3,
    noise: NoiseModel,
}

impl PosePrior {
    /// # Errors
    /// A noise model that is not 6-dimensional.
    pub fn new(key: VarId, prior: Pose3, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 6, "a pose prior")?;
        Ok(Self {
            keys: [key],
            prior,
            noise,
        })
    }
}

impl Factor for PosePrior {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let e = self.prior.between(values.pose(self.keys[0])?).log();
        if let Some(j) = jacobians {
            put(j, 0, 0, 0, &dm(&se3_right_jacobian_inv(&e)));
        }
        Ok(DVector::from_column_slice(e.as_slice()))
    }
}

/// Prior on a vector-valued variable (velocity, IMU bias or Hough line): `x - prior`.
#[derive(Debug, Clone)]
pub struct VectorPrior {
    keys: [VarId; 1],
    prior: DVector<f64>,
    noise: NoiseModel,
}

impl VectorPrior {
    /// Prior on a velocity.
    ///
    /// # Errors
    /// A noise model that is not 3-dimensional.
    pub fn velocity(key: VarId, prior: Vector3<f64>, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 3, "a velocity prior")?;
        Ok(Self {
            keys: [key],
            prior: DVector::from_column_slice(prior.as_slice()),
            noise,
        })
    }

    /// Prior on IMU biases.
    ///
    /// # Errors
    /// A noise model that is not 6-dimensional.
    pub fn bias(key: VarId, prior: ImuBias, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 6, "a bias prior")?;
        Ok(Self {
            keys: [key],
            prior: DVector::from_column_slice(prior.vector().as_slice()),
            noise,
        })
    }

    /// Prior on a Hough line `(rho, theta)`.
    ///
    /// # Errors
    /// A noise model that is not 2-dimensional.
    pub fn line(key: VarId, prior: HoughLine, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 2, "a line prior")?;
        Ok(Self {
            keys: [key],
            prior: DVector::from_vec(vec![prior.rho_m, prior.theta_rad]),
            noise,
        })
    }
}

impl Factor for VectorPrior {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let x = match values.get(self.keys[0])? {
            crate::values::Variable::Velocity(v) => DVector::from_column_slice(v.as_slice()),
            crate::values::Variable::Bias(b) => DVector::from_column_slice(b.vector().as_slice()),
            crate::values::Variable::Line(l) => DVector::from_vec(vec![l.rho_m, l.theta_rad]),
            crate::values::Variable::Pose(_) => {
                return Err(Error::WrongKind {
                    id: self.keys[0].0,
                    expected: "vector-valued variable",
                });
            }
        };
        if x.len() != self.prior.len() {
            return Err(Error::WrongKind {
                id: self.keys[0].0,
                expected: "variable of the prior's dimension",
            });
        }
        if let Some(j) = jacobians {
            j[0].fill_with_identity();
        }
        Ok(x - &self.prior)
    }
}

/// Relative pose between two states: `Log(z^-1 (x_i^-1 x_j))` (wheel odometry, loop closures,
/// and the full relative pose of a GPR registration, eq. 4.12 / 4.14).
#[derive(Debug, Clone)]
pub struct BetweenPose {
    keys: [VarId; 2],
    measured: Pose3,
    noise: NoiseModel,
}

impl BetweenPose {
    /// `measured` is `i_from_j`.
    ///
    /// # Errors
    /// A noise model that is not 6-dimensional.
    pub fn new(i: VarId, j: VarId, measured: Pose3, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 6, "a between factor")?;
        Ok(Self {
            keys: [i, j],
            measured,
            noise,
        })
    }
}

impl Factor for BetweenPose {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let ti = values.pose(self.keys[0])?;
        let tj = values.pose(self.keys[1])?;
        let tij = ti.between(tj);
        let e = self.measured.between(&tij).log();
        if let Some(j) = jacobians {
            let jinv = se3_right_jacobian_inv(&e);
            let ji: Matrix6<f64> = -jinv * tij.inverse().adjoint();
            put(j, 0, 0, 0, &dm(&ji));
            put(j, 1, 0, 0, &dm(&jinv));
        }
        Ok(DVector::from_column_slice(e.as_slice()))
    }
}

/// One component of the translation between two states, `x_i^-1 x_j`, minus `z`:
///
/// - [`TrackOffset::along`], x: the along-track distance a GPR registration (or a wheel
///   encoder) measures;
/// - [`TrackOffset::across`], y: the offset across the track that a GPR registration is taken
///   to imply. Two submaps that share features saw nearly the same strip of ground. Without a
///   bound the across offset between two passes is free, and an along-track residual can be
///   absorbed by turning the reference state's yaw about it (a 5 mm bias on the simulated
///   basement's registrations cost 8 cm of ATE that way); with one, passes that truly ran
///   apart are pulled together by their true offset.
#[derive(Debug, Clone)]
pub struct TrackOffset {
    keys: [VarId; 2],
    /// 0: along track (x), 1: across (y).
    axis: usize,
    z_m: f64,
    noise: NoiseModel,
}

impl TrackOffset {
    /// The along-track distance `distance_m` from `i` to `j`.
    ///
    /// # Errors
    /// A noise model that is not 1-dimensional.
    pub fn along(i: VarId, j: VarId, distance_m: f64, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 1, "an along-track factor")?;
        Ok(Self {
            keys: [i, j],
            axis: 0,
            z_m: distance_m,
            noise,
        })
    }

    /// The offset `offset_m` of `j` across `i`'s track.
    ///
    /// # Errors
    /// A noise model that is not 1-dimensional.
    pub fn across(i: VarId, j: VarId, offset_m: f64, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 1, "an across-track factor")?;
        Ok(Self {
            keys: [i, j],
            axis: 1,
            z_m: offset_m,
            noise,
        })
    }
}

impl Factor for TrackOffset {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let ti = values.pose(self.keys[0])?;
        let tj = values.pose(self.keys[1])?;
        let tij = ti.between(tj);
        let axis = self.axis;
        if let Some(j) = jacobians {
            // d t_ij / d(rot_i) = [t_ij]x, d/d(trans_i) = -I, d/d(trans_j) = R_ij; row `axis`.
            let dth: Matrix3<f64> = skew(&tij.trans_m);
            for c in 0..3 {
                j[0][(0, c)] = dth[(axis, c)];
                j[0][(0, 3 + c)] = if c == axis { -1.0 } else { 0.0 };
                j[1][(0, c)] = 0.0;
                j[1][(0, 3 + c)] = tij.rot[(axis, c)];
            }
        }
        Ok(DVector::from_element(1, tij.trans_m[axis] - self.z_m))
    }
}

/// Which position components a [`PositionFix`] constrains.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PositionAxes {
    /// x, y and z.
    Xyz,
    /// x and y only (a prior-map fix on the ground plane).
    Xy,
}

/// Absolute position of the body origin (a GPS fix, or a localising-GPR prior-map match).
/// With [`PositionFix::moving`], the fix was taken `dt` before (or after) the state and is
/// compared with the state's position moved by its velocity: `t + v dt - z`, so the velocity
/// is estimated with the fix instead of being frozen into it.
#[derive(Debug, Clone)]
pub struct PositionFix {
    /// The pose, and the velocity (used when `dt_s` is not zero).
    keys: [VarId; 2],
    dt_s: f64,
    position_m: Vector3<f64>,
    noise: NoiseModel,
}

impl PositionFix {
    /// A fix of the pose's position.
    ///
    /// # Errors
    /// A noise model whose dimension does not match `axes`.
    pub fn new(key: VarId, position_m: Vector3<f64>, axes: PositionAxes, noise: NoiseModel) -> Result<Self> {
        Self::moving(key, key, 0.0, position_m, axes, noise)
    }

    /// A fix taken `dt_s` after the state of `pose` (before it when negative), whose velocity
    /// is `velocity`.
    ///
    /// # Errors
    /// A noise model whose dimension does not match `axes`; a `dt_s` that is not finite.
    pub fn moving(
        pose: VarId,
        velocity: VarId,
        dt_s: f64,
        position_m: Vector3<f64>,
        axes: PositionAxes,
        noise: NoiseModel,
    ) -> Result<Self> {
        let n = match axes {
            PositionAxes::Xyz => 3,
            PositionAxes::Xy => 2,
        };
        check_dim(&noise, n, "a position fix")?;
        if !dt_s.is_finite() {
            return Err(Error::BadMeasurement(format!("a position fix {dt_s} s from its state")));
        }
        Ok(Self {
            keys: [pose, velocity],
            dt_s,
            position_m,
            noise,
        })
    }
}

impl PositionFix {
    /// Whether the fix reaches the state's velocity (taken at another time than the state).
    fn moves(&self) -> bool {
        self.dt_s != 0.0
    }
}

impl Factor for PositionFix {
    fn keys(&self) -> &[VarId] {
        &self.keys[..if self.moves() { 2 } else { 1 }]
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let p = values.pose(self.keys[0])?;
        let n = self.noise.dim();
        let mut r = p.trans_m - self.position_m;
        if self.moves() {
            r += values.velocity(self.keys[1])? * self.dt_s;
        }
        if let Some(j) = jacobians {
            j[0].fill(0.0);
            j[0].view_mut((0, 3), (n, 3)).copy_from(&p.rot.view((0, 0), (n, 3)));
            if self.moves() {
                j[1].fill(0.0);
                j[1].fill_diagonal(self.dt_s);
            }
        }
        Ok(DVector::from_iterator(n, r.iter().take(n).copied()))
    }
}

/// The forward distance from a pose to a Hough line (seed 000 eq. 5.3-5.7):
/// `(rho - (x cos theta + y sin theta)) / cos(psi - theta)`, `psi` the heading.
/// Returns the distance and its derivatives with respect to the pose (right perturbation,
/// `[rot, trans]`) and the line `(rho, theta)`.
#[must_use]
pub fn forward_distance_to_line(pose: &Pose3, line: &HoughLine) -> (f64, Vector6<f64>, [f64; 2]) {
    let r = &pose.rot;
    let (x, y) = (pose.trans_m.x, pose.trans_m.y);
    let psi = pose.yaw_rad();
    let (s, c) = line.theta_rad.sin_cos();
    let (sd, cd) = (psi - line.theta_rad).sin_cos();
    let d = line.rho_m - (x * c + y * s);
    let h = d / cd;
    // d psi / d w for R Exp(w): dR = R [w]x, psi = atan2(R10, R00).
    let den = r[(0, 0)] * r[(0, 0)] + r[(1, 0)] * r[(1, 0)];
    let d_r10 = Vector3::new(0.0, -r[(1, 2)], r[(1, 1)]);
    let d_r00 = Vector3::new(0.0, -r[(0, 2)], r[(0, 1)]);
    let dpsi_dw = (r[(0, 0)] * d_r10 - r[(1, 0)] * d_r00) / den;
    let dh_dpsi = d * sd / (cd * cd);
    let dh_dxy = [-c / cd, -s / cd];
    let mut jp = Vector6::zeros();
    for k in 0..3 {
        jp[k] = dh_dpsi * dpsi_dw[k];
        // t + R dt: d(x, y)/d dt = rows 0 and 1 of R.
        jp[3 + k] = dh_dxy[0] * r[(0, k)] + dh_dxy[1] * r[(1, k)];
    }
    let jl = [1.0 / cd, (x * s - y * c) / cd - d * sd / (cd * cd)];
    (h, jp, jl)
}

/// Forward distance to a line that is a variable (seed 000 eq. 5.7).
#[derive(Debug, Clone)]
pub struct LineDistance {
    keys: [VarId; 2],
    distance_m: f64,
    noise: NoiseModel,
}

impl LineDistance {
    /// # Errors
    /// A noise model that is not 1-dimensional.
    pub fn new(pose: VarId, line: VarId, distance_m: f64, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 1, "a line factor")?;
        Ok(Self {
            keys: [pose, line],
            distance_m,
            noise,
        })
    }
}

impl Factor for LineDistance {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let (h, jp, jl) = forward_distance_to_line(values.pose(self.keys[0])?, values.line(self.keys[1])?);
        if let Some(j) = jacobians {
            for k in 0..6 {
                j[0][(0, k)] = jp[k];
            }
            j[1][(0, 0)] = jl[0];
            j[1][(0, 1)] = jl[1];
        }
        Ok(DVector::from_element(1, h - self.distance_m))
    }
}

/// Forward distance to a line of a known map (the line is a constant).
#[derive(Debug, Clone)]
pub struct KnownLineDistance {
    keys: [VarId; 1],
    line: HoughLine,
    distance_m: f64,
    noise: NoiseModel,
}

impl KnownLineDistance {
    /// # Errors
    /// A noise model that is not 1-dimensional.
    pub fn new(pose: VarId, line: HoughLine, distance_m: f64, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 1, "a line factor")?;
        Ok(Self {
            keys: [pose],
            line,
            distance_m,
            noise,
        })
    }
}

impl Factor for KnownLineDistance {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let (h, jp, _) = forward_distance_to_line(values.pose(self.keys[0])?, &self.line);
        if let Some(j) = jacobians {
            for k in 0..6 {
                j[0][(0, k)] = jp[k];
            }
        }
        Ok(DVector::from_element(1, h - self.distance_m))
    }
}

/// Ground-vehicle constraint: the body-frame velocity has no lateral (y) and no vertical (z)
/// component (non-holonomic), optionally with a soft zero roll/pitch rate is left to priors.
#[derive(Debug, Clone)]
pub struct NonHolonomic {
    keys: [VarId; 2],
    noise: NoiseModel,
}

impl NonHolonomic {
    /// # Errors
    /// A noise model that is not 2-dimensional.
    pub fn new(pose: VarId, velocity: VarId, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 2, "a non-holonomic constraint")?;
        Ok(Self {
            keys: [pose, velocity],
            noise,
        })
    }
}

impl Factor for NonHolonomic {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let p = values.pose(self.keys[0])?;
        let v = values.velocity(self.keys[1])?;
        let vb = p.rot.transpose() * v;
        if let Some(j) = jacobians {
            // R^T v under R Exp(w): Exp(-w) R^T v ~= vb + [vb]x w.
            let dw = skew(&vb);
            let rt = p.rot.transpose();
            j[0].fill(0.0);
            j[0].view_mut((0, 0), (2, 3)).copy_from(&dw.view((1, 0), (2, 3)));
            j[1].copy_from(&rt.view((1, 0), (2, 3)));
        }
        Ok(DVector::from_vec(vec![vb.y, vb.z]))
    }
}

/// Planar-ground constraint: roll and pitch of the body near zero and height near `z_m`.
#[derive(Debug, Clone)]
pub struct Planar {
    keys: [VarId; 1],
    height_m: f64,
    noise: NoiseModel,
}

impl Planar {
    /// Residual `[z - height, (R e_z)_x, (R e_z)_y]` (the body up axis tilting out of vertical).
    ///
    /// # Errors
    /// A noise model that is not 3-dimensional.
    pub fn new(pose: VarId, height_m: f64, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 3, "a planar constraint")?;
        Ok(Self {
            keys: [pose],
            height_m,
            noise,
        })
    }
}

impl Factor for Planar {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let p = values.pose(self.keys[0])?;
        let up = p.rot.column(2).into_owned();
        if let Some(j) = jacobians {
            // R Exp(w) e_z ~= R e_z - R [e_z]x w.
            let d_up: Matrix3<f64> = -p.rot * skew(&Vector3::z());
            j[0].fill(0.0);
            for k in 0..3 {
                j[0][(0, 3 + k)] = p.rot[(2, k)];
                j[0][(1, k)] = d_up[(0, k)];
                j[0][(2, k)] = d_up[(1, k)];
            }
        }
        Ok(DVector::from_vec(vec![p.trans_m.z - self.height_m, up.x, up.y]))
    }
}

/// Bias random walk between consecutive states (seed 000 eq. 4.6-4.7): `b_j - b_i`.
#[derive(Debug, Clone)]
pub struct BiasRandomWalk {
    keys: [VarId; 2],
    noise: NoiseModel,
}

impl BiasRandomWalk {
    /// # Errors
    /// A noise model that is not 6-dimensional.
    pub fn new(i: VarId, j: VarId, noise: NoiseModel) -> Result<Self> {
        check_dim(&noise, 6, "a bias random walk")?;
        Ok(Self { keys: [i, j], noise })
    }
}

impl Factor for BiasRandomWalk {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let bi = values.bias(self.keys[0])?.vector();
        let bj = values.bias(self.keys[1])?.vector();
        if let Some(j) = jacobians {
            j[0].fill_with_identity();
            j[0].neg_mut();
            j[1].fill_with_identity();
        }
        Ok(DVector::from_column_slice((bj - bi).as_slice()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factor::analytic_and_numeric_jacobians;
    use crate::values::Variable;

    const STEP: f64 = 1e-6;
    const JAC_TOL: f64 = 1e-6;

    fn pose(seed: f64) -> Pose3 {
        Pose3::exp(&Vector6::new(
            0.1 * seed,
            -0.2,
            0.3 + seed,
            1.0 + seed,
            2.0,
            -0.5 * seed,
        ))
    }

    fn assert_jacobians(f: &dyn Factor, v: &Values) {
        for (k, (a, n)) in analytic_and_numeric_jacobians(f, v, STEP)
            .expect("evaluate")
            .into_iter()
            .enumerate()
        {
            let err = (&a - &n).abs().max();
            assert!(
                err < JAC_TOL,
                "{f:?} key {k}: max |analytic - numeric| = {err:e}\n{a}\n{n}"
            );
        }
    }

    fn two_poses() -> (Values, VarId, VarId) {
        let mut v = Values::new();
        let a = v.push(Variable::Pose(pose(0.4)));
        let b = v.push(Variable::Pose(pose(1.3)));
        (v, a, b)
    }

    #[test]
    fn pose_factors_have_correct_jacobians() {
        let (v, a, b) = two_poses();
        let n6 = NoiseModel::isotropic(6, 0.1).expect("noise");
        assert_jacobians(&PosePrior::new(a, pose(0.1), n6.clone()).expect("f"), &v);
        assert_jacobians(&BetweenPose::new(a, b, pose(0.7), n6).expect("f"), &v);
        let n1 = NoiseModel::isotropic(1, 0.1).expect("noise");
        assert_jacobians(&TrackOffset::along(a, b, 0.3, n1).expect("f"), &v);
        let n1 = NoiseModel::isotropic(1, 0.2).expect("noise");
        assert_jacobians(&TrackOffset::across(a, b, -0.1, n1).expect("f"), &v);
        let n3 = NoiseModel::isotropic(3, 0.1).expect("noise");
        let z = Vector3::new(1.0, 2.0, 3.0);
        assert_jacobians(&PositionFix::new(a, z, PositionAxes::Xyz, n3.clone()).expect("f"), &v);
        let n2 = NoiseModel::isotropic(2, 0.1).expect("noise");
        assert_jacobians(&PositionFix::new(a, z, PositionAxes::Xy, n2.clone()).expect("f"), &v);
        assert_jacobians(&Planar::new(b, 0.2, n3).expect("f"), &v);
        let mut v = v;
        let vel = v.push(Variable::Velocity(Vector3::new(20.0, -3.0, 0.5)));
        assert_jacobians(
            &PositionFix::moving(a, vel, -0.04, z, PositionAxes::Xy, n2).expect("f"),
            &v,
        );
    }

    #[test]
    fn line_factors_have_correct_jacobians() {
        let (mut v, a, _) = two_poses();
        let line = HoughLine {
            rho_m: 25.0,
            theta_rad: 0.4,
        };
        let l = v.push(Variable::Line(line));
        let n1 = NoiseModel::isotropic(1, 0.05).expect("noise");
        assert_jacobians(&LineDistance::new(a, l, 20.0, n1.clone()).expect("f"), &v);
        assert_jacobians(&KnownLineDistance::new(a, line, 20.0, n1).expect("f"), &v);
        let n2 = NoiseModel::isotropic(2, 0.2).expect("noise");
        assert_jacobians(&VectorPrior::line(l, line, n2).expect("f"), &v);
    }

    #[test]
    fn line_distance_matches_geometry() {
        // Facing +x from the origin, the wall x = 5 is 5 m ahead; turned 60 degrees, 10 m.
        let wall = HoughLine {
            rho_m: 5.0,
            theta_rad: 0.0,
        };
        let (h, _, _) = forward_distance_to_line(&Pose3::identity(), &wall);
        assert!((h - 5.0).abs() < 1e-12);
        let turned = Pose3::new(
            crate::lie::so3_exp(&Vector3::new(0.0, 0.0, 60f64.to_radians())),
            Vector3::zeros(),
        );
        assert!((forward_distance_to_line(&turned, &wall).0 - 10.0).abs() < 1e-9);
    }

    #[test]
    fn vehicle_and_bias_factors_have_correct_jacobians() {
        let (mut v, a, _) = two_poses();
        let vel = v.push(Variable::Velocity(Vector3::new(1.0, 0.3, -0.2)));
        assert_jacobians(
            &NonHolonomic::new(a, vel, NoiseModel::isotropic(2, 0.1).expect("n")).expect("f"),
            &v,
        );
        let bi = v.push(Variable::Bias(ImuBias::from_vector(&Vector6::new(
            0.1, 0.2, 0.3, 0.01, 0.02, 0.03,
        ))));
        let bj = v.push(Variable::Bias(ImuBias::default()));
        let n6 = NoiseModel::isotropic(6, 0.1).expect("noise");
        assert_jacobians(&BiasRandomWalk::new(bi, bj, n6.clone()).expect("f"), &v);
        assert_jacobians(&VectorPrior::bias(bi, ImuBias::default(), n6).expect("f"), &v);
        let n3 = NoiseModel::isotropic(3, 0.1).expect("noise");
        assert_jacobians(&VectorPrior::velocity(vel, Vector3::zeros(), n3).expect("f"), &v);
    }
}
