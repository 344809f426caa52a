//! Batch Levenberg-Marquardt over a whole graph.

use std::time::Instant;

use nalgebra::DVector;

use crate::graph::FactorGraph;
use crate::linear::{Factorization, HessianStructure, NormalEquations, Ordering, linearize_split_into, retract};
use crate::values::{Values, Variable};
use crate::{Error, Result};

/// Levenberg-Marquardt settings (defaults as GTSAM's `LevenbergMarquardtParams` in the peer).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmParams {
    /// Outer iterations at most.
    pub max_iterations: usize,
    /// Stop when the error falls by less than this fraction in an iteration.
    pub relative_error_tol: f64,
    /// Stop when the error falls by less than this in an iteration.
    pub absolute_error_tol: f64,
    /// Initial damping.
    pub lambda_initial: f64,
    /// Damping multiplier on a rejected step, divisor on an accepted one.
    pub lambda_factor: f64,
    /// Give up when the damping grows past this.
    pub lambda_max: f64,
    /// Threads that linearise (1: the caller's alone; more split the factors, see
    /// [`crate::linear::linearize_split_into`]).
    pub linearize_threads: usize,
}

impl Default for LmParams {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            relative_error_tol: 1e-6,
            absolute_error_tol: 1e-6,
            lambda_initial: 1e-5,
            lambda_factor: 10.0,
            lambda_max: 1e5,
            linearize_threads: 1,
        }
    }
}

/// How an optimisation went. The values are always the best found, converged or not.
#[derive(Debug, Clone, PartialEq)]
pub struct LmReport {
    /// Accepted iterations.
    pub iterations: usize,
    /// Linear solves, accepted or not.
    pub linear_solves: usize,
    /// Error before.
    pub initial_error: f64,
    /// Error after.
    pub final_error: f64,
    /// True when a tolerance was met (false: iteration or damping limit).
    pub converged: bool,
    /// Wall time, seconds.
    pub seconds: f64,
    /// Of which linearising, seconds.
    pub linearize_s: f64,
    /// Of which numeric factorisation and solve, seconds.
    pub solve_s: f64,
    /// Of which evaluating candidate steps, seconds.
    pub evaluate_s: f64,
}

/// Levenberg-Marquardt on the factors `factors` of `graph` over the free variables of
/// `ordering`; `values` is moved to the solution. `structure`, when given, is reused if it
/// fits (and replaced otherwise) so repeated solves of the same structure skip the symbolic
/// factorisation.
///
/// # Errors
/// A factor that cannot be evaluated, or a faer failure on the structure.
pub fn levenberg_marquardt(
    graph: &FactorGraph,
    factors: &[usize],
    values: &mut Values,
    ordering: &Ordering,
    params: &LmParams,
    structure: &mut Option<HessianStructure>,
) -> Result<LmReport> {
    levenberg_marquardt_keep_hessian(graph, factors, values, ordering, params, structure).map(|(r, _)| r)
}

/// What [`levenberg_marquardt_keep_hessian`] hands back beside its report.
#[derive(Debug)]
pub struct KeptHessian {
    /// The last normal equations it built.
    pub equations: NormalEquations,
    /// The factorisation of their `H + lambda I` and its `lambda`, when the last one made was
    /// of them (not when the iterations ended on a relinearisation or a failed factorisation).
    pub factorization: Option<(Factorization, f64)>,
}

