//! The estimate's uncertainty about a scalar function of its variables (the along-track
//! distance between two states), from the information of the whole graph: what a Mahalanobis
//! gate on a new measurement of that function needs.
//!
//! For a measurement `z = h(x) + e`, `e ~ N(0, s^2)`, the innovation `h(x_hat) - z` has
//! variance `g^T H^-1 g + s^2`, where `g` is the gradient of `h` at the estimate and `H` the
//! information (Gauss-Newton Hessian) of every factor there. `H^-1` is the joint marginal
//! covariance, so `g^T H^-1 g` is the marginal variance of `h`: for the along-track distance
//! between a state of the current pass and one of an earlier pass, it is the uncertainty of
//! the one relative to the other along every path the graph joins them by (the odometry
//! between them, and the registrations that tied the passes together before).
//!
//! [`WholeGraphInformation`] linearises and factorises the whole graph once; each variance is
//! then one solve with that factor. Its cost is that of one Gauss-Newton step of the whole
//! graph (tens of milliseconds at 2000 states), so the online estimator makes one only for a
//! measurement that the measurement's own sigma cannot accept alone, and keeps it until the
//! estimate moves (the next update).

use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::linear::{Factorization, HessianStructure, Ordering, linearize};
use crate::values::Values;
use crate::{Error, Result};

/// The whole graph's information at one set of values, factorised (see the module docs).
#[derive(Debug)]
pub struct WholeGraphInformation {
    structure: HessianStructure,
    factorization: Factorization,
}

impl WholeGraphInformation {
    /// Linearises the first `factors` factors of `graph` at `values` over every variable and
    /// factorises the information.
    ///
    /// # Errors
    /// A factor that cannot be evaluated; information that is not positive definite even with
    /// a very weak prior on every direction.
    pub fn new(graph: &FactorGraph, factors: usize, values: &Values) -> Result<Self> {
        let all: Vec<usize> = (0..factors.min(graph.len())).collect();
        let ordering = Ordering::all(values);
        let structure = HessianStructure::new(graph, &all, values, &ordering)?;
        let ne = linearize(graph, &all, values, &structure)?;
        let factorization = Factorization::for_covariance(&structure, &ne.hessian)?;
        Ok(Self {
            structure,
            factorization,
        })
    }

    /// Marginal variance `g^T H^-1 g` of the one-dimensional residual of `factor` at `values`
    /// (its noise model is not used: `g` is the residual's own gradient).
    ///
    /// # Errors
    /// A factor that is not one-dimensional, cannot be evaluated, or reaches a variable this
    /// information does not hold.
    pub fn variance(&self, factor: &dyn Factor, values: &Values) -> Result<f64> {
        let g = self.gradient(factor, values)?;
        let x = self.solve(&g);
        Ok(dot(&g, &x).max(0.0))
    }

    /// `H^-1 v` for a vector `v` over every variable (system order, as
    /// [`WholeGraphInformation::gradient`] gives).
    #[must_use]
    pub fn solve(&self, v: &[f64]) -> Vec<f64> {
        let mut x = v.to_vec();
        self.factorization.solve_in_place(&mut x);
        x
    }

    /// The gradient `g` of the one-dimensional residual of `factor` at `values`, over every
    /// variable in system order (zero but for the factor's variables).
    ///
    /// # Errors
    /// As [`WholeGraphInformation::variance`].
    pub fn gradient(&self, factor: &dyn Factor, values: &Values) -> Result<Vec<f64>> {
        if factor.noise().dim() != 1 {
            return Err(Error::BadMeasurement(format!(
                "the variance of a {}-dimensional residual",
                factor.noise().dim()
            )));
        }
        let keys = factor.keys();
        let mut jacobians: Vec<nalgebra::DMatrix<f64>> = keys
            .iter()
            .map(|k| Ok(nalgebra::DMatrix::zeros(1, values.get(*k)?.dim())))
            .collect::<Result<_>>()?;
        factor.evaluate(values, Some(&mut jacobians))?;
        let ordering = self.structure.ordering();
        let mut g = vec![0.0; ordering.dim()];
        for (key, jac) in keys.iter().zip(&jacobians) {
            let (off, dim) = ordering.slot(*key).ok_or(Error::UnknownVariable(key.0))?;
            for c in 0..dim {
                g[off + c] += jac[(0, c)];
            }
        }
        Ok(g)
    }
}

