//! Gauss-Newton linearisation into sparse normal equations and their sparse Cholesky solve.
//!
//! The Hessian `J^T J` is stored block-sparse in compressed columns (lower block triangle):
//! the structure depends only on which variables share a factor, so it is built once per
//! structure and the faer symbolic factorisation (fill-reducing ordering and elimination tree)
//! is reused for every numeric factorisation with that structure.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, LltRef, SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering,
    factorize_symbolic_cholesky,
};
use faer::sparse::linalg::{SupernodalThreshold, SymbolicSupernodalParams};
use faer::sparse::{SymbolicSparseColMat, SymbolicSparseColMatRef};
use faer::{Conj, Par, Side};
use nalgebra::{DMatrix, DVector};

use crate::cholesky::{UpdatePlan, Workspace, factorize, solve_one};
use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::noise::NoiseModel;
use crate::values::{Values, VarId};
use crate::{Error, Result};

/// Which variables are solved for, and where each sits in the linear system.
///
/// Lookups are by variable id into a table that spans only the free ids (from the lowest to
/// the highest), so a window of the newest states costs its own size, not the whole run's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ordering {
    /// The lowest free id: `slots[k]` is variable `base + k`.
    base: usize,
    /// Per variable id from `base`: `(offset, dim, position in free)` when free, `None` when
    /// held fixed.
    slots: Vec<Option<(usize, usize, usize)>>,
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
        let known = || free.iter().filter(|id| id.0 < values.len()).map(|id| id.0);
        let base = known().min().unwrap_or(0);
        let end = known().max().map_or(base, |m| m + 1);
        let mut slots = vec![None; end - base];
        let mut dim = 0;
        let mut kept = Vec::with_capacity(free.len());
        for id in free {
            if let Ok(v) = values.get(*id)
                && slots[id.0 - base].is_none()
            {
                slots[id.0 - base] = Some((dim, v.dim(), kept.len()));
                dim += v.dim();
                kept.push(*id);
            }
        }
        Self {
            base,
            slots,
            free: kept,
            dim,
        }
    }

    fn entry(&self, id: VarId) -> Option<(usize, usize, usize)> {
        id.0.checked_sub(self.base)
            .and_then(|k| self.slots.get(k))
            .copied()
            .flatten()
    }

    /// `(offset, dim)` of a free variable.
    #[must_use]
    pub fn slot(&self, id: VarId) -> Option<(usize, usize)> {
        self.entry(id).map(|(offset, dim, _)| (offset, dim))
    }

    /// Position of a free variable in [`Ordering::free_vars`].
    #[must_use]
    pub fn position(&self, id: VarId) -> Option<usize> {
        self.entry(id).map(|(_, _, position)| position)
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

/// The compressed-column structure of `J^T J` for one set of free variables and factors, its
/// elimination ordering and the symbolic Cholesky of that structure.
///
/// The ordering is chosen here: approximate minimum degree (faer's AMD) on the graph of the
/// *variables* (one node per pose, velocity, bias or line; edges where a factor joins two),
/// not on the scalar matrix, which is 6-15 times larger. The system is then assembled directly
/// in elimination order, so the numeric factorisation needs no permutation of its input.
#[derive(Debug, Clone)]
pub struct HessianStructure {
    /// The free variables in elimination (system) order.
    ordering: Ordering,
    /// Per position in the caller's order: the position in elimination order.
    elimination_position: Vec<usize>,
    dim: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Index of each diagonal entry in the value array.
    diag: Vec<usize>,
    /// Per column variable (elimination position): `(row variable position, offset of its rows
    /// inside each of the column variable's columns)`, sorted by row variable.
    segments: Vec<Vec<(usize, usize)>>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// Which supernodes update which (see [`crate::cholesky`]).
    plan: Arc<UpdatePlan>,
    /// The block pattern in the caller's order (reuse key), and the variables' dimensions.
    pattern: Vec<(usize, usize)>,
    dims: Vec<usize>,
}

/// The lower block pattern `(row, column)` of the factors over the positions of `ordering`, and
/// each position's dimension.
fn block_pattern(graph: &FactorGraph, factors: &[usize], ordering: &Ordering) -> (Vec<(usize, usize)>, Vec<usize>) {
    let mut blocks: Vec<(usize, usize)> = (0..ordering.free.len()).map(|p| (p, p)).collect();
    let mut keys = Vec::new();
    for &fi in factors {
        keys.clear();
        keys.extend(graph.factors()[fi].keys().iter().filter_map(|k| ordering.position(*k)));
        for &a in &keys {
            for &b in &keys {
                if a > b {
                    blocks.push((a, b));
                }
            }
        }
    }
    // Sorted and deduplicated once: a set grown pair by pair was half the time of building a
    // structure (perf, the 20.9-minute localisation run).
    blocks.sort_unstable();
    blocks.dedup();
    let dims = ordering
        .free
        .iter()
        .filter_map(|v| ordering.slot(*v).map(|s| s.1))
        .collect();
    (blocks, dims)
}

/// Approximate minimum degree order of the variables of a lower block pattern: per position,
/// its place in elimination order.
fn minimum_degree_positions(pattern: &[(usize, usize)], nvar: usize) -> Result<Vec<usize>> {
    let mut rows_of: Vec<Vec<usize>> = vec![Vec::new(); nvar];
    for &(a, b) in pattern {
        rows_of[b].push(a);
    }
    let mut col_ptr = Vec::with_capacity(nvar + 1);
    let mut row_idx = Vec::with_capacity(pattern.len());
    col_ptr.push(0);
    for rows in &mut rows_of {
        rows.sort_unstable();
        row_idx.extend_from_slice(rows);
        col_ptr.push(row_idx.len());
    }
    let nnz = row_idx.len();
    let sym = SymbolicSparseColMatRef::new_checked(nvar, nvar, &col_ptr, None, &row_idx);
    let mut perm = vec![0usize; nvar];
    let mut perm_inv = vec![0usize; nvar];
    let mut mem = MemBuffer::new(amd::order_scratch::<usize>(nvar, nnz));
    amd::order(
        &mut perm,
        &mut perm_inv,
        sym,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )
    .map_err(|e| Error::LinearSolve(format!("ordering: {e:?}")))?;
    // `perm[k]` is the variable eliminated k-th, `perm_inv` its inverse.
    Ok(perm_inv)
}

/// The compressed columns of the upper triangle of a symmetric pattern made of dense blocks:
/// `rows_of[b]` holds the variables `a >= b` (sorted) whose block `(a, b)` is stored, with the
/// diagonal block whole. Column `c` of variable `a` then has the rows of every variable `b`
/// with a block `(a, b)`, in order (its transpose, built by blocks). `dim` and `nnz` are the
/// pattern's size and number of entries.
fn upper_pattern(
    rows_of: &[Vec<usize>],
    dims: &[usize],
    offsets: &[usize],
    (dim, nnz): (usize, usize),
) -> (Vec<usize>, Vec<usize>) {
    let mut cols_of: Vec<Vec<usize>> = vec![Vec::new(); rows_of.len()];
    for (b, rows) in rows_of.iter().enumerate() {
        for &a in rows {
            cols_of[a].push(b);
        }
    }
    let mut col_ptr = Vec::with_capacity(dim + 1);
    let mut row_idx = Vec::with_capacity(nnz);
    col_ptr.push(0);
    for (a, cols) in cols_of.iter().enumerate() {
        for _ in 0..dims[a] {
            for &b in cols {
                row_idx.extend(offsets[b]..offsets[b] + dims[b]);
            }
            col_ptr.push(row_idx.len());
        }
    }
    (col_ptr, row_idx)
}

impl HessianStructure {
    /// The structure of the factors `factors` of `graph` over the free variables of `free`
    /// (in any order: the structure picks the elimination order).
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when faer rejects the structure.
    pub fn new(graph: &FactorGraph, factors: &[usize], values: &Values, free: &Ordering) -> Result<Self> {
        let (pattern, dims) = block_pattern(graph, factors, free);
        let elimination_position = minimum_degree_positions(&pattern, dims.len())?;
        let ordering = Self::eliminate(values, free, &elimination_position);
        // The same blocks and dimensions, renumbered into elimination order.
        let nvar = dims.len();
        let mut elim_dims = vec![0; nvar];
        for (p, d) in dims.iter().enumerate() {
            elim_dims[elimination_position[p]] = *d;
        }
        let elim_pattern = pattern.iter().map(|&(a, b)| {
            let (ea, eb) = (elimination_position[a], elimination_position[b]);
            (ea.max(eb), ea.min(eb))
        });
        let mut offsets = Vec::with_capacity(nvar);
        let mut dim = 0;
        for d in &elim_dims {
            offsets.push(dim);
            dim += d;
        }
        // Rows of each column variable: the variables at or below it that share a factor.
        let mut rows_of: Vec<Vec<usize>> = vec![Vec::new(); nvar];
        for (a, b) in elim_pattern {
            rows_of[b].push(a);
        }
        let nnz = rows_of
            .iter()
            .zip(&elim_dims)
            .map(|(rows, d)| d * rows.iter().map(|a| elim_dims[*a]).sum::<usize>())
            .sum();
        let mut col_ptr = Vec::with_capacity(dim + 1);
        let mut row_idx = Vec::with_capacity(nnz);
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
                seg += elim_dims[a];
            }
            for c in 0..elim_dims[b] {
                let start = row_idx.len();
                for &a in &rows_of[b] {
                    row_idx.extend(offsets[a]..offsets[a] + elim_dims[a]);
                }
                diag.push(start + own + c);
                col_ptr.push(row_idx.len());
            }
        }
        // faer's symbolic analysis without a permutation reads the upper triangle (the numeric
        // factorisation reads the lower one, as stored): hand it the transposed pattern.
        let (upper_col_ptr, upper_row_idx) = upper_pattern(&rows_of, &elim_dims, &offsets, (dim, nnz));
        let sym = SymbolicSparseColMat::<usize>::new_checked(dim, dim, upper_col_ptr, None, upper_row_idx);
        // Supernodal: the Hessian is made of dense 3x3 to 15x15 blocks, which dense kernels
        // factor much faster than the column-by-column simplicial variant faer picks otherwise.
        // (Forced, also because the simplicial numeric factorisation would read the upper
        // triangle, which is not stored.) Supernodes are not merged: merging adds explicit
        // zeros to the factor (1.95 instead of 1.49 million entries at N = 2000 with two IMU
        // states to a supernode), whose memory traffic in every factorisation and solve costs
        // more than fewer, wider supernodes save (batch LM 0.225 -> 0.213 s at N = 2000).
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
            supernodal_params: SymbolicSupernodalParams { relax: None },
            ..Default::default()
        };
        let symbolic = factorize_symbolic_cholesky(sym.as_ref(), Side::Upper, SymmetricOrdering::Identity, params)
            .map_err(|e| Error::LinearSolve(format!("symbolic: {e:?}")))?;
        let plan = Arc::new(UpdatePlan::new(supernodal(&symbolic)?, (&col_ptr, &row_idx)));
        Ok(Self {
            ordering,
            elimination_position,
            dim,
            col_ptr,
            row_idx,
            diag,
            segments,
            symbolic: Arc::new(symbolic),
            plan,
            pattern,
            dims,
        })
    }

    fn eliminate(values: &Values, free: &Ordering, elimination_position: &[usize]) -> Ordering {
        let mut order = vec![VarId(0); free.free.len()];
        for (p, id) in free.free.iter().enumerate() {
            order[elimination_position[p]] = *id;
        }
        Ordering::free(values, &order)
    }

    /// True when `self` can serve the factors `factors` over the free variables of `free`: the
    /// same block pattern in the same positions (possibly other variables, as when a window
    /// slides). Call [`HessianStructure::rebind`] before using it for them.
    #[must_use]
    pub fn fits(&self, graph: &FactorGraph, factors: &[usize], free: &Ordering) -> bool {
        if free.free.len() != self.dims.len() {
            return false;
        }
        let (pattern, dims) = block_pattern(graph, factors, free);
        pattern == self.pattern && dims == self.dims
    }

    /// Points a structure that [`HessianStructure::fits`] at the variables of `free`.
    pub fn rebind(&mut self, values: &Values, free: &Ordering) {
        if free.free != self.ordering.free {
            self.ordering = Self::eliminate(values, free, &self.elimination_position);
            // Variables are identified by their position in `free`, so an equal pattern in the
            // caller's order is an equal pattern in elimination order.
        }
    }

    /// Offset, inside each column of variable `pb` (elimination position), of the rows of
    /// variable `pa`.
    fn segment(&self, pa: usize, pb: usize) -> Result<usize> {
        let segments = &self.segments[pb];
        segments
            .binary_search_by_key(&pa, |(a, _)| *a)
            .map(|i| segments[i].1)
            .map_err(|_| Error::LinearSolve("factor outside the Hessian structure".into()))
    }

    /// The free variables in the order of the linear system.
    #[must_use]
    pub fn ordering(&self) -> &Ordering {
        &self.ordering
    }

    /// The largest diagonal entry of a Hessian stored in this structure (0 when empty).
    #[must_use]
    pub fn max_diagonal(&self, hessian: &[f64]) -> f64 {
        self.diag
            .iter()
            .filter_map(|&d| hessian.get(d))
            .fold(0.0, |m: f64, v| m.max(*v))
    }

    /// Number of stored entries.
    #[must_use]
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// Stored entries of the Cholesky factor.
    #[must_use]
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.len_val()
    }
}

