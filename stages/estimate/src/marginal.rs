//! Marginalisation of the states that leave a fixed-lag smoother's window: the Schur complement
//! of their linearised factors as a linear prior ([`MarginalPrior`]) on the variables they were
//! joined to.
//!
//! The prior's Jacobian is the square root of the marginal information, fixed where it was
//! computed (first-estimate Jacobians); its residual follows the variables through their local
//! coordinates about that point. A prior whose point a whole-graph re-solve has moved is
//! re-centred there ([`MarginalPrior::recentred`]), keeping its information: the re-solve's
//! values are the optimum of every factor, the marginalised ones included.

use nalgebra::{DMatrix, DVector, SymmetricEigen};

use crate::factor::Factor;
use crate::noise::NoiseModel;
use crate::values::{Values, VarId, Variable};
use crate::{Error, Result};

/// Eigenvalues below this fraction of the largest are treated as zero (directions the
/// marginalised factors say nothing about).
const RELATIVE_EIGEN_FLOOR: f64 = 1e-10;

/// A linear Gaussian prior `0.5 |A d + b|^2` on the local coordinates `d` of its variables about
/// the point where it was made: what the marginalised states said about the ones they left.
#[derive(Debug, Clone)]
pub struct MarginalPrior {
    keys: Vec<VarId>,
    at: Vec<Variable>,
    /// `A`: rows whitened (the noise model is the identity).
    sqrt_information: DMatrix<f64>,
    /// `b`.
    offset: DVector<f64>,
    noise: NoiseModel,
}

impl MarginalPrior {
    /// The prior's variables.
    #[must_use]
    pub fn variables(&self) -> &[VarId] {
        &self.keys
    }

    /// Its information `A^T A` over the variables' tangent coordinates, in key order.
    #[must_use]
    pub fn information(&self) -> DMatrix<f64> {
        self.sqrt_information.transpose() * &self.sqrt_information
    }

    /// The same information about the variables' values in `values`, with its gradient there
    /// `-balance` (as far as the information reaches): with `balance` the gradient of the other
    /// factors on these variables, `values` stays a stationary point of the prior and them.
    ///
    /// # Errors
    /// A variable missing from `values`, or a `balance` of the wrong length.
    pub fn recentred(&self, values: &Values, balance: &DVector<f64>) -> Result<Self> {
        if balance.len() != self.sqrt_information.ncols() {
            return Err(Error::LinearSolve(format!(
                "re-centring a prior on {} coordinates with a gradient of {}",
                self.sqrt_information.ncols(),
                balance.len()
            )));
        }
        let at = self
            .keys
            .iter()
            .map(|k| values.get(*k).copied())
            .collect::<Result<_>>()?;
        // The rows of A are orthogonal (scaled eigenvectors), so A^T b = -balance on their span
        // takes b_i = -(a_i . balance) / |a_i|^2.
        let offset = DVector::from_iterator(
            self.sqrt_information.nrows(),
            self.sqrt_information
                .row_iter()
                .map(|a| -a.transpose().dot(balance) / a.norm_squared()),
        );
        Ok(Self {
            at,
            offset,
            ..self.clone()
        })
    }
}

impl Factor for MarginalPrior {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }
    fn noise(&self) -> &NoiseModel {
        &self.noise
    }
    fn evaluate(&self, values: &Values, jacobians: Option<&mut [DMatrix<f64>]>) -> Result<DVector<f64>> {
        let mut r = self.offset.clone();
        let mut col = 0;
        for (key, at) in self.keys.iter().zip(&self.at) {
            let d = at.local(values.get(*key)?).ok_or(Error::WrongKind {
                id: key.0,
                expected: "variable of the kind its marginal prior was made on",
            })?;
            r += self.sqrt_information.columns(col, d.len()) * &d;
            col += d.len();
        }
        // First-estimate Jacobians: the local coordinates' derivative at the prior's point.
        if let Some(jac) = jacobians {
            let mut col = 0;
            for (j, at) in jac.iter_mut().zip(&self.at) {
                let d = at.dim();
                j.copy_from(&self.sqrt_information.columns(col, d));
                col += d;
            }
        }
        Ok(r)
    }
}

