//! Numeric supernodal Cholesky on faer's symbolic analysis.
//!
//! faer's own numeric factorisation (0.22) is left-looking and, for each supernode, walks
//! *every* descendant in the elimination tree, also the many that have no row in it. A
//! trajectory's Hessian is a long chain of states, so its elimination tree is a path: supernode
//! `s` has `s` descendants and the walk alone costs the square of the number of supernodes
//! (0.5 s of a 0.6 s factorisation for 12,500 IMU states). This one is the same left-looking
//! algorithm on the same storage, but it visits only the descendants that update each
//! supernode, found once per symbolic structure ([`UpdatePlan`]): its cost follows the fill.
//! faer's dense kernels do the arithmetic, but for supernodes of at most [`SMALL_COLUMNS`]
//! columns, whose diagonal block and the rows below it are factorised by one left-looking
//! kernel of our own (faer's blocked kernels spend more on set-up than on arithmetic at those
//! sizes). The result is in faer's layout: one right-hand side is solved here ([`solve_one`]),
//! several by faer's solve.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltError, LltRegularization, cholesky_in_place, cholesky_in_place_scratch};
use faer::linalg::matmul::matmul;
use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::{Accum, MatMut, MatRef, Par};

/// Supernodes of at most this many columns are factorised by [`small_panel_cholesky`].
pub(crate) const SMALL_COLUMNS: usize = 64;

/// One descendant's update of a supernode: rows `start..` of the descendant's off-diagonal
/// pattern are at or below the supernode's first column, and the first `mid` of them are
/// among its columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Update {
    source: usize,
    start: usize,
    mid: usize,
}

/// A run of consecutive stored entries of the input matrix that land on consecutive entries
/// of the factor's values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Run {
    source: usize,
    target: usize,
    len: usize,
}

/// For each supernode, where the input's entries go in its panel (in runs) and the
/// descendants that update it (in increasing order), and the workspace sizes the numeric
/// factorisation needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct UpdatePlan {
    run_ptr: Vec<usize>,
    runs: Vec<Run>,
    /// Per column, the index of its diagonal entry in the factor's values.
    diagonal: Vec<usize>,
    ptr: Vec<usize>,
    updates: Vec<Update>,
    /// The largest update product (rows x columns).
    max_product: usize,
    /// The widest supernode.
    max_columns: usize,
}

impl UpdatePlan {
    /// The plan of factorising the lower triangle stored in compressed columns `(col_ptr,
    /// row_idx)` with `symbolic`: the runs of its entries, and the updates (a supernode's
    /// off-diagonal rows, grouped by the supernode that holds them, are the supernodes it
    /// updates).
    pub(crate) fn new(symbolic: &SymbolicSupernodalCholesky<usize>, (col_ptr, row_idx): (&[usize], &[usize])) -> Self {
        let n_super = symbolic.n_supernodes();
        let (begin, end) = (symbolic.supernode_begin(), symbolic.supernode_end());
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let rows = symbolic.row_idx();
        let mut supernode_of = vec![0; symbolic.nrows()];
        let mut max_columns = 0;
        for s in 0..n_super {
            supernode_of[begin[s]..end[s]].fill(s);
            max_columns = max_columns.max(end[s] - begin[s]);
        }
        // Each descendant's pattern in runs of one target supernode, in increasing order.
        let mut runs: Vec<(usize, Update)> = Vec::new();
        for d in 0..n_super {
            let pattern = &rows[row_ptr[d]..row_ptr[d + 1]];
            let mut start = 0;
            while start < pattern.len() {
                let target = supernode_of[pattern[start]];
                let mid = pattern[start..].partition_point(|&r| r < end[target]);
                runs.push((target, Update { source: d, start, mid }));
                start += mid;
            }
        }
        let mut ptr = vec![0; n_super + 1];
        for (target, _) in &runs {
            ptr[target + 1] += 1;
        }
        for s in 0..n_super {
            ptr[s + 1] += ptr[s];
        }
        let mut next = ptr.clone();
        let mut updates = vec![
            Update {
                source: 0,
                start: 0,
                mid: 0
            };
            runs.len()
        ];
        let mut max_product = 0;
        for (target, u) in runs {
            let below = row_ptr[u.source + 1] - row_ptr[u.source] - u.start;
            max_product = max_product.max(below * u.mid);
            updates[next[target]] = u;
            next[target] += 1;
        }
        let (run_ptr, runs, diagonal) = assembly(symbolic, col_ptr, row_idx);
        Self {
            run_ptr,
            runs,
            diagonal,
            ptr,
            updates,
            max_product,
            max_columns,
        }
    }