/// The supernodal structure of a symbolic factorisation (the structures here force it).
fn supernodal(symbolic: &SymbolicCholesky<usize>) -> Result<&SymbolicSupernodalCholesky<usize>> {
    match symbolic.raw() {
        SymbolicCholeskyRaw::Supernodal(s) => Ok(s),
        SymbolicCholeskyRaw::Simplicial(_) => Err(Error::LinearSolve("symbolic: not supernodal".into())),
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

impl Default for NormalEquations {
    /// Empty, to be filled by [`linearize_into`].
    fn default() -> Self {
        Self {
            hessian: Vec::new(),
            gradient: DVector::zeros(0),
            error: 0.0,
        }
    }
}

/// Linearises the factors `factors` of `graph` at `values`: whitened, robust-reweighted
/// Jacobians accumulated into `J^T J` and `J^T r` over the free variables of `structure`'s
/// ordering (variables it does not hold are constants).
///
/// # Errors
/// A factor that cannot be evaluated.
pub fn linearize(
    graph: &FactorGraph,
    factors: &[usize],
    values: &Values,
    structure: &HessianStructure,
) -> Result<NormalEquations> {
    let mut ne = NormalEquations::default();
    linearize_into(graph, factors, values, structure, &mut ne)?;
    Ok(ne)
}

/// [`linearize`] into `ne`, reusing its buffers (a Hessian of a few thousand states is
/// megabytes, which fresh allocations would fault in page by page at every iteration).
///
/// # Errors
/// A factor that cannot be evaluated; `ne` then holds a partial sum.
pub fn linearize_into(
    graph: &FactorGraph,
    factors: &[usize],
    values: &Values,
    structure: &HessianStructure,
    ne: &mut NormalEquations,
) -> Result<()> {
    let ordering = &structure.ordering;
    ne.hessian.clear();
    ne.hessian.resize(structure.nnz(), 0.0);
    if ne.gradient.len() == structure.dim {
        ne.gradient.fill(0.0);
    } else {
        ne.gradient = DVector::zeros(structure.dim);
    }
    let (hessian, gradient) = (&mut ne.hessian, &mut ne.gradient);
    let mut error = 0.0;
    // Scratch reused across factors: per-key Jacobians and the factor's information.
    let mut jac: Vec<DMatrix<f64>> = Vec::new();
    let mut info = Information::default();
    // Per free key, in elimination order: (key index, position, offset, dim, column in `info`).
    let mut free: Vec<(usize, usize, usize, usize, usize)> = Vec::new();
    for &fi in factors {
        let f: &dyn Factor = graph.factors()[fi].as_ref();
        let noise = f.noise();
        let m = noise.dim();
        let keys = f.keys();
        if jac.len() < keys.len() {
            jac.resize_with(keys.len(), || DMatrix::zeros(0, 0));
        }
        for (j, k) in jac.iter_mut().zip(keys) {
            let d = values.get(*k)?.dim();
            if j.shape() != (m, d) {
                *j = DMatrix::zeros(m, d);
            } else {
                j.as_mut_slice().fill(0.0);
            }
        }
        let r = f.evaluate(values, Some(&mut jac[..keys.len()]))?;
        let loss = |norm: f64| noise.kernel().map_or(0.5 * norm * norm, |k| k.loss(norm));
        free.clear();
        for (k, key) in keys.iter().enumerate() {
            if let (Some(p), Some((off, dim))) = (ordering.position(*key), ordering.slot(*key)) {
                free.push((k, p, off, dim, 0));
            }
        }
        if free.is_empty() {
            error += loss(noise.whiten(&r).norm());
            continue;
        }
        // Columns in elimination order: a block below the diagonal of the Hessian is then
        // below the diagonal of the factor's `J^T J`.
        free.sort_unstable_by_key(|e| e.1);
        let mut cols = 0;
        for e in &mut free {
            e.4 = cols;
            cols += e.3;
        }
        info.begin(m, cols);
        for &(k, _, _, _, c0) in &free {
            info.set_block(c0, &jac[k]);
        }
        error += loss(info.make(noise, &r));
        let g = info.gradient();
        for (b, &(_, pb, off_b, db, cb)) in free.iter().enumerate() {
            for (gi, gv) in gradient.as_mut_slice()[off_b..off_b + db]
                .iter_mut()
                .zip(&g[cb..cb + db])
            {
                *gi += gv;
            }
            // The diagonal block, whole (the structure stores it so): above the diagonal
            // from the rows of the columns before.
            let seg = structure.segment(pb, pb)?;
            for c in 0..db {
                let base = structure.col_ptr[off_b + c] + seg;
                let (above, below) = hessian[base..base + db].split_at_mut(c);
                for (i, h) in above.iter_mut().enumerate() {
                    *h += info.at(cb + c, cb + i);
                }
                for (h, v) in below.iter_mut().zip(info.column_from(cb + c, cb + c, db - c)) {
                    *h += v;
                }
            }
            // The blocks below it, on variables later in elimination order.
            for &(_, pa, _, da, ca) in &free[b + 1..] {
                let seg = structure.segment(pa, pb)?;
                for c in 0..db {
                    let base = structure.col_ptr[off_b + c] + seg;
                    for (h, v) in hessian[base..base + da]
                        .iter_mut()
                        .zip(info.column_from(ca, cb + c, da))
                    {
                        *h += v;
                    }
                }
            }
        }
    }
    ne.error = error;
    Ok(())
}

/// [`linearize_into`] on `threads` threads: the factors split in contiguous parts, each
/// linearised into its own normal equations (`ne` for the first, `spare` for the others, kept
/// for the next call), which are then added into `ne`. The result is the same for the same
/// number of threads (not bit for bit the same as on one: the sums are grouped differently).
///
/// # Errors
/// As [`linearize_into`].
pub fn linearize_split_into(
    graph: &FactorGraph,
    factors: &[usize],
    values: &Values,
    structure: &HessianStructure,
    (ne, spare): (&mut NormalEquations, &mut Vec<NormalEquations>),
    threads: usize,
) -> Result<()> {
    let threads = threads.clamp(1, factors.len().max(1));
    if threads == 1 {
        return linearize_into(graph, factors, values, structure, ne);
    }
    let mut parts = factors.chunks(factors.len().div_ceil(threads));
    let first = parts.next().unwrap_or_default();
    let others: Vec<&[usize]> = parts.collect();
    if spare.len() < others.len() {
        spare.resize_with(others.len(), NormalEquations::default);
    }
    let spare = &mut spare[..others.len()];
    std::thread::scope(|scope| {
        let handles: Vec<_> = others
            .iter()
            .zip(spare.iter_mut())
            .map(|(part, ne_k)| scope.spawn(move || linearize_into(graph, part, values, structure, ne_k)))
            .collect();
        let mine = linearize_into(graph, first, values, structure, ne);
        handles.into_iter().fold(mine, |done, h| {
            let theirs = h
                .join()
                .unwrap_or_else(|_| Err(Error::LinearSolve("a linearising thread panicked".into())));
            done.and(theirs)
        })
    })?;
    for other in spare.iter() {
        for (h, v) in ne.hessian.iter_mut().zip(&other.hessian) {
            *h += v;
        }
        ne.gradient += &other.gradient;
        ne.error += other.error;
    }
    Ok(())
}

/// One factor's information `J^T J` and `J^T r`, made from its whitened, robust-reweighted
/// Jacobian, with the buffers to make the next one.
///
/// The Jacobian is held by rows, each padded with zeros to a multiple of 4 columns: whitening
/// then adds whole rows, and each tile of `J^T J` (4 columns by 4, or with AVX2 8, rows) is a
/// sum over the rows of outer products kept in accumulators (which vectorise, where dot
/// products of columns form one long dependency chain per entry). Only the tiles on and below
/// the diagonal are made: callers read the lower triangle ([`Information::at`] mirrors the
/// rest).
#[derive(Debug, Default)]
pub(crate) struct Information {
    /// Rows of the unwhitened Jacobian, `width` long.
    raw: Vec<f64>,
    /// Rows of the whitened, reweighted one.
    rows: Vec<f64>,
    /// `J^T J`, `width x width` column-major, its lower tiles.
    h: Vec<f64>,
    /// `J^T r`, `width` long.
    g: Vec<f64>,
    /// The whitened, reweighted residual.
    rw: Vec<f64>,
    m: usize,
    n: usize,
    width: usize,
}

impl Information {
    /// Starts a factor of `m` residuals over `n` columns (zeroed).
    pub(crate) fn begin(&mut self, m: usize, n: usize) {
        self.m = m;
        self.n = n;
        self.width = n.div_ceil(4) * 4;
        self.raw.clear();
        self.raw.resize(m * self.width, 0.0);
        self.rows.resize(m * self.width, 0.0);
        self.h.resize(self.width * self.width, 0.0);
        self.g.resize(self.width, 0.0);
    }

    /// Places the `m x d` Jacobian block `j` at columns `c0..c0 + d`.
    pub(crate) fn set_block(&mut self, c0: usize, j: &DMatrix<f64>) {
        let (m, w) = (self.m, self.width);
        for (c, col) in j.as_slice().chunks_exact(m.max(1)).enumerate() {
            for (k, v) in col.iter().enumerate() {
                self.raw[k * w + c0 + c] = *v;
            }
        }
    }

    /// Whitens the Jacobian and the residual `r` with `noise`, reweights both by its robust
    /// kernel, and makes `J^T J` and `J^T r` of them. Returns the norm of the whitened
    /// residual before reweighting (the argument of the factor's loss).
    pub(crate) fn make(&mut self, noise: &NoiseModel, r: &DVector<f64>) -> f64 {
        let w = self.width;
        noise.whiten_rows(&self.raw, w, &mut self.rows);
        self.rw.resize(self.m, 0.0);
        noise.whiten_into(r.as_slice(), &mut self.rw);
        let norm = self.rw.iter().map(|x| x * x).sum::<f64>().sqrt();
        let s = noise.robust_scale_at(norm);
        if s != 1.0 {
            for x in self.rows.iter_mut().chain(&mut self.rw) {
                *x *= s;
            }
        }
        self.g.fill(0.0);
        for (row, rk) in self.rows.chunks_exact(w).zip(&self.rw) {
            for (gc, v) in self.g.iter_mut().zip(row) {
                *gc += rk * v;
            }
        }
        lower_gram(&self.rows, w, &mut self.h);
        norm
    }

    /// Entry `(i, j)` of `J^T J`.
    #[inline]
    pub(crate) fn at(&self, i: usize, j: usize) -> f64 {
        let (i, j) = if i / 4 >= j / 4 { (i, j) } else { (j, i) };
        self.h[j * self.width + i]
    }

    /// `J^T J`'s column `j` from row `i` (`i >= j`'s tile), `len` entries.
    #[inline]
    pub(crate) fn column_from(&self, i: usize, j: usize, len: usize) -> &[f64] {
        debug_assert!(i / 4 >= j / 4);
        &self.h[j * self.width + i..][..len]
    }

    /// `J^T r`.
    pub(crate) fn gradient(&self) -> &[f64] {
        &self.g[..self.n]
    }

    /// The full symmetric `J^T J` and `J^T r` into `h` and `g` (resized to fit).
    pub(crate) fn to_dense(&self, h: &mut DMatrix<f64>, g: &mut DVector<f64>) {
        let n = self.n;
        if h.shape() != (n, n) {
            *h = DMatrix::zeros(n, n);
        }
        for j in 0..n {
            for i in 0..n {
                h[(i, j)] = self.at(i, j);
            }
        }
        *g = DVector::from_column_slice(self.gradient());
    }
}

/// The tiles on and below the diagonal of `J^T J` (`width x width`, column-major) for the rows
/// `rows` of `J`, each `width` long; with AVX2 where the CPU has it (the same operations in the
/// same order, so the same numbers either way).
fn lower_gram(rows: &[f64], width: usize, h: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2, checked just above.
        unsafe { lower_gram_avx2(rows, width, h) };
        return;
    }
    lower_gram_portable(rows, width, h);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn lower_gram_avx2(rows: &[f64], width: usize, h: &mut [f64]) {
    for jb in (0..width).step_by(4) {
        let mut ib = jb;
        while ib + 8 <= width {
            gram_tile_avx2::<2>(rows, width, ib, jb, h);
            ib += 8;
        }
        if ib < width {
            gram_tile_avx2::<1>(rows, width, ib, jb, h);
        }
    }
}

/// Rows `ib..ib + 4 V` of columns `jb..jb + 4` of `J^T J`, in `4 V` AVX2 registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn gram_tile_avx2<const V: usize>(rows: &[f64], width: usize, ib: usize, jb: usize, h: &mut [f64]) {
    use std::arch::x86_64::{
        _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_setzero_pd, _mm256_storeu_pd,
    };
    let mut acc = [[_mm256_setzero_pd(); V]; 4];
    for row in rows.chunks_exact(width) {
        let a = &row[ib..ib + 4 * V];
        let mut av = [_mm256_setzero_pd(); V];
        for (v, x) in av.iter_mut().enumerate() {
            // SAFETY: `a` is `4 V` long.
            *x = unsafe { _mm256_loadu_pd(a[4 * v..].as_ptr()) };
        }
        for (acc_t, b) in acc.iter_mut().zip(&row[jb..jb + 4]) {
            let b = _mm256_set1_pd(*b);
            for (x, a) in acc_t.iter_mut().zip(&av) {
                *x = _mm256_add_pd(*x, _mm256_mul_pd(*a, b));
            }
        }
    }
    for (t, acc_t) in acc.iter().enumerate() {
        let out = &mut h[(jb + t) * width + ib..][..4 * V];
        for (v, x) in acc_t.iter().enumerate() {
            // SAFETY: `out` is `4 V` long.
            unsafe { _mm256_storeu_pd(out[4 * v..].as_mut_ptr(), *x) };
        }
    }
}

/// [`lower_gram`]: tile `(ib, jb)` holds `sum over rows of a b^T` with `a` the row's entries
/// `ib..ib + 4` and `b` those at `jb..jb + 4`, added row by row.
fn lower_gram_portable(rows: &[f64], width: usize, h: &mut [f64]) {
    for jb in (0..width).step_by(4) {
        for ib in (jb..width).step_by(4) {
            let mut acc = [[0.0f64; 4]; 4];
            for row in rows.chunks_exact(width) {
                let a = &row[ib..ib + 4];
                for (acc_j, b) in acc.iter_mut().zip(&row[jb..jb + 4]) {
                    for (x, ai) in acc_j.iter_mut().zip(a) {
                        *x += ai * b;
                    }
                }
            }
            for (j, acc_j) in acc.iter().enumerate() {
                h[(jb + j) * width + ib..][..4].copy_from_slice(acc_j);
            }
        }
    }
}

/// One factor's information: `J^T J` and `J^T r` of its Jacobian `a` (the free keys' columns
/// side by side) and residual `r`, whitened and robust-reweighted, into `h` and `g` (resized
/// to fit). Returns the norm of the whitened residual before reweighting (the argument of the
/// factor's loss).
pub(crate) fn whitened_gram(
    noise: &NoiseModel,
    a: &DMatrix<f64>,
    r: &DVector<f64>,
    info: &mut Information,
    h: &mut DMatrix<f64>,
    g: &mut DVector<f64>,
) -> f64 {
    info.begin(a.nrows(), a.ncols());
    info.set_block(0, a);
    let norm = info.make(noise, r);
    info.to_dense(h, g);
    norm
}

/// Damping, relative to the largest diagonal entry, of a Hessian with a direction no factor
/// observes, for its covariance ([`Factorization::for_covariance`]).
pub const FREE_DIRECTION_DAMPING: f64 = 1e-9;

/// A numeric Cholesky factorisation of `H + lambda I`, with the buffers to redo it.
pub struct Factorization {
    symbolic: Arc<SymbolicCholesky<usize>>,
    plan: Arc<UpdatePlan>,
    values: Vec<f64>,
    work: Workspace,
    dim: usize,
}

impl std::fmt::Debug for Factorization {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Factorization")
            .field("dim", &self.dim)
            .field("factor_nnz", &self.values.len())
            .finish_non_exhaustive()
    }
}