/// Dense normal equations `(H, g)` of `factors` at `values` (whitened, robust-reweighted) over
/// the variables `vars` in that order; every other variable a factor touches is held at its
/// value.
///
/// # Errors
/// A factor that cannot be evaluated, or a variable listed twice.
pub fn normal_equations(
    factors: &[&dyn Factor],
    values: &Values,
    vars: &[VarId],
) -> Result<(DMatrix<f64>, DVector<f64>)> {
    let mut slot: std::collections::BTreeMap<VarId, (usize, usize)> = std::collections::BTreeMap::new();
    let mut n = 0;
    for id in vars {
        let d = values.get(*id)?.dim();
        if slot.insert(*id, (n, d)).is_some() {
            return Err(Error::LinearSolve(format!("variable {} listed twice", id.0)));
        }
        n += d;
    }
    let mut h = DMatrix::zeros(n, n);
    let mut g = DVector::zeros(n);
    let (mut info, mut hf, mut gf) = (
        crate::linear::Information::default(),
        DMatrix::zeros(0, 0),
        DVector::zeros(0),
    );
    for f in factors {
        let noise = f.noise();
        let m = noise.dim();
        let mut jac: Vec<DMatrix<f64>> = f
            .keys()
            .iter()
            .map(|k| values.get(*k).map(|v| DMatrix::zeros(m, v.dim())))
            .collect::<Result<_>>()?;
        let r = f.evaluate(values, Some(&mut jac))?;
        // The free keys' columns side by side.
        let free: Vec<(usize, usize, usize)> = f
            .keys()
            .iter()
            .enumerate()
            .filter_map(|(i, k)| slot.get(k).map(|(off, d)| (i, *off, *d)))
            .collect();
        let cols: usize = free.iter().map(|(_, _, d)| d).sum();
        if cols == 0 {
            continue;
        }
        let mut a = DMatrix::zeros(m, cols);
        let mut c0 = 0;
        for &(i, _, d) in &free {
            a.columns_mut(c0, d).copy_from(&jac[i]);
            c0 += d;
        }
        crate::linear::whitened_gram(noise, &a, &r, &mut info, &mut hf, &mut gf);
        let mut ca = 0;
        for &(_, off_a, da) in &free {
            let mut gb = g.rows_mut(off_a, da);
            gb += gf.rows(ca, da);
            let mut cb = 0;
            for &(_, off_b, db) in &free {
                let mut blk = h.view_mut((off_a, off_b), (da, db));
                blk += hf.view((ca, cb), (da, db));
                cb += db;
            }
            ca += da;
        }
    }
    Ok((h, g))
}