    fn updates_of(&self, s: usize) -> &[Update] {
        &self.updates[self.ptr[s]..self.ptr[s + 1]]
    }

    /// Number of (descendant, supernode) updates.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.updates.len()
    }
}

/// Per supernode, the runs that carry the entries on and below the diagonal of `(col_ptr,
/// row_idx)` into its panel (each entry to its own place, so they are copies), and per column
/// the place of the diagonal entry.
fn assembly(
    symbolic: &SymbolicSupernodalCholesky<usize>,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> (Vec<usize>, Vec<Run>, Vec<usize>) {
    let val_ptr = symbolic.col_ptr_for_val();
    let mut g2l = vec![usize::MAX; symbolic.nrows()];
    let mut run_ptr = Vec::with_capacity(symbolic.n_supernodes() + 1);
    let mut runs: Vec<Run> = Vec::new();
    let mut diagonal = vec![0; symbolic.nrows()];
    run_ptr.push(0);
    for (s, panel_start) in val_ptr.iter().enumerate().take(symbolic.n_supernodes()) {
        let (s_start, s_end, pattern) = enter_supernode(symbolic, s, &mut g2l);
        let nrows = s_end - s_start + pattern.len();
        for j in s_start..s_end {
            let column = panel_start + (j - s_start) * nrows;
            diagonal[j] = column + j - s_start;
            let first_run = runs.len();
            let entries = col_ptr[j]..col_ptr[j + 1];
            for (k, &i) in entries.clone().zip(&row_idx[entries]) {
                if i < j {
                    continue;
                }
                let target = column + if i < s_end { i - s_start } else { g2l[i] };
                match runs[first_run..].last_mut() {
                    Some(run) if run.source + run.len == k && run.target + run.len == target => run.len += 1,
                    _ => runs.push(Run {
                        source: k,
                        target,
                        len: 1,
                    }),
                }
            }
        }
        for &r in pattern {
            g2l[r] = usize::MAX;
        }
        run_ptr.push(runs.len());
    }
    (run_ptr, runs, diagonal)
}

/// Supernode `s` of `symbolic`: its first and end columns and its off-diagonal rows, with `g2l`
/// set to each off-diagonal row's place in the supernode's panel (below its own columns' rows).
/// The caller resets those entries of `g2l` when done with the supernode.
fn enter_supernode<'a>(
    symbolic: &'a SymbolicSupernodalCholesky<usize>,
    s: usize,
    g2l: &mut [usize],
) -> (usize, usize, &'a [usize]) {
    let (start, end) = (symbolic.supernode_begin()[s], symbolic.supernode_end()[s]);
    let row_ptr = symbolic.col_ptr_for_row_idx();
    let pattern = &symbolic.row_idx()[row_ptr[s]..row_ptr[s + 1]];
    for (i, &r) in pattern.iter().enumerate() {
        g2l[r] = end - start + i;
    }
    (start, end, pattern)
}

/// Buffers of [`factorize`], kept between factorisations of one structure.
pub(crate) struct Workspace {
    global_to_local: Vec<usize>,
    product: Vec<f64>,
    dense: MemBuffer,
}

impl Workspace {
    pub(crate) fn new(symbolic: &SymbolicSupernodalCholesky<usize>, plan: &UpdatePlan) -> Self {
        Self {
            global_to_local: vec![usize::MAX; symbolic.nrows()],
            product: vec![0.0; plan.max_product],
            dense: MemBuffer::new(cholesky_in_place_scratch::<f64>(
                plan.max_columns,
                Par::Seq,
                Default::default(),
            )),
        }
    }
}

/// A pivot that was not positive: the matrix is not positive definite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct NonPositivePivot {
    /// The column (in the structure's order).
    pub(crate) column: usize,
}