impl Factorization {
    /// Factorises `H + lambda I` with the structure's symbolic factorisation.
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when the matrix is not positive definite.
    pub fn new(structure: &HessianStructure, hessian: &[f64], lambda: f64) -> Result<Self> {
        let mut f = Self {
            values: vec![0.0; structure.symbolic.len_val()],
            work: Workspace::new(supernodal(&structure.symbolic)?, &structure.plan),
            symbolic: structure.symbolic.clone(),
            plan: structure.plan.clone(),
            dim: structure.dim,
        };
        f.refactor(structure, hessian, lambda)?;
        Ok(f)
    }

    /// Factorises `H` for a covariance: undamped, or where a direction no factor observes
    /// (a line seen from one side only) leaves it singular, with the least damping that makes
    /// a factor (a relative [`FREE_DIRECTION_DAMPING`] of the largest diagonal entry: a very
    /// weak prior on that direction), so that whether a covariance exists does not depend on
    /// rounding.
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when even the damped matrix is not positive definite.
    pub fn for_covariance(structure: &HessianStructure, hessian: &[f64]) -> Result<Self> {
        Self::new(structure, hessian, 0.0).or_else(|_| {
            Self::new(
                structure,
                hessian,
                FREE_DIRECTION_DAMPING * structure.max_diagonal(hessian),
            )
        })
    }

