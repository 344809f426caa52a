//! Gauss-Newton linearisation into sparse normal equations and their sparse Cholesky solve.
//!
//! The Hessian `J^T J` is stored block-sparse in compressed columns (lower block triangle):
//! the structure depends only on which variables share a factor, so it is built once per
//! structure and the faer symbolic factorisation (fill-reducing ordering and elimination tree)
//! is reused for every numeric factorisation with that structure.

use std::collections::BTreeSet;

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::cholesky::{CholeskySymbolicParams, LltRef, SymbolicCholesky, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Par, Side};
use nalgebra::{DMatrix, DVector};

use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::values::{Values, VarId};
use crate::{Error, Result};

/// Which variables are solved for, and where each sits in the linear system.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ordering {
    /// Per variable id: `(offset, dim)` when free, `None` when held fixed.
    slots: Vec<Option<(usize, usize)>>,
    /// Per variable id: its position in `free`.
    position: Vec<Option<usize>>,
    free: Vec<VarId>,
    dim: usize,
}

impl Ordering {
    /// Every variable free, in id order.
    #[must_use]
    pub fn all(values: &Values) -> Self {
        let ids: Vec<VarId> = (0..values.len()).map(VarId).collect();
        Self::free(values, &ids)
    }

    /// Only `free` variables are solved for (in the given order); the rest are constants.
    #[must_use]
    pub fn free(values: &Values, free: &[VarId]) -> Self {
        let mut slots = vec![None; values.len()];
        let mut position = vec![None; values.len()];
        let mut dim = 0;
        let mut kept = Vec::with_capacity(free.len());
        for id in free {
            if let Ok(v) = values.get(*id)
                && slots[id.0].is_none()
            {
                slots[id.0] = Some((dim, v.dim()));
                position[id.0] = Some(kept.len());
                dim += v.dim();
                kept.push(*id);
            }
        }
        Self {
            slots,
            position,
            free: kept,
            dim,
        }
    }

    /// `(offset, dim)` of a free variable.
    #[must_use]
    pub fn slot(&self, id: VarId) -> Option<(usize, usize)> {
        self.slots.get(id.0).copied().flatten()
    }

    /// Position of a free variable in [`Ordering::free_vars`].
    #[must_use]
    pub fn position(&self, id: VarId) -> Option<usize> {
        self.position.get(id.0).copied().flatten()
    }

    /// The free variables in system order.
    #[must_use]
    pub fn free_vars(&self) -> &[VarId] {
        &self.free
    }

    /// Dimension of the linear system.
    #[must_use]
    pub fn dim(&self) -> usize {
        self.dim
    }
}

/// The compressed-column structure of `J^T J` for one ordering and factor set, and the
/// symbolic Cholesky of that structure.
#[derive(Debug, Clone)]
pub struct HessianStructure {
    dim: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Index of each diagonal entry in the value array.
    diag: Vec<usize>,
    /// Per column variable position: `(row variable position, offset of its rows inside each
    /// of the column variable's columns)`, sorted by row variable.
    segments: Vec<Vec<(usize, usize)>>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// The canonical block pattern the structure was built from (reuse key).
    pattern: Vec<(usize, usize)>,
    dims: Vec<usize>,
}

fn block_pattern(graph: &FactorGraph, factors: &[usize], ordering: &Ordering) -> (Vec<(usize, usize)>, Vec<usize>) {
    let mut blocks = BTreeSet::new();
    for (p, _) in ordering.free.iter().enumerate() {
        blocks.insert((p, p));
    }
    for &fi in factors {
        let keys: Vec<usize> = graph.factors()[fi]
            .keys()
            .iter()
            .filter_map(|k| ordering.position(*k))
            .collect();
        for &a in &keys {
            for &b in &keys {
                if a >= b {
                    blocks.insert((a, b));
                }
            }
        }
    }
    let dims = ordering
        .free
        .iter()
        .filter_map(|v| ordering.slot(*v).map(|s| s.1))
        .collect();
    (blocks.into_iter().collect(), dims)
}

