//! The factor trait and the numerical-derivative check every factor's tests use.

use nalgebra::{DMatrix, DVector};

use crate::Result;
use crate::noise::NoiseModel;
use crate::values::{Values, VarId};

/// A measurement constraint on a few variables.
///
/// `evaluate` returns the unwhitened residual `h(x) - z` (in the measurement's tangent
/// space) and, when asked, its Jacobian with respect to each key's tangent perturbation
/// (`jacobians[k]` is pre-sized to `noise().dim() x dim(keys()[k])` by the caller).
pub trait Factor: Send + Sync + std::fmt::Debug {
    /// The variables this factor touches.
    fn keys(&self) -> &[VarId];
    /// Measurement noise (and robust kernel).
    fn noise(&self) -> &NoiseModel;
    /// Residual and optional Jacobians at `values`.
    ///
    /// # Errors
    /// A key that is missing from `values` or of the wrong kind.
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>>;

    /// The factor's contribution to the graph error (GTSAM's definition).
    ///
    /// # Errors
    /// As [`Factor::evaluate`].
    fn error(&self, values: &Values) -> Result<f64> {
        Ok(self.noise().error(&self.evaluate(values, None)?))
    }
}

/// Jacobians of `factor` at `values`: analytical (from `evaluate`) and by central differences
/// through each variable's retraction. Used by the tests of every factor.
///
/// # Errors
/// As [`Factor::evaluate`].
pub fn analytic_and_numeric_jacobians(
    factor: &dyn Factor,
    values: &Values,
    step: f64,
) -> Result<Vec<(DMatrix<f64>, DMatrix<f64>)>> {
    let m = factor.noise().dim();
    let mut analytic: Vec<DMatrix<f64>> = factor
        .keys()
        .iter()
        .map(|k| values.get(*k).map(|v| DMatrix::zeros(m, v.dim())))
        .collect::<Result<_>>()?;
    factor.evaluate(values, Some(&mut analytic))?;
    let mut out = Vec::new();
    for (key, a) in factor.keys().iter().zip(analytic) {
        let var = *values.get(*key)?;
        let mut num = DMatrix::zeros(m, var.dim());
        for c in 0..var.dim() {
            let mut d = DVector::zeros(var.dim());
            d[c] = step;
            let mut plus = values.clone();
            plus.set(*key, var.retract(d.as_view()))?;
            d[c] = -step;
            let mut minus = values.clone();
            minus.set(*key, var.retract(d.as_view()))?;
            let col = (factor.evaluate(&plus, None)? - factor.evaluate(&minus, None)?) / (2.0 * step);
            num.set_column(c, &col);
        }
        out.push((a, num));
    }
    Ok(out)
}