    /// [`Factorization::for_covariance`], but taking `held`, a factorisation of `H + lambda I`
    /// already made (with its `lambda`), when its damping is no more than the free-direction
    /// damping.
    ///
    /// # Errors
    /// As [`Factorization::for_covariance`].
    pub fn for_covariance_reusing(
        structure: &HessianStructure,
        hessian: &[f64],
        held: Option<(Self, f64)>,
    ) -> Result<Self> {
        match held {
            Some((f, lambda)) if lambda <= FREE_DIRECTION_DAMPING * structure.max_diagonal(hessian) => Ok(f),
            _ => Self::for_covariance(structure, hessian),
        }
    }

    /// Factorises `H + lambda I` again, reusing the buffers when `structure` is the one this
    /// factorisation was made with.
    ///
    /// # Errors
    /// [`Error::LinearSolve`] when the matrix is not positive definite.
    pub fn refactor(&mut self, structure: &HessianStructure, hessian: &[f64], lambda: f64) -> Result<()> {
        if !Arc::ptr_eq(&self.symbolic, &structure.symbolic) {
            *self = Self::new(structure, hessian, lambda)?;
            return Ok(());
        }
        factorize(
            supernodal(&self.symbolic)?,
            &self.plan,
            hessian,
            lambda,
            &mut self.values,
            &mut self.work,
        )
        .map_err(|e| Error::LinearSolve(format!("not positive definite at column {}", e.column)))
    }