/// Marginalises the variables `marginalised` out of `factors` linearised at `values` (whitened,
/// robust-reweighted), with `kept` the other variables left free; every other variable a factor
/// touches is held at its value. The Schur complement becomes a [`MarginalPrior`] on `kept`
/// (`None` when it carries no information).
///
/// # Errors
/// A factor that cannot be evaluated, a variable in both lists, or marginalised variables that
/// the factors do not determine (their information singular).
pub fn marginalise(
    factors: &[&dyn Factor],
    values: &Values,
    marginalised: &[VarId],
    kept: &[VarId],
) -> Result<Option<MarginalPrior>> {
    let vars: Vec<VarId> = marginalised.iter().chain(kept).copied().collect();
    let (h, g) = normal_equations(factors, values, &vars)?;
    let n = h.nrows();
    let nm: usize = marginalised
        .iter()
        .map(|id| values.get(*id).map(Variable::dim))
        .sum::<Result<usize>>()?;
    let nk = n - nm;
    if nk == 0 {
        return Ok(None);
    }
    // Schur complement: H_kk - H_km H_mm^-1 H_mk, g_k - H_km H_mm^-1 g_m.
    let hmm = h.view((0, 0), (nm, nm)).into_owned();
    let chol = hmm.cholesky().ok_or_else(|| {
        Error::LinearSolve("marginalised variables not determined by their factors (information singular)".into())
    })?;
    let hmk = h.view((0, nm), (nm, nk)).into_owned();
    let x = chol.solve(&hmk);
    let y = chol.solve(&g.rows(0, nm).into_owned());
    let hkk = h.view((nm, nm), (nk, nk)) - hmk.transpose() * &x;
    let gk = g.rows(nm, nk) - hmk.transpose() * &y;
    let hkk = 0.5 * (&hkk + hkk.transpose());
    // A square root of a positive semi-definite matrix: keep the directions with information.
    let eig = SymmetricEigen::new(hkk);
    let largest = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    if largest <= 0.0 || !largest.is_finite() {
        return Ok(None);
    }
    let keep: Vec<usize> = (0..nk)
        .filter(|&i| eig.eigenvalues[i] > RELATIVE_EIGEN_FLOOR * largest)
        .collect();
    let mut a = DMatrix::zeros(keep.len(), nk);
    let mut b = DVector::zeros(keep.len());
    for (row, &i) in keep.iter().enumerate() {
        let lambda = eig.eigenvalues[i];
        let v = eig.eigenvectors.column(i);
        a.row_mut(row).copy_from(&(v.transpose() * lambda.sqrt()));
        b[row] = v.dot(&gk) / lambda.sqrt();
    }
    let at = kept.iter().map(|k| values.get(*k).copied()).collect::<Result<_>>()?;
    Ok(Some(MarginalPrior {
        keys: kept.to_vec(),
        at,
        sqrt_information: a,
        offset: b,
        noise: NoiseModel::isotropic(keep.len(), 1.0)?,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenPose, PosePrior};
    use crate::graph::FactorGraph;
    use crate::lie::Pose3;
    use crate::linear::{Factorization, HessianStructure, Ordering, linearize, marginal_covariance};
    use nalgebra::Vector6;

    fn chain() -> (FactorGraph, Values, Vec<VarId>) {
        let mut values = Values::new();
        let mut graph = FactorGraph::new();
        let prior = NoiseModel::diagonal(&[0.01, 0.01, 0.02, 0.1, 0.1, 0.1]).expect("noise");
        let odo = NoiseModel::diagonal(&[0.02, 0.03, 0.05, 0.2, 0.1, 0.3]).expect("noise");
        let step = Pose3::exp(&Vector6::new(0.01, -0.02, 0.2, 1.0, 0.1, 0.0));
        let ids: Vec<VarId> = (0..5)
            .map(|k| {
                let wobble = f64::from(k) * 0.05;
                values.push(Variable::Pose(Pose3::exp(&Vector6::new(
                    wobble,
                    -wobble,
                    0.2 * f64::from(k),
                    f64::from(k),
                    wobble,
                    0.0,
                ))))
            })
            .collect();
        graph.add(PosePrior::new(ids[0], Pose3::identity(), prior).expect("f"));
        for w in ids.windows(2) {
            graph.add(BetweenPose::new(w[0], w[1], step, odo.clone()).expect("f"));
        }
        // A second path from the first pose to the third, so that the prior is on two poses.
        graph.add(BetweenPose::new(ids[0], ids[2], step.compose(&step), odo).expect("f"));
        (graph, values, ids)
    }

    /// The factors of `graph` on `id`.
    fn factors_on(graph: &FactorGraph, id: VarId) -> Vec<&dyn Factor> {
        graph
            .factors()
            .iter()
            .filter(|f| f.keys().contains(&id))
            .map(|f| f.as_ref())
            .collect()
    }

    #[test]
    fn the_prior_carries_the_marginal_information_of_what_it_replaced() {
        let (graph, values, ids) = chain();
        // Marginalise pose 0 out of the factors on it: the prior and the two odometry factors.
        let prior = marginalise(&factors_on(&graph, ids[0]), &values, &[ids[0]], &[ids[1], ids[2]])
            .expect("marginalise")
            .expect("information");
        // Against the dense Schur complement of the whole linearised graph.
        let all: Vec<usize> = (0..graph.len()).collect();
        let ordering = Ordering::all(&values);
        let st = HessianStructure::new(&graph, &all, &values, &ordering).expect("structure");
        let ne = linearize(&graph, &all, &values, &st).expect("linearise");
        let f = Factorization::new(&st, &ne.hessian, 0.0).expect("factor");
        // The joint covariance of poses 1 and 2 in the full graph equals that of the graph with
        // pose 0 replaced by the prior.
        let mut reduced = FactorGraph::new();
        for f in graph.factors().iter().filter(|f| !f.keys().contains(&ids[0])) {
            reduced.add_shared(f.clone());
        }
        reduced.add(prior.clone());
        let free = Ordering::free(&values, &ids[1..]);
        let red_all: Vec<usize> = (0..reduced.len()).collect();
        let st2 = HessianStructure::new(&reduced, &red_all, &values, &free).expect("structure");
        let ne2 = linearize(&reduced, &red_all, &values, &st2).expect("linearise");
        let f2 = Factorization::new(&st2, &ne2.hessian, 0.0).expect("factor");
        for id in &ids[1..] {
            let full = marginal_covariance(&f, st.ordering(), *id).expect("cov");
            let red = marginal_covariance(&f2, st2.ordering(), *id).expect("cov");
            assert!(
                (&full - &red).norm() < 1e-9 * full.norm(),
                "pose {}: {full} vs {red}",
                id.0
            );
        }
        // The same gradient on the kept variables too: one Gauss-Newton step of either graph
        // moves them alike.
        let mut step_full = ne.gradient.as_slice().to_vec();
        f.solve_in_place(&mut step_full);
        let mut step_red = ne2.gradient.as_slice().to_vec();
        f2.solve_in_place(&mut step_red);
        for id in &ids[1..] {
            let (a, d) = st.ordering().slot(*id).expect("slot");
            let (b, _) = st2.ordering().slot(*id).expect("slot");
            for i in 0..d {
                assert!(
                    (step_full[a + i] - step_red[b + i]).abs() < 1e-9 * (1.0 + step_full[a + i].abs()),
                    "pose {} component {i}",
                    id.0
                );
            }
        }
        // Re-centred on the same point against the rest of the graph's gradient there, the
        // prior's own gradient cancels it, with the same information.
        let rest: Vec<&dyn Factor> = reduced.factors()[..reduced.len() - 1]
            .iter()
            .map(|f| f.as_ref())
            .collect();
        let (_, g_rest) = normal_equations(&rest, &values, &ids[1..3]).expect("normal equations");
        let moved = prior.recentred(&values, &g_rest).expect("recentre");
        assert!((moved.information() - prior.information()).norm() < 1e-12 * prior.information().norm());
        let (_, g_prior) = normal_equations(&[&moved as &dyn Factor], &values, &ids[1..3]).expect("normal equations");
        assert!(
            (&g_prior + &g_rest).norm() < 1e-9 * g_rest.norm(),
            "{g_prior} vs {g_rest}"
        );
        assert!(prior.recentred(&values, &DVector::zeros(3)).is_err());
    }

    #[test]
    fn undetermined_marginalised_variables_are_an_error() {
        let (graph, values, ids) = chain();
        // Poses 3 and 4 from the one odometry factor between them: six directions free.
        assert!(marginalise(&factors_on(&graph, ids[4]), &values, &[ids[3], ids[4]], &[ids[2]]).is_err());
    }
}