/// Factorises the symmetric matrix whose lower triangle is stored in `values` (compressed
/// columns, the structure `symbolic` and `plan` were made for, no permutation) plus `lambda`
/// on its diagonal (damping, added as the values are copied in: no damped copy) into
/// `l_values`, in faer's supernodal layout (each supernode's columns, diagonal block first,
/// column-major).
///
/// # Errors
/// The first supernode whose diagonal block is not positive definite.
pub(crate) fn factorize(
    symbolic: &SymbolicSupernodalCholesky<usize>,
    plan: &UpdatePlan,
    values: &[f64],
    lambda: f64,
    l_values: &mut [f64],
    work: &mut Workspace,
) -> Result<(), NonPositivePivot> {
    let (begin, end) = (symbolic.supernode_begin(), symbolic.supernode_end());
    let row_ptr = symbolic.col_ptr_for_row_idx();
    let val_ptr = symbolic.col_ptr_for_val();
    let rows = symbolic.row_idx();
    let g2l = &mut work.global_to_local;
    for s in 0..symbolic.n_supernodes() {
        let (s_start, s_end, pattern) = enter_supernode(symbolic, s, g2l);
        let ncols = s_end - s_start;
        let nrows = ncols + pattern.len();
        let local = |r: usize, g2l: &[usize]| if r < s_end { r - s_start } else { g2l[r] };
        let (done, rest) = l_values.split_at_mut(val_ptr[s]);
        let ls = &mut rest[..val_ptr[s + 1] - val_ptr[s]];
        // Zeroed here, not all at once before: the panel is then in cache for what follows.
        ls.fill(0.0);
        for run in &plan.runs[plan.run_ptr[s]..plan.run_ptr[s + 1]] {
            let at = run.target - val_ptr[s];
            ls[at..at + run.len].copy_from_slice(&values[run.source..run.source + run.len]);
        }
        for j in s_start..s_end {
            ls[plan.diagonal[j] - val_ptr[s]] += lambda;
        }
        for u in plan.updates_of(s) {
            let d = u.source;
            let d_ncols = end[d] - begin[d];
            let d_pattern = &rows[row_ptr[d]..row_ptr[d + 1]];
            let d_nrows = d_ncols + d_pattern.len();
            let ld = MatRef::from_column_major_slice(&done[val_ptr[d]..val_ptr[d + 1]], d_nrows, d_ncols);
            let below = d_pattern.len() - u.start;
            let lower = ld.subrows(d_ncols + u.start, below);
            let mid = lower.subrows(0, u.mid);
            let product = &mut work.product[..below * u.mid];
            matmul(
                MatMut::from_column_major_slice_mut(product, below, u.mid),
                Accum::Replace,
                lower,
                mid.transpose(),
                1.0,
                Par::Seq,
            );
            let targets = &d_pattern[u.start..];
            for (j, &c) in targets[..u.mid].iter().enumerate() {
                let col = &mut ls[(c - s_start) * nrows..][..nrows];
                let p = &product[j * below..][..below];
                // Rows at or below the column's own (the lower triangle).
                for i in j..below {
                    col[local(targets[i], g2l)] -= p[i];
                }
            }
        }
        factor_panel(ls, nrows, ncols, &mut work.dense).map_err(|j| NonPositivePivot { column: s_start + j })?;
        for &r in pattern {
            g2l[r] = usize::MAX;
        }
    }
    Ok(())
}

/// Factorises a supernode's `nrows x ncols` panel (column-major, diagonal block on top) in
/// place: [`small_panel_cholesky`] up to [`SMALL_COLUMNS`] columns, else faer's blocked
/// Cholesky of the diagonal block and triangular solve of the rows below.
///
/// # Errors
/// The first column (of the panel) whose pivot is not positive.
fn factor_panel(panel: &mut [f64], nrows: usize, ncols: usize, dense: &mut MemBuffer) -> Result<(), usize> {
    if ncols <= SMALL_COLUMNS {
        return small_panel_cholesky(panel, nrows, ncols);
    }
    let panel = MatMut::from_column_major_slice_mut(panel, nrows, ncols);
    let (mut top, bottom) = panel.split_at_row_mut(ncols);
    cholesky_in_place(
        top.as_mut(),
        LltRegularization::default(),
        Par::Seq,
        MemStack::new(dense),
        Default::default(),
    )
    .map_err(|LltError::NonPositivePivot { index }| index)?;
    solve_lower_triangular_in_place(top.as_ref(), bottom.transpose_mut(), Par::Seq);
    Ok(())
}

/// Factorises a supernode's `nrows x ncols` panel (column-major: its diagonal block on top, the
/// rows below it under) in place, left-looking: each column takes the updates of the columns
/// left of it over its rows from the diagonal down, then is divided by the square root of its
/// diagonal entry. That is the diagonal block's Cholesky factor and the rows below
/// solved against it, in one pass. Uses AVX2 and FMA where the CPU has them.
///
/// # Errors
/// The first column whose pivot is not positive (or NaN).
fn small_panel_cholesky(panel: &mut [f64], nrows: usize, ncols: usize) -> Result<(), usize> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has AVX2 and FMA, checked just above.
        return unsafe { small_panel_cholesky_avx2(panel, nrows, ncols) };
    }
    small_panel_cholesky_with(panel, nrows, ncols, |a, b, c| c - a * b)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn small_panel_cholesky_avx2(panel: &mut [f64], nrows: usize, ncols: usize) -> Result<(), usize> {
    small_panel_cholesky_with(panel, nrows, ncols, |a, b, c| (-a).mul_add(b, c))
}