impl HessianStructure {
    /// The structure of the factors `factors` of `graph` under `ordering`.
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when faer rejects the structure.
    pub fn new(graph: &FactorGraph, factors: &[usize], ordering: &Ordering) -> Result<Self> {
        let (pattern, dims) = block_pattern(graph, factors, ordering);
        Self::from_pattern(pattern, dims)
    }

    fn from_pattern(pattern: Vec<(usize, usize)>, dims: Vec<usize>) -> Result<Self> {
        let nvar = dims.len();
        let mut offsets = Vec::with_capacity(nvar);
        let mut dim = 0;
        for d in &dims {
            offsets.push(dim);
            dim += d;
        }
        // Rows of each column variable: the variables at or below it that share a factor.
        let mut rows_of: Vec<Vec<usize>> = vec![Vec::new(); nvar];
        for &(a, b) in &pattern {
            rows_of[b].push(a);
        }
        let mut col_ptr = Vec::with_capacity(dim + 1);
        let mut row_idx = Vec::new();
        let mut diag = Vec::with_capacity(dim);
        let mut segments = vec![Vec::new(); nvar];
        col_ptr.push(0);
        for b in 0..nvar {
            rows_of[b].sort_unstable();
            let mut seg = 0;
            let mut own = 0;
            for &a in &rows_of[b] {
                if a == b {
                    own = seg;
                }
                segments[b].push((a, seg));
                seg += dims[a];
            }
            for c in 0..dims[b] {
                let start = row_idx.len();
                for &a in &rows_of[b] {
                    row_idx.extend(offsets[a]..offsets[a] + dims[a]);
                }
                diag.push(start + own + c);
                col_ptr.push(row_idx.len());
            }
        }
        let sym = SymbolicSparseColMat::<usize>::new_checked(dim, dim, col_ptr.clone(), None, row_idx.clone());
        // Supernodal: the Hessian is made of dense 3x3 to 15x15 blocks, which dense kernels
        // factor much faster than the column-by-column simplicial variant faer picks otherwise.
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
            ..Default::default()
        };
        let symbolic = factorize_symbolic_cholesky(sym.as_ref(), Side::Lower, Default::default(), params)
            .map_err(|e| Error::LinearSolve(format!("symbolic: {e:?}")))?;
        let symbolic = Arc::new(symbolic);
        Ok(Self {
            dim,
            col_ptr,
            row_idx,
            diag,
            segments,
            symbolic,
            pattern,
            dims,
        })
    }

    /// True when `self` can serve the factors `factors` under `ordering` as it is.
    #[must_use]
    pub fn fits(&self, graph: &FactorGraph, factors: &[usize], ordering: &Ordering) -> bool {
        let (pattern, dims) = block_pattern(graph, factors, ordering);
        pattern == self.pattern && dims == self.dims
    }

    /// Number of stored entries.
    #[must_use]
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }
}

/// Normal equations `H dx = -g` at one linearisation point.
#[derive(Debug, Clone)]
pub struct NormalEquations {
    /// Values of `H` in the structure's order.
    pub hessian: Vec<f64>,
    /// `J^T r`.
    pub gradient: DVector<f64>,
    /// Graph error at the linearisation point.
    pub error: f64,
}

