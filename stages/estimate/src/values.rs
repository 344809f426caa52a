//! Variables of the estimation problem and the container that holds their current values.

use nalgebra::{DVector, DVectorView, Vector3, Vector6};

use crate::lie::Pose3;
use crate::{Error, Result};

/// Index of a variable in [`Values`] (and so in the graph).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VarId(pub usize);

/// Accelerometer and gyroscope biases; tangent order `[acc, gyro]` as GTSAM's `ConstantBias`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ImuBias {
    /// Accelerometer bias, m/s^2.
    pub acc_mps2: Vector3<f64>,
    /// Gyroscope bias, rad/s.
    pub gyro_radps: Vector3<f64>,
}

impl ImuBias {
    /// As a 6-vector `[acc, gyro]`.
    #[must_use]
    pub fn vector(&self) -> Vector6<f64> {
        Vector6::new(
            self.acc_mps2.x,
            self.acc_mps2.y,
            self.acc_mps2.z,
            self.gyro_radps.x,
            self.gyro_radps.y,
            self.gyro_radps.z,
        )
    }

    /// From a 6-vector `[acc, gyro]`.
    #[must_use]
    pub fn from_vector(v: &Vector6<f64>) -> Self {
        Self {
            acc_mps2: v.fixed_rows::<3>(0).into_owned(),
            gyro_radps: v.fixed_rows::<3>(3).into_owned(),
        }
    }
}

/// A 2-D line in Hough normal form: points `(x, y)` with `x cos(theta) + y sin(theta) = rho`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HoughLine {
    /// Distance of the line from the origin along its normal, metres.
    pub rho_m: f64,
    /// Angle of the normal, radians.
    pub theta_rad: f64,
}

/// One variable's value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Variable {
    /// SE(3) pose `world_from_body` (tangent dimension 6).
    Pose(Pose3),
    /// Velocity in the world frame, m/s (dimension 3).
    Velocity(Vector3<f64>),
    /// IMU biases (dimension 6).
    Bias(ImuBias),
    /// A Hough line (dimension 2).
    Line(HoughLine),
}

impl Variable {
    /// Tangent-space dimension.
    #[must_use]
    pub fn dim(&self) -> usize {
        match self {
            Self::Pose(_) | Self::Bias(_) => 6,
            Self::Velocity(_) => 3,
            Self::Line(_) => 2,
        }
    }

    /// The value moved by `delta` (length [`Variable::dim`]) in its tangent space.
    #[must_use]
    pub fn retract(&self, delta: DVectorView<'_, f64>) -> Self {
        match self {
            Self::Pose(p) => Self::Pose(p.retract(&Vector6::from_iterator(delta.iter().copied()))),
            Self::Velocity(v) => Self::Velocity(v + Vector3::from_iterator(delta.iter().copied())),
            Self::Bias(b) => Self::Bias(ImuBias::from_vector(
                &(b.vector() + Vector6::from_iterator(delta.iter().copied())),
            )),
            Self::Line(l) => Self::Line(HoughLine {
                rho_m: l.rho_m + delta[0],
                theta_rad: l.theta_rad + delta[1],
            }),
        }
    }

    /// The inverse of [`Variable::retract`]: `delta` with `self.retract(delta) = other`, or
    /// `None` when `other` is another kind of variable.
    #[must_use]
    pub fn local(&self, other: &Self) -> Option<DVector<f64>> {
        Some(match (self, other) {
            (Self::Pose(a), Self::Pose(b)) => DVector::from_column_slice(a.local(b).as_slice()),
            (Self::Velocity(a), Self::Velocity(b)) => DVector::from_column_slice((b - a).as_slice()),
            (Self::Bias(a), Self::Bias(b)) => DVector::from_column_slice((b.vector() - a.vector()).as_slice()),
            (Self::Line(a), Self::Line(b)) => DVector::from_vec(vec![b.rho_m - a.rho_m, b.theta_rad - a.theta_rad]),
            _ => return None,
        })
    }
}