/// [`levenberg_marquardt`], also handing back the last normal equations it built (at the last
/// linearisation point: the solution, or the point one accepted step before it), for a
/// covariance without another linearisation, and their factorisation when it has one.
///
/// # Errors
/// As [`levenberg_marquardt`].
pub fn levenberg_marquardt_keep_hessian(
    graph: &FactorGraph,
    factors: &[usize],
    values: &mut Values,
    ordering: &Ordering,
    params: &LmParams,
    structure: &mut Option<HessianStructure>,
) -> Result<(LmReport, KeptHessian)> {
    let start = Instant::now();
    faer::set_global_parallelism(faer::Par::Seq);
    let st = match structure.take() {
        Some(mut s) if s.fits(graph, factors, ordering) => {
            s.rebind(values, ordering);
            s
        }
        _ => HessianStructure::new(graph, factors, values, ordering)?,
    };
    let mut lambda = params.lambda_initial;
    let mut factorization: Option<Factorization> = None;
    let t = Instant::now();
    let mut ne = NormalEquations::default();
    let mut spare = Vec::new();
    let threads = params.linearize_threads;
    linearize_split_into(graph, factors, values, &st, (&mut ne, &mut spare), threads)?;
    let first_linearize_s = t.elapsed().as_secs_f64();
    let initial_error = ne.error;
    let mut report = LmReport {
        iterations: 0,
        linear_solves: 0,
        initial_error,
        final_error: initial_error,
        converged: false,
        seconds: 0.0,
        linearize_s: 0.0,
        solve_s: 0.0,
        evaluate_s: 0.0,
    };
    if ordering.dim() == 0 {
        report.converged = true;
        *structure = Some(st);
        return Ok((
            report,
            KeptHessian {
                equations: ne,
                factorization: None,
            },
        ));
    }
    report.linearize_s = first_linearize_s;
    // The lambda of the factorisation held, while it is of `ne`.
    let mut factored_lambda: Option<f64> = None;
    'outer: while report.iterations < params.max_iterations {
        loop {
            report.linear_solves += 1;
            let t = Instant::now();
            // The factorisation's buffers are kept for the next solve.
            let factored = match factorization.as_mut() {
                Some(f) => f.refactor(&st, &ne.hessian, lambda).map(|()| &*f),
                None => Factorization::new(&st, &ne.hessian, lambda).map(|f| &*factorization.insert(f)),
            };
            factored_lambda = factored.is_ok().then_some(lambda);
            let step = match factored {
                Ok(f) => {
                    let mut dx = ne.gradient.as_slice().to_vec();
                    f.solve_in_place(&mut dx);
                    Some(-DVector::from_vec(dx))
                }
                Err(Error::LinearSolve(_)) => None,
                Err(e) => return Err(e),
            };
            report.solve_s += t.elapsed().as_secs_f64();
            if let Some(dx) = step {
                // Retract in place; a rejected step puts the free variables back.
                let backup: Vec<Variable> = ordering
                    .free_vars()
                    .iter()
                    .map(|id| values.get(*id).copied())
                    .collect::<Result<_>>()?;
                let t = Instant::now();
                retract(values, st.ordering(), &dx)?;
                let new_error = factors
                    .iter()
                    .map(|&f| graph.factors()[f].error(values))
                    .sum::<Result<f64>>()?;
                report.evaluate_s += t.elapsed().as_secs_f64();
                if !(new_error.is_finite() && new_error <= ne.error) {
                    for (id, v) in ordering.free_vars().iter().zip(backup) {
                        values.set(*id, v)?;
                    }
                } else {
                    let decrease = ne.error - new_error;
                    report.iterations += 1;
                    report.final_error = new_error;
                    lambda = (lambda / params.lambda_factor).max(1e-12);
                    let converged =
                        decrease <= params.absolute_error_tol || decrease <= params.relative_error_tol * ne.error;
                    if converged {
                        report.converged = true;
                        break 'outer;
                    }
                    if report.iterations >= params.max_iterations {
                        // A linearisation here would serve no step (the normal equations
                        // handed back stay one accepted step behind, as documented).
                        break 'outer;
                    }
                    let t = Instant::now();
                    factored_lambda = None;
                    linearize_split_into(graph, factors, values, &st, (&mut ne, &mut spare), threads)?;
                    report.linearize_s += t.elapsed().as_secs_f64();
                    break;
                }
            }
            lambda *= params.lambda_factor;
            if lambda > params.lambda_max {
                tracing::debug!(lambda, "Levenberg-Marquardt: damping limit reached");
                report.converged = true;
                break 'outer;
            }
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    *structure = Some(st);
    let factorization = factorization.zip(factored_lambda);
    Ok((
        report,
        KeptHessian {
            equations: ne,
            factorization,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenPose, PosePrior};
    use crate::lie::Pose3;
    use crate::noise::{NoiseModel, RobustKernel};
    use crate::values::{VarId, Variable};
    use nalgebra::Vector6;

    #[test]
    fn pose_chain_converges_to_the_measurements() {
        let mut values = Values::new();
        let mut graph = FactorGraph::new();
        let n6 = NoiseModel::isotropic(6, 0.1).expect("noise");
        let step = Pose3::exp(&Vector6::new(0.0, 0.0, 0.3, 1.0, 0.0, 0.0));
        let ids: Vec<VarId> = (0..6)
            .map(|k| {
                values.push(Variable::Pose(Pose3::exp(&Vector6::new(
                    0.0,
                    0.1,
                    0.0,
                    f64::from(k),
                    2.0,
                    0.0,
                ))))
            })
            .collect();
        graph.add(PosePrior::new(ids[0], Pose3::identity(), n6.clone()).expect("f"));
        for w in ids.windows(2) {
            graph.add(BetweenPose::new(w[0], w[1], step, n6.clone()).expect("f"));
        }
        // A wrong loop closure that the Huber kernel should keep from dominating.
        graph.add(
            BetweenPose::new(
                ids[0],
                ids[5],
                Pose3::identity(),
                n6.robust(RobustKernel::Huber { k: 1.345 }),
            )
            .expect("f"),
        );
        let all: Vec<usize> = (0..graph.len()).collect();
        let ord = Ordering::all(&values);
        let mut st = None;
        let rep = levenberg_marquardt(&graph, &all, &mut values, &ord, &LmParams::default(), &mut st).expect("lm");
        assert!(rep.converged && rep.final_error < rep.initial_error, "{rep:?}");
        let p1 = values.pose(ids[1]).expect("pose");
        assert!(step.between(p1).log().norm() < 0.2, "{p1:?}");
        // A second solve from the optimum reuses the structure and does not move.
        let again = levenberg_marquardt(&graph, &all, &mut values, &ord, &LmParams::default(), &mut st).expect("lm");
        assert!((again.final_error - rep.final_error).abs() < 1e-6 * rep.final_error.max(1.0));
    }
}