/// Linearises the factors `factors` of `graph` at `values`: whitened, robust-reweighted
/// Jacobians accumulated into `J^T J` and `J^T r` over the free variables of `ordering`.
///
/// # Errors
/// A factor that cannot be evaluated.
pub fn linearize(
    graph: &FactorGraph,
    factors: &[usize],
    values: &Values,
    ordering: &Ordering,
    structure: &HessianStructure,
) -> Result<NormalEquations> {
    let mut hessian = vec![0.0; structure.nnz()];
    let mut gradient = DVector::zeros(structure.dim);
    let mut error = 0.0;
    let mut jac: Vec<DMatrix<f64>> = Vec::new();
    for &fi in factors {
        let f: &dyn Factor = graph.factors()[fi].as_ref();
        let noise = f.noise();
        let m = noise.dim();
        jac.clear();
        for k in f.keys() {
            jac.push(DMatrix::zeros(m, values.get(*k)?.dim()));
        }
        let r = f.evaluate(values, Some(&mut jac))?;
        let mut rw = noise.whiten(&r);
        let norm = rw.norm();
        error += noise.kernel().map_or(0.5 * norm * norm, |k| k.loss(norm));
        let s = noise.robust_scale(&rw);
        // The free keys' Jacobians side by side: (key index, position, column in `jall`).
        let mut free: Vec<(usize, usize, usize)> = Vec::with_capacity(jac.len());
        let mut cols = 0;
        for (k, key) in f.keys().iter().enumerate() {
            if let Some(p) = ordering.position(*key) {
                free.push((k, p, cols));
                cols += jac[k].ncols();
            }
        }
        if free.is_empty() {
            continue;
        }
        let mut jall = DMatrix::zeros(m, cols);
        for &(k, _, c0) in &free {
            jall.columns_mut(c0, jac[k].ncols()).copy_from(&jac[k]);
        }
        noise.whiten_jacobian(&mut jall);
        if s != 1.0 {
            jall *= s;
            rw *= s;
        }
        let jtj = jall.tr_mul(&jall);
        let g = jall.tr_mul(&rw);
        for &(ka, pa, ca) in &free {
            let (off_a, da) = ordering.slot(ordering.free[pa]).ok_or(Error::UnknownVariable(pa))?;
            debug_assert_eq!(da, jac[ka].ncols());
            for (gi, gv) in gradient.rows_mut(off_a, da).iter_mut().zip(g.rows(ca, da).iter()) {
                *gi += gv;
            }
            for &(_, pb, cb) in &free {
                if pa < pb {
                    continue;
                }
                let (off_b, db) = ordering.slot(ordering.free[pb]).ok_or(Error::UnknownVariable(pb))?;
                let seg = structure.segments[pb]
                    .iter()
                    .find(|(a, _)| *a == pa)
                    .map(|(_, seg)| *seg)
                    .ok_or(Error::LinearSolve("factor outside the Hessian structure".into()))?;
                for c in 0..db {
                    let base = structure.col_ptr[off_b + c] + seg;
                    let src = jtj.view((ca, cb + c), (da, 1));
                    for (h, v) in hessian[base..base + da].iter_mut().zip(src.iter()) {
                        *h += v;
                    }
                }
            }
        }
    }
    Ok(NormalEquations {
        hessian,
        gradient,
        error,
    })
}

/// A numeric Cholesky factorisation of `H + lambda I`.
#[derive(Debug)]
pub struct Factorization {
    symbolic: Arc<SymbolicCholesky<usize>>,
    values: Vec<f64>,
    dim: usize,
}

impl Factorization {
    /// Factorises `H + lambda I` with the structure's symbolic factorisation.
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when the matrix is not positive definite.
    pub fn new(structure: &HessianStructure, hessian: &[f64], lambda: f64) -> Result<Self> {
        let mut vals = hessian.to_vec();
        if lambda != 0.0 {
            for &d in &structure.diag {
                vals[d] += lambda;
            }
        }
        let sym = faer::sparse::SymbolicSparseColMatRef::new_checked(
            structure.dim,
            structure.dim,
            &structure.col_ptr,
            None,
            &structure.row_idx,
        );
        let mat = SparseColMatRef::new(sym, &vals);
        let symbolic = structure.symbolic.clone();
        let mut values = vec![0.0; symbolic.len_val()];
        let mut mem = MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()));
        symbolic
            .factorize_numeric_llt::<f64>(
                &mut values,
                mat,
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map_err(|e| Error::LinearSolve(format!("{e:?}")))?;
        Ok(Self {
            symbolic,
            values,
            dim: structure.dim,
        })
    }

    /// Solves `(H + lambda I) x = rhs` in place; `rhs` may hold several columns (column-major).
    pub fn solve_in_place(&self, rhs: &mut [f64]) {
        let ncols = rhs.len() / self.dim.max(1);
        let mat = faer::MatMut::from_column_major_slice_mut(rhs, self.dim, ncols);
        let mut mem = MemBuffer::new(self.symbolic.solve_in_place_scratch::<f64>(ncols, Par::Seq));
        LltRef::new(&self.symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            mat,
            Par::Seq,
            MemStack::new(&mut mem),
        );
    }
}