/// `a . b`.
#[must_use]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{PosePrior, TrackOffset};
    use crate::lie::Pose3;
    use crate::noise::NoiseModel;
    use crate::values::{VarId, Variable};
    use nalgebra::{Matrix3, Vector3};

    /// Poses on a line 1 m apart, the first held by a tight prior, each joined to the next by
    /// an along-track distance of sigma `step_sigma`, and optionally a distance of sigma
    /// `closure_sigma` from the first to the last.
    fn chain(n: usize, step_sigma: f64, closure_sigma: Option<f64>) -> (FactorGraph, Values, Vec<VarId>) {
        let mut values = Values::new();
        let ids: Vec<VarId> = (0..n)
            .map(|k| {
                values.push(Variable::Pose(Pose3::new(
                    Matrix3::identity(),
                    Vector3::new(k as f64, 0.0, 0.0),
                )))
            })
            .collect();
        let mut graph = FactorGraph::new();
        let pose = |k: usize| Pose3::new(Matrix3::identity(), Vector3::new(k as f64, 0.0, 0.0));
        graph.add(
            PosePrior::new(ids[0], pose(0), NoiseModel::isotropic(6, 1e-4).expect("test input")).expect("test input"),
        );
        for k in 1..n {
            // the along-track distance and a tight hold on the rest of the relative pose
            graph.add(
                TrackOffset::along(
                    ids[k - 1],
                    ids[k],
                    1.0,
                    NoiseModel::isotropic(1, step_sigma).expect("test input"),
                )
                .expect("test input"),
            );
            graph.add(
                crate::factors::BetweenPose::new(
                    ids[k - 1],
                    ids[k],
                    Pose3::new(Matrix3::identity(), Vector3::new(1.0, 0.0, 0.0)),
                    NoiseModel::diagonal(&[1e-4, 1e-4, 1e-4, 1e3, 1e-4, 1e-4]).expect("test input"),
                )
                .expect("test input"),
            );
        }
        if let Some(s) = closure_sigma {
            graph.add(
                TrackOffset::along(
                    ids[0],
                    ids[n - 1],
                    (n - 1) as f64,
                    NoiseModel::isotropic(1, s).expect("test input"),
                )
                .expect("test input"),
            );
        }
        (graph, values, ids)
    }

    fn along_variance(graph: &FactorGraph, values: &Values, a: VarId, b: VarId) -> f64 {
        let info = WholeGraphInformation::new(graph, graph.len(), values).expect("test input");
        let f = TrackOffset::along(a, b, 0.0, NoiseModel::isotropic(1, 1.0).expect("test input")).expect("test input");
        info.variance(&f, values).expect("test input")
    }

    #[test]
    fn the_relative_variance_adds_up_along_the_chain_and_a_closure_shrinks_it() {
        let (graph, values, ids) = chain(11, 0.1, None);
        // along an open chain the steps' variances add, whatever the absolute uncertainty
        for (a, b) in [(0, 10), (3, 7), (9, 10)] {
            let v = along_variance(&graph, &values, ids[a], ids[b]);
            let want = (b - a) as f64 * 0.01;
            assert!((v - want).abs() < 1e-6 * want.max(1e-3), "{a}->{b}: {v} (want {want})");
        }
        // a closure of sigma 0.1 over the whole chain: two parallel paths, variances combine
        // as resistances (1 / (1/0.1 + 1/0.01)) end to end
        let (graph, values, ids) = chain(11, 0.1, Some(0.1));
        let v = along_variance(&graph, &values, ids[0], ids[10]);
        let want = 1.0 / (1.0 / 0.1 + 1.0 / 0.01);
        assert!((v - want).abs() < 1e-6, "{v} (want {want})");
        // and between two inner states: a path of 4 steps against one of 6 steps plus the closure
        let v = along_variance(&graph, &values, ids[3], ids[7]);
        let want = 1.0 / (1.0 / 0.04 + 1.0 / (0.06 + 0.01));
        assert!((v - want).abs() < 1e-6, "{v} (want {want})");
    }

    #[test]
    fn only_a_one_dimensional_residual_has_a_variance() {
        let (graph, values, ids) = chain(3, 0.1, None);
        let info = WholeGraphInformation::new(&graph, graph.len(), &values).expect("test input");
        let f = PosePrior::new(
            ids[1],
            Pose3::identity(),
            NoiseModel::isotropic(6, 1.0).expect("test input"),
        )
        .expect("test input");
        assert!(info.variance(&f, &values).is_err());
    }
}