/// The current value of every variable, indexed by [`VarId`].
#[derive(Debug, Clone, Default)]
pub struct Values {
    vars: Vec<Variable>,
}

impl Values {
    /// No variables.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a variable and returns its id.
    pub fn push(&mut self, v: Variable) -> VarId {
        self.vars.push(v);
        VarId(self.vars.len() - 1)
    }

    /// Number of variables.
    #[must_use]
    pub fn len(&self) -> usize {
        self.vars.len()
    }

    /// True when there are no variables.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.vars.is_empty()
    }

    /// Total tangent dimension.
    #[must_use]
    pub fn dim(&self) -> usize {
        self.vars.iter().map(Variable::dim).sum()
    }

    /// The variable `id`.
    ///
    /// # Errors
    /// [`Error::UnknownVariable`].
    pub fn get(&self, id: VarId) -> Result<&Variable> {
        self.vars.get(id.0).ok_or(Error::UnknownVariable(id.0))
    }

    /// Replaces the value of `id`.
    ///
    /// # Errors
    /// [`Error::UnknownVariable`].
    pub fn set(&mut self, id: VarId, v: Variable) -> Result<()> {
        let slot = self.vars.get_mut(id.0).ok_or(Error::UnknownVariable(id.0))?;
        *slot = v;
        Ok(())
    }

    /// All variables in id order.
    #[must_use]
    pub fn as_slice(&self) -> &[Variable] {
        &self.vars
    }

    /// The pose `id`.
    ///
    /// # Errors
    /// Unknown id, or a variable of another kind.
    pub fn pose(&self, id: VarId) -> Result<&Pose3> {
        match self.get(id)? {
            Variable::Pose(p) => Ok(p),
            _ => Err(Error::WrongKind {
                id: id.0,
                expected: "pose",
            }),
        }
    }

    /// The velocity `id`.
    ///
    /// # Errors
    /// Unknown id, or a variable of another kind.
    pub fn velocity(&self, id: VarId) -> Result<&Vector3<f64>> {
        match self.get(id)? {
            Variable::Velocity(v) => Ok(v),
            _ => Err(Error::WrongKind {
                id: id.0,
                expected: "velocity",
            }),
        }
    }

    /// The IMU bias `id`.
    ///
    /// # Errors
    /// Unknown id, or a variable of another kind.
    pub fn bias(&self, id: VarId) -> Result<&ImuBias> {
        match self.get(id)? {
            Variable::Bias(b) => Ok(b),
            _ => Err(Error::WrongKind {
                id: id.0,
                expected: "IMU bias",
            }),
        }
    }

    /// The Hough line `id`.
    ///
    /// # Errors
    /// Unknown id, or a variable of another kind.
    pub fn line(&self, id: VarId) -> Result<&HoughLine> {
        match self.get(id)? {
            Variable::Line(l) => Ok(l),
            _ => Err(Error::WrongKind {
                id: id.0,
                expected: "line",
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn local_inverts_the_retraction() {
        let pose = Variable::Pose(Pose3::exp(&Vector6::new(0.3, -0.2, 1.0, 2.0, -1.0, 0.5)));
        let velocity = Variable::Velocity(Vector3::new(1.0, -2.0, 0.5));
        let bias = Variable::Bias(ImuBias::from_vector(&Vector6::new(0.1, 0.2, -0.3, 0.01, 0.02, 0.03)));
        let line = Variable::Line(HoughLine {
            rho_m: 4.0,
            theta_rad: 0.7,
        });
        for v in [pose, velocity, bias, line] {
            let d = DVector::from_fn(v.dim(), |i, _| {
                0.05 * (i as f64 + 1.0) * if i % 2 == 0 { 1.0 } else { -1.0 }
            });
            let moved = v.retract(d.as_view());
            let back = v.local(&moved).expect("same kind");
            assert!((back - &d).norm() < 1e-12, "{v:?}");
        }
        assert!(pose.local(&velocity).is_none());
    }
}