/// Applies a step `dx` (system order) to the free variables of `values`.
///
/// # Errors
/// [`Error::UnknownVariable`] for an ordering that does not belong to `values`.
pub fn retract(values: &mut Values, ordering: &Ordering, dx: &DVector<f64>) -> Result<()> {
    for id in &ordering.free {
        if let Some((off, dim)) = ordering.slot(*id) {
            let v = *values.get(*id)?;
            values.set(*id, v.retract(dx.rows(off, dim)))?;
        }
    }
    Ok(())
}

/// Marginal covariance of the free variable `id`: the block `(H^-1)_{id,id}`.
///
/// # Errors
/// A variable that is not free.
pub fn marginal_covariance(factorization: &Factorization, ordering: &Ordering, id: VarId) -> Result<DMatrix<f64>> {
    let (off, dim) = ordering.slot(id).ok_or(Error::UnknownVariable(id.0))?;
    let n = ordering.dim();
    let mut rhs = vec![0.0; n * dim];
    for c in 0..dim {
        rhs[c * n + off + c] = 1.0;
    }
    factorization.solve_in_place(&mut rhs);
    let mut out = DMatrix::zeros(dim, dim);
    for c in 0..dim {
        for r in 0..dim {
            out[(r, c)] = rhs[c * n + off + r];
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenPose, PosePrior};
    use crate::lie::Pose3;
    use crate::noise::NoiseModel;
    use crate::values::Variable;
    use nalgebra::Vector6;

    #[test]
    fn sparse_solve_matches_dense() {
        let mut values = Values::new();
        let mut graph = FactorGraph::new();
        let n6 = NoiseModel::diagonal(&[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]).expect("noise");
        let ids: Vec<VarId> = (0..4)
            .map(|k| {
                values.push(Variable::Pose(Pose3::exp(&Vector6::new(
                    0.1 * f64::from(k),
                    0.0,
                    0.2,
                    1.0,
                    0.5,
                    0.0,
                ))))
            })
            .collect();
        graph.add(PosePrior::new(ids[0], Pose3::identity(), n6.clone()).expect("f"));
        for w in ids.windows(2) {
            graph.add(
                BetweenPose::new(
                    w[0],
                    w[1],
                    Pose3::exp(&Vector6::new(0.0, 0.1, 0.0, 1.0, 0.0, 0.0)),
                    n6.clone(),
                )
                .expect("f"),
            );
        }
        graph.add(BetweenPose::new(ids[0], ids[3], Pose3::identity(), n6).expect("f"));
        let all: Vec<usize> = (0..graph.len()).collect();
        let ord = Ordering::all(&values);
        let st = HessianStructure::new(&graph, &all, &ord).expect("structure");
        let ne = linearize(&graph, &all, &values, &ord, &st).expect("linearize");
        // Dense H from the lower-triangle storage.
        let n = ord.dim();
        let mut h = DMatrix::zeros(n, n);
        for c in 0..n {
            for k in st.col_ptr[c]..st.col_ptr[c + 1] {
                let r = st.row_idx[k];
                if r >= c {
                    h[(r, c)] = ne.hessian[k];
                    h[(c, r)] = ne.hessian[k];
                }
            }
        }
        let lambda = 1e-3;
        let dense = (h.clone() + DMatrix::identity(n, n) * lambda)
            .cholesky()
            .expect("spd")
            .solve(&ne.gradient);
        let fact = Factorization::new(&st, &ne.hessian, lambda).expect("llt");
        let mut x = ne.gradient.as_slice().to_vec();
        fact.solve_in_place(&mut x);
        let sparse = DVector::from_vec(x);
        assert!((dense - sparse).norm() < 1e-9);
        assert!(st.fits(&graph, &all, &ord));
        let cov = marginal_covariance(&fact, &ord, ids[3]).expect("cov");
        let dense_inv = (h + DMatrix::identity(n, n) * lambda).try_inverse().expect("inv");
        assert!((cov - dense_inv.view((18, 18), (6, 6))).norm() < 1e-9);
    }
}