/// [`small_panel_cholesky`] with `nmadd(a, b, c) = c - a b`.
///
/// Columns are taken four at a time: the updates from the columns left of the four, over the
/// rows below them, run as a register-blocked product (each entry of a left column loaded
/// once for the four), skipping the left columns that are zero on all four (blocks of zeros
/// that the structure holds); then the four are finished one by one. Every entry still takes
/// its updates one by one in increasing column order, as in the plain column-by-column
/// algorithm, so the numbers are those of it.
#[inline(always)]
fn small_panel_cholesky_with(
    panel: &mut [f64],
    nrows: usize,
    ncols: usize,
    nmadd: impl Fn(f64, f64, f64) -> f64 + Copy,
) -> Result<(), usize> {
    debug_assert!(ncols <= SMALL_COLUMNS);
    let mut left = [0usize; SMALL_COLUMNS];
    for jb in (0..ncols).step_by(BLOCK) {
        let nb = (ncols - jb).min(BLOCK);
        if nb == BLOCK {
            let mut n_left = 0;
            for k in 0..jb {
                if panel[k * nrows + jb..][..BLOCK].iter().any(|l| *l != 0.0) {
                    left[n_left] = k;
                    n_left += 1;
                }
            }
            block_update(panel, nrows, jb, &left[..n_left], nmadd);
        } else {
            // The last columns, fewer than a block: their updates one column at a time.
            for j in jb..ncols {
                for k in 0..jb {
                    column_update(panel, nrows, j, k, nmadd);
                }
            }
        }
        for j in jb..jb + nb {
            for k in jb..j {
                column_update(panel, nrows, j, k, nmadd);
            }
            let col = &mut panel[j * nrows + j..(j + 1) * nrows];
            let pivot = col[0];
            if pivot.is_nan() || pivot <= 0.0 {
                return Err(j);
            }
            let d = pivot.sqrt();
            col[0] = d;
            let inv = d.recip();
            for x in &mut col[1..] {
                *x *= inv;
            }
        }
    }
    Ok(())
}

/// Columns taken together by [`small_panel_cholesky_with`].
const BLOCK: usize = 4;
/// Rows of a register tile in [`block_update`].
const TILE: usize = 8;

/// Column `j`'s entries from its diagonal down take column `k`'s update.
#[inline(always)]
fn column_update(panel: &mut [f64], nrows: usize, j: usize, k: usize, nmadd: impl Fn(f64, f64, f64) -> f64) {
    let (left, right) = panel.split_at_mut(j * nrows);
    let done = &left[k * nrows + j..(k + 1) * nrows];
    let l_jk = done[0];
    if l_jk != 0.0 {
        for (x, &l) in right[j..nrows].iter_mut().zip(done) {
            *x = nmadd(l, l_jk, *x);
        }
    }
}

/// Columns `jb..jb + BLOCK` take the updates of the columns `left` (increasing, all left of
/// `jb`), over their rows from `jb` down: the rows of their diagonal block entry by entry (only
/// those on or below the diagonal), the rows below in tiles of [`TILE`] rows (then one of half
/// that, then single rows) held in registers across all of `left`.
#[inline(always)]
fn block_update(
    panel: &mut [f64],
    nrows: usize,
    jb: usize,
    left: &[usize],
    nmadd: impl Fn(f64, f64, f64) -> f64 + Copy,
) {
    for t in 0..BLOCK {
        let j = jb + t;
        for i in j..jb + BLOCK {
            let mut x = panel[j * nrows + i];
            for &k in left {
                x = nmadd(panel[k * nrows + i], panel[k * nrows + j], x);
            }
            panel[j * nrows + i] = x;
        }
    }
    let (done, block) = panel.split_at_mut(jb * nrows);
    let mut i = jb + BLOCK;
    while i + TILE <= nrows {
        tile_update::<TILE>(done, block, nrows, jb, i, left, nmadd);
        i += TILE;
    }
    if i + TILE / 2 <= nrows {
        tile_update::<{ TILE / 2 }>(done, block, nrows, jb, i, left, nmadd);
        i += TILE / 2;
    }
    for i in i..nrows {
        tile_update::<1>(done, block, nrows, jb, i, left, nmadd);
    }
}