    /// Solves `(H + lambda I) x = rhs` in place; `rhs` may hold several columns (column-major:
    /// one column by our own substitution, several by faer's).
    pub fn solve_in_place(&self, rhs: &mut [f64]) {
        if rhs.len() == self.dim
            && let Ok(symbolic) = supernodal(&self.symbolic)
        {
            solve_one(symbolic, &self.values, rhs);
            return;
        }
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
    fn information_is_jt_j_and_jt_r_for_any_shape() {
        // Widths that are and are not multiples of the 4-column tiles, and a single row; a
        // full and a diagonal noise model.
        for (m, n) in [(15, 30), (7, 13), (6, 12), (1, 5), (3, 4)] {
            let j = DMatrix::from_fn(m, n, |r, c| ((r * 31 + c * 17) % 11) as f64 - 5.0 + 0.25 * c as f64);
            let r = DVector::from_fn(m, |k, _| 1.5 - k as f64);
            let cov = DMatrix::from_fn(m, m, |a, b| {
                if a == b {
                    2.0 + a as f64
                } else {
                    0.3 / (1.0 + a.abs_diff(b) as f64)
                }
            });
            let sigmas: Vec<f64> = (0..m).map(|k| 0.5 + 0.1 * k as f64).collect();
            for noise in [
                NoiseModel::from_covariance(&cov).expect("spd"),
                NoiseModel::diagonal(&sigmas).expect("sigmas"),
            ] {
                let mut jw = j.clone();
                noise.whiten_jacobian(&mut jw);
                let rw = noise.whiten(&r);
                let (want_h, want_g) = (jw.transpose() * &jw, jw.transpose() * &rw);
                let mut info = Information::default();
                let (mut h, mut g) = (DMatrix::zeros(0, 0), DVector::zeros(0));
                let norm = whitened_gram(&noise, &j, &r, &mut info, &mut h, &mut g);
                assert!((norm - rw.norm()).abs() <= 1e-12 * rw.norm());
                assert!(
                    (&h - &want_h).norm() <= 1e-12 * want_h.norm(),
                    "{m}x{n}: {h} vs {want_h}"
                );
                assert!((&g - &want_g).norm() <= 1e-12 * want_g.norm().max(1.0), "{m}x{n}");
                // The vectorised and the portable tiles give the same numbers.
                let mut portable = vec![0.0; info.h.len()];
                lower_gram_portable(&info.rows, info.width, &mut portable);
                for jb in (0..info.width).step_by(4) {
                    for c in jb..jb + 4 {
                        let col = c * info.width;
                        assert_eq!(
                            portable[col + jb..col + info.width],
                            info.h[col + jb..col + info.width],
                            "{m}x{n}"
                        );
                    }
                }
            }
        }
    }

    /// A pose chain of `n` with a loop closure every `every` poses back to a pose `back` earlier.
    fn chain_with_closures(n: usize, every: usize, back: usize) -> (FactorGraph, Values) {
        let mut values = Values::new();
        let mut graph = FactorGraph::new();
        let noise = NoiseModel::diagonal(&[0.01, 0.02, 0.03, 0.1, 0.2, 0.3]).expect("noise");
        let ids: Vec<VarId> = (0..n)
            .map(|k| {
                let t = k as f64;
                values.push(Variable::Pose(Pose3::exp(&Vector6::new(
                    0.01 * t.sin(),
                    0.02 * t.cos(),
                    0.05 * t,
                    t,
                    0.3 * t.sin(),
                    0.0,
                ))))
            })
            .collect();
        graph.add(PosePrior::new(ids[0], Pose3::identity(), noise.clone()).expect("prior"));
        let step = Pose3::exp(&Vector6::new(0.0, 0.0, 0.05, 1.0, 0.0, 0.0));
        for w in ids.windows(2) {
            graph.add(BetweenPose::new(w[0], w[1], step, noise.clone()).expect("between"));
        }
        for k in (back..n).step_by(every) {
            graph.add(BetweenPose::new(ids[k - back], ids[k], Pose3::identity(), noise.clone()).expect("closure"));
        }
        (graph, values)
    }

    #[test]
    fn supernodal_factor_is_faers_and_visits_only_the_updating_supernodes() {
        let mut widths = Vec::new();
        let mut cases: Vec<(usize, FactorGraph, Values)> = [(3, 5, 2), (400, 1000, 1), (400, 7, 50), (400, 3, 397)]
            .into_iter()
            .map(|(n, every, back)| {
                let (graph, values) = chain_with_closures(n, every, back);
                (n, graph, values)
            })
            .collect();
        // Twelve poses all seen from one another: one supernode wider than the small kernel's.
        let (mut graph, values) = chain_with_closures(12, 1000, 1);
        let noise = NoiseModel::isotropic(6, 0.5).expect("noise");
        for i in 0..12 {
            for j in i + 2..12 {
                graph.add(BetweenPose::new(VarId(i), VarId(j), Pose3::identity(), noise.clone()).expect("closure"));
            }
        }
        cases.push((12, graph, values));
        for (n, graph, values) in cases {
            let all: Vec<usize> = (0..graph.len()).collect();
            let st = HessianStructure::new(&graph, &all, &values, &Ordering::all(&values)).expect("structure");
            let ne = linearize(&graph, &all, &values, &st).expect("linearize");
            let ours = Factorization::new(&st, &ne.hessian, 1e-4).expect("ours");
            // faer's own numeric factorisation of the same damped matrix.
            let mut damped = ne.hessian.clone();
            for &d in &st.diag {
                damped[d] += 1e-4;
            }
            let sym = SymbolicSparseColMatRef::new_checked(st.dim, st.dim, &st.col_ptr, None, &st.row_idx);
            let mut theirs = vec![0.0; st.symbolic.len_val()];
            let mut mem = MemBuffer::new(
                st.symbolic
                    .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
            );
            st.symbolic
                .factorize_numeric_llt::<f64>(
                    &mut theirs,
                    faer::sparse::SparseColMatRef::new(sym, &damped),
                    Side::Lower,
                    Default::default(),
                    Par::Seq,
                    MemStack::new(&mut mem),
                    Default::default(),
                )
                .expect("faer");
            // The factors' lower triangles (faer leaves other values above the diagonal of a
            // supernode's diagonal block; its solve reads only the lower one).
            let sn = supernodal(&st.symbolic).expect("supernodal");
            let lower = |values: &[f64]| {
                let mut values = values.to_vec();
                let (begin, end, at) = (sn.supernode_begin(), sn.supernode_end(), sn.col_ptr_for_val());
                for s in 0..sn.n_supernodes() {
                    let ncols = end[s] - begin[s];
                    let nrows = (at[s + 1] - at[s]) / ncols;
                    for j in 0..ncols {
                        values[at[s] + j * nrows..][..j].fill(0.0);
                    }
                }
                values
            };
            widths.extend((0..sn.n_supernodes()).map(|s| sn.supernode_end()[s] - sn.supernode_begin()[s]));
            let (ours_lower, theirs) = (lower(&ours.values), lower(&theirs));
            let scale = theirs.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            let worst = ours_lower
                .iter()
                .zip(&theirs)
                .fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                worst <= 1e-12 * scale,
                "n {n}: L differs by {worst} (largest entry {scale})"
            );
            // faer's solve on our factor solves the damped system.
            let rhs: Vec<f64> = (0..st.dim).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
            let mut x = rhs.clone();
            ours.solve_in_place(&mut x);
            let mut back = vec![0.0; st.dim];
            // the lower triangle (the values also hold the upper one of each variable's block)
            for j in 0..st.dim {
                let column = st.col_ptr[j]..st.col_ptr[j + 1];
                for (&i, &h) in st.row_idx[column.clone()].iter().zip(&damped[column]) {
                    if i >= j {
                        back[i] += h * x[j];
                    }
                    if i > j {
                        back[j] += h * x[i];
                    }
                }
            }
            let residual = back.iter().zip(&rhs).fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(residual < 1e-6, "n {n}: residual {residual}");
            // A chain's elimination tree is a path: each supernode is updated by a few, not
            // by all of the supernodes before it.
            assert!(
                st.plan.len() <= 4 * sn.n_supernodes(),
                "n {n}: {} updates for {} supernodes",
                st.plan.len(),
                sn.n_supernodes()
            );
        }
        // both kernels: the small one and faer's for wider supernodes
        let small = crate::cholesky::SMALL_COLUMNS;
        assert!(widths.iter().any(|&w| w <= small) && widths.iter().any(|&w| w > small));
    }

    #[test]
    fn a_matrix_that_is_not_positive_definite_names_its_column() {
        let (graph, values) = chain_with_closures(50, 1000, 1);
        let all: Vec<usize> = (0..graph.len()).collect();
        let st = HessianStructure::new(&graph, &all, &values, &Ordering::all(&values)).expect("structure");
        let mut ne = linearize(&graph, &all, &values, &st).expect("linearize");
        let d = st.diag[100];
        ne.hessian[d] = -1.0;
        let e = Factorization::new(&st, &ne.hessian, 0.0).expect_err("indefinite");
        assert!(e.to_string().contains("column 100"), "{e}");
    }

    #[test]
    fn linearising_on_threads_adds_up_to_one_thread() {
        let (graph, values) = chain_with_closures(300, 7, 50);
        let all: Vec<usize> = (0..graph.len()).collect();
        let st = HessianStructure::new(&graph, &all, &values, &Ordering::all(&values)).expect("structure");
        let one = linearize(&graph, &all, &values, &st).expect("linearize");
        let mut runs = Vec::new();
        for _ in 0..2 {
            let mut ne = linearize(&graph, &[], &values, &st).expect("empty");
            let mut spare = Vec::new();
            linearize_split_into(&graph, &all, &values, &st, (&mut ne, &mut spare), 3).expect("threads");
            assert_eq!(spare.len(), 2);
            runs.push(ne);
        }
        let (three, again) = (&runs[0], &runs[1]);
        let scale = one.hessian.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        let worst = one
            .hessian
            .iter()
            .zip(&three.hessian)
            .fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst <= 1e-12 * scale, "Hessian differs by {worst} (largest {scale})");
        assert!((&one.gradient - &three.gradient).norm() <= 1e-12 * one.gradient.norm());
        assert!((one.error - three.error).abs() <= 1e-12 * one.error);
        // The same thread count gives the same numbers.
        assert_eq!(
            (&three.hessian, &three.gradient, three.error),
            (&again.hessian, &again.gradient, again.error)
        );
    }

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
        let st = HessianStructure::new(&graph, &all, &values, &ord).expect("structure");
        let ne = linearize(&graph, &all, &values, &st).expect("linearize");
        let sys = st.ordering();
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
        let cov = marginal_covariance(&fact, sys, ids[3]).expect("cov");
        let dense_inv = (h + DMatrix::identity(n, n) * lambda).try_inverse().expect("inv");
        let (off, _) = sys.slot(ids[3]).expect("free");
        assert!((cov - dense_inv.view((off, off), (6, 6))).norm() < 1e-9);
    }
}