/// Rows `i..i + R` of the block of columns `jb..jb + BLOCK` (`block`, the panel from column
/// `jb`) take the updates of the columns `left` of `done` (the panel before `jb`), held in
/// registers across all of `left`.
#[inline(always)]
fn tile_update<const R: usize>(
    done: &[f64],
    block: &mut [f64],
    nrows: usize,
    jb: usize,
    i: usize,
    left: &[usize],
    nmadd: impl Fn(f64, f64, f64) -> f64,
) {
    let mut acc = [[0.0f64; R]; BLOCK];
    for (t, acc_t) in acc.iter_mut().enumerate() {
        acc_t.copy_from_slice(&block[t * nrows + i..][..R]);
    }
    for &k in left {
        let col = &done[k * nrows..(k + 1) * nrows];
        let l = &col[i..i + R];
        for (acc_t, &l_jk) in acc.iter_mut().zip(&col[jb..jb + BLOCK]) {
            for (x, &li) in acc_t.iter_mut().zip(l) {
                *x = nmadd(li, l_jk, *x);
            }
        }
    }
    for (t, acc_t) in acc.iter().enumerate() {
        block[t * nrows + i..][..R].copy_from_slice(acc_t);
    }
}

/// Solves `L L^T x = b` in place for one right-hand side `x` (`b` on entry), with `L` the factor
/// [`factorize`] made in `l_values`. Per supernode, the entries of `x` on its off-diagonal rows
/// are gathered once, so that each column's update (forward) or dot product (backward) runs
/// over contiguous memory.
pub(crate) fn solve_one(symbolic: &SymbolicSupernodalCholesky<usize>, l_values: &[f64], x: &mut [f64]) {
    let (begin, end) = (symbolic.supernode_begin(), symbolic.supernode_end());
    let row_ptr = symbolic.col_ptr_for_row_idx();
    let val_ptr = symbolic.col_ptr_for_val();
    let rows = symbolic.row_idx();
    let n_super = symbolic.n_supernodes();
    let widest = (0..n_super).map(|s| row_ptr[s + 1] - row_ptr[s]).max().unwrap_or(0);
    let mut below = vec![0.0; widest];
    // Supernode `s`: its first column, its columns, its off-diagonal rows and its panel.
    let supernode = |s: usize| {
        let pattern = &rows[row_ptr[s]..row_ptr[s + 1]];
        (
            begin[s],
            end[s] - begin[s],
            pattern,
            &l_values[val_ptr[s]..val_ptr[s + 1]],
        )
    };
    // Forward: L y = b.
    for s in 0..n_super {
        let (s0, ncols, pattern, panel) = supernode(s);
        let t = gather(x, pattern, &mut below);
        let xs = &mut x[s0..s0 + ncols];
        for (j, col) in panel.chunks_exact(ncols + pattern.len()).enumerate() {
            let xj = xs[j] / col[j];
            xs[j] = xj;
            for (xi, l) in xs[j + 1..].iter_mut().zip(&col[j + 1..ncols]) {
                *xi -= l * xj;
            }
            for (ti, l) in t.iter_mut().zip(&col[ncols..]) {
                *ti -= l * xj;
            }
        }
        for (ti, &r) in t.iter().zip(pattern) {
            x[r] = *ti;
        }
    }
    // Backward: L^T x = y.
    for s in (0..n_super).rev() {
        let (s0, ncols, pattern, panel) = supernode(s);
        let t = gather(x, pattern, &mut below);
        let xs = &mut x[s0..s0 + ncols];
        for (j, col) in panel.chunks_exact(ncols + pattern.len()).enumerate().rev() {
            let mut v = xs[j];
            for (xi, l) in xs[j + 1..].iter().zip(&col[j + 1..ncols]) {
                v -= l * xi;
            }
            v -= dot(t, &col[ncols..]);
            xs[j] = v / col[j];
        }
    }
}

/// The entries of `x` at `rows`, into the front of `buffer`.
fn gather<'a>(x: &[f64], rows: &[usize], buffer: &'a mut [f64]) -> &'a mut [f64] {
    let t = &mut buffer[..rows.len()];
    for (ti, &r) in t.iter_mut().zip(rows) {
        *ti = x[r];
    }
    t
}

/// `a . b`, in four interleaved partial sums (which vectorise).
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (a4, a_rest) = a.as_chunks::<4>();
    let (b4, b_rest) = b.as_chunks::<4>();
    for (x, y) in a4.iter().zip(b4) {
        for ((s, xi), yi) in acc.iter_mut().zip(x).zip(y) {
            *s += xi * yi;
        }
    }
    let tail: f64 = a_rest.iter().zip(b_rest).map(|(x, y)| x * y).sum();
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}
