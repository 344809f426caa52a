//! The incremental smoother: partial re-elimination of the whole graph, iSAM2-style.
//!
//! The graph is kept eliminated as a Bayes net over every variable: per variable `j` a
//! Gaussian conditional `R_j dx_j + S_j dx_sep(j) = d_j` on the variables eliminated after it
//! that share a factor with it (its separator), with the elimination tree linking each
//! variable to the first of its separator (its parent). The linear system is the graph
//! linearised at a point `theta`; the estimate is `theta` moved by the solution `dx`.
//!
//! One [`IncrementalSmoother::update`]:
//!
//! 1. **Fluid relinearisation**: variables whose `dx` grew past
//!    thresholds ([`IncrementalParams::relinearize_rotation_rad`] and others) move their linearisation point to the
//!    estimate; the factors on them are linearised again.
//! 2. The variables of the new and relinearised factors, and every ancestor of theirs in the
//!    elimination tree, are **re-eliminated**; nothing else is touched. Subtrees hanging off
//!    that top part (orphans) enter through the marginal factor their elimination left on
//!    their separator, kept with their conditional. The re-eliminated part is ordered by
//!    approximate minimum degree with the newest state last (its pose the very last), so the
//!    next odometry step touches only the newest variables and a loop closure reorganises
//!    the cycle it closes into a shallow tree instead of a long path.
//! 3. **Back-substitution** from the roots, recomputing `dx` for the re-eliminated variables
//!    and descending into the rest of the tree only where a separator's `dx` changed by more
//!    than [`IncrementalParams::wildfire_threshold`].
//!
//! The cost of an update follows what its factors touch: an odometry step re-eliminates the
//! last two states; a loop closure re-eliminates the path from the older state to the root,
//! which the ordering keeps short after the first closure of a cycle. Nothing is re-solved
//! in the background, so the same input always gives the same estimate, at any feed rate.
//!
//! Nothing is conditioned on or dropped: the newest pose, eliminated last, is a root whose
//! conditional is its marginal, so [`IncrementalSmoother::newest_covariance`] is the full
//! marginal covariance (at the linearisation point), not the covariance given older states.
//!
//! Factors are linearised on demand at `theta` when their variables are re-eliminated (an
//! IMU factor costs a few microseconds), not cached; what is kept per variable is its
//! conditional and its separator's marginal factor.

use std::collections::BTreeSet;

use nalgebra::{DMatrix, DVector};

use crate::batch::{LmParams, LmReport, levenberg_marquardt};
use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::linear::Ordering;
use crate::values::{Values, VarId, Variable};
use crate::{Error, Result};

/// Settings of the incremental smoother.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IncrementalParams {
    /// A pose (or a line's angle) is relinearised when a rotation component of its step from
    /// the linearisation point exceeds this, rad.
    pub relinearize_rotation_rad: f64,
    /// ... or a translation component (a line's distance) exceeds this, m.
    pub relinearize_translation_m: f64,
    /// A velocity, when a component of its step exceeds this, m/s.
    pub relinearize_velocity_mps: f64,
    /// An IMU bias, when a component of its step exceeds this (m/s^2 and rad/s alike). The
    /// preintegrated IMU factor is first-order in the bias by construction, so this can be
    /// loose.
    pub relinearize_bias: f64,
    /// Back-substitution descends into a variable's subtree only when a separator's step
    /// changed by more than this.
    pub wildfire_threshold: f64,
    /// Compute the newest pose's marginal covariance after each update.
    pub newest_covariance: bool,
}

impl Default for IncrementalParams {
    fn default() -> Self {
        Self {
            relinearize_rotation_rad: 0.001,
            relinearize_translation_m: 0.1,
            relinearize_velocity_mps: 0.1,
            relinearize_bias: 0.1,
            wildfire_threshold: 1e-3,
            newest_covariance: true,
        }
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct IncrementalReport {
    /// Variables re-eliminated.
    pub eliminated: usize,
    /// Variables relinearised.
    pub relinearized: usize,
    /// Factors linearised.
    pub linearized: usize,
    /// Variables whose step was recomputed in back-substitution.
    pub solved: usize,
    /// Largest separator of a re-eliminated variable (scalar dimension).
    pub max_separator: usize,
}

/// A Gaussian conditional `r dx_j + s dx_sep = d`, and the marginal factor on `sep` that the
/// elimination of `j` (with its subtree) left behind.
#[derive(Debug, Clone)]
struct Conditional {
    sep: Vec<usize>,
    r: DMatrix<f64>,
    s: DMatrix<f64>,
    d: DVector<f64>,
    marginal: Hessian,
}

/// A factor in information form over `keys`: `0.5 dx' h dx + g' dx`.
#[derive(Debug, Clone)]
struct Hessian {
    keys: Vec<usize>,
    h: DMatrix<f64>,
    g: DVector<f64>,
}

/// The incremental smoother (see the module docs).
#[derive(Debug, Default)]
pub struct IncrementalSmoother {
    params: IncrementalParams,
    theta: Values,
    delta: Vec<DVector<f64>>,
    dims: Vec<usize>,
    factors_of: Vec<Vec<usize>>,
    known_factors: usize,
    cond: Vec<Option<Conditional>>,
    parent: Vec<Option<usize>>,
    children: Vec<Vec<usize>>,
    position: Vec<u64>,
    next_position: u64,
    /// Variables whose step exceeds the relinearisation threshold.
    over_threshold: BTreeSet<usize>,
    newest: Vec<usize>,
    newest_cov: Option<DMatrix<f64>>,
    states: usize,
    /// Scratch: per variable, its place in the part being re-eliminated (`usize::MAX`: none).
    local: Vec<usize>,
    /// Scratch: per variable, whether back-substitution moved its step (all false between
    /// updates).
    changed: Vec<bool>,
}

impl IncrementalSmoother {
    /// An empty smoother.
    #[must_use]
    pub fn new(params: IncrementalParams) -> Self {
        Self {
            params,
            ..Self::default()
        }
    }

    /// The settings.
    #[must_use]
    pub fn params(&self) -> &IncrementalParams {
        &self.params
    }

    /// Number of states so far.
    #[must_use]
    pub fn state_count(&self) -> usize {
        self.states
    }

    /// Marginal covariance `[rot x3, trans x3]` of the newest state's pose after the last
    /// update.
    #[must_use]
    pub fn newest_covariance(&self) -> Option<&DMatrix<f64>> {
        self.newest_cov.as_ref()
    }

    /// Adds the variables pushed to `values` and the factors added to `graph` since the last
    /// update (`new_state`: the newest state's variables, pose first, or empty), re-eliminates
    /// what they touch and writes the new estimate of every variable that moved to `values`.
    ///
    /// # Errors
    /// A factor that cannot be evaluated; a system that stays singular with damping.
    pub fn update(
        &mut self,
        graph: &FactorGraph,
        values: &mut Values,
        new_state: &[VarId],
    ) -> Result<IncrementalReport> {
        let mut report = IncrementalReport::default();
        let mut marked = BTreeSet::new();
        // New variables, linearised where the caller put them.
        for k in self.theta.len()..values.len() {
            let v = *values.get(VarId(k))?;
            self.theta.push(v);
            self.dims.push(v.dim());
            self.delta.push(DVector::zeros(v.dim()));
            self.factors_of.push(Vec::new());
            self.cond.push(None);
            self.parent.push(None);
            self.children.push(Vec::new());
            self.position.push(0);
            self.local.push(usize::MAX);
            self.changed.push(false);
            marked.insert(k);
        }
        if !new_state.is_empty() {
            self.newest = new_state.iter().map(|v| v.0).collect();
            self.states += 1;
        }
        // Fluid relinearisation: the step so far becomes part of the linearisation point.
        let relin: Vec<usize> = std::mem::take(&mut self.over_threshold).into_iter().collect();
        for &j in &relin {
            let moved = self.theta.get(VarId(j))?.retract(self.delta[j].as_view());
            self.theta.set(VarId(j), moved)?;
            self.delta[j].fill(0.0);
            for &fi in &self.factors_of[j] {
                marked.extend(graph.factors()[fi].keys().iter().map(|k| k.0));
            }
        }
        report.relinearized = relin.len();
        for fi in self.known_factors..graph.len() {
            for k in graph.factors()[fi].keys() {
                let list = self.factors_of.get_mut(k.0).ok_or(Error::UnknownVariable(k.0))?;
                list.push(fi);
                marked.insert(k.0);
            }
        }
        self.known_factors = graph.len();
        if marked.is_empty() {
            return Ok(report);
        }
        // The affected part: the marked variables and their ancestors.
        let mut affected = Vec::new();
        for &m in &marked {
            let mut v = Some(m);
            while let Some(j) = v {
                if self.local[j] != usize::MAX {
                    break;
                }
                self.local[j] = affected.len();
                affected.push(j);
                v = self.parent[j];
            }
        }
        let result = self.reeliminate(graph, &affected, &mut report);
        for &j in &affected {
            self.local[j] = usize::MAX;
        }
        let orphans = result?;
        self.back_substitute(&affected, &orphans, values, &mut report)?;
        self.newest_cov = None;
        if self.params.newest_covariance
            && let Some(&p) = self.newest.first()
            && let Some(c) = &self.cond[p]
            && c.sep.is_empty()
            && let Some(rinv) = c.r.clone().try_inverse()
        {
            self.newest_cov = Some(&rinv * rinv.transpose());
        }
        Ok(report)
    }

    /// Re-eliminates `affected` (closed under parents; `self.local` maps them to their index
    /// in it). Returns the orphans: variables outside it whose parent was in it.
    fn reeliminate(
        &mut self,
        graph: &FactorGraph,
        affected: &[usize],
        report: &mut IncrementalReport,
    ) -> Result<Vec<usize>> {
        let n = affected.len();
        let inside = |local: &[usize], k: usize| local[k] != usize::MAX;
        // The pool: factors whose variables are all affected (linearised now), and the
        // marginal factors of the orphan subtrees.
        let mut pool: Vec<Hessian> = Vec::new();
        let mut taken = BTreeSet::new();
        let mut orphans = Vec::new();
        for &j in affected {
            for &fi in &self.factors_of[j] {
                if taken.contains(&fi) {
                    continue;
                }
                if graph.factors()[fi].keys().iter().all(|k| inside(&self.local, k.0)) {
                    taken.insert(fi);
                    pool.push(self.linearize(graph.factors()[fi].as_ref())?);
                }
            }
            for &c in &self.children[j] {
                if !inside(&self.local, c) {
                    orphans.push(c);
                }
            }
        }
        report.linearized += pool.len();
        orphans.sort_unstable();
        for &c in &orphans {
            let cond = self.cond[c].as_ref().ok_or(Error::LinearSolve(format!(
                "variable {c} has a parent but no conditional"
            )))?;
            pool.push(cond.marginal.clone());
            self.parent[c] = None;
        }
        for &j in affected {
            self.cond[j] = None;
            self.parent[j] = None;
            self.children[j].clear();
        }
        // Elimination order: minimum degree over the affected variables, the newest state
        // last (its pose the very last).
        let order = self.elimination_order(affected, &pool)?;
        let mut rank = vec![0usize; n];
        for (r, &l) in order.iter().enumerate() {
            rank[l] = r;
        }
        // Factors by the rank of their first variable to be eliminated.
        let mut waiting: Vec<Vec<usize>> = vec![Vec::new(); n];
        let first =
            |f: &Hessian, local: &[usize], rank: &[usize]| f.keys.iter().map(|k| rank[local[*k]]).min().unwrap_or(0);
        for (i, f) in pool.iter().enumerate() {
            waiting[first(f, &self.local, &rank)].push(i);
        }
        let mut pool: Vec<Option<Hessian>> = pool.into_iter().map(Some).collect();
        for r in 0..n {
            let j = affected[order[r]];
            let gathered: Vec<Hessian> = std::mem::take(&mut waiting[r])
                .into_iter()
                .filter_map(|i| pool[i].take())
                .collect();
            let cond = self.eliminate_one(j, &gathered, &rank)?;
            report.max_separator = report.max_separator.max(cond.s.ncols());
            self.position[j] = self.next_position;
            self.next_position += 1;
            if let Some(&p) = cond.sep.first() {
                self.parent[j] = Some(p);
                self.children[p].push(j);
            }
            if !cond.marginal.keys.is_empty() {
                let at = first(&cond.marginal, &self.local, &rank);
                waiting[at].push(pool.len());
                pool.push(Some(cond.marginal.clone()));
            }
            self.cond[j] = Some(cond);
        }
        report.eliminated += n;
        // Each orphan hangs off the first of its separator to be eliminated.
        for &c in &orphans {
            let cond = self.cond[c].as_ref().ok_or(Error::UnknownVariable(c))?;
            if let Some(&p) = cond.sep.iter().min_by_key(|k| self.position[**k]) {
                self.parent[c] = Some(p);
                self.children[p].push(c);
            }
        }
        Ok(orphans)
    }

    /// Positions in `affected` in elimination order.
    fn elimination_order(&self, affected: &[usize], pool: &[Hessian]) -> Result<Vec<usize>> {
        let n = affected.len();
        let mut adjacency: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); n];
        for f in pool {
            for a in &f.keys {
                for b in &f.keys {
                    let (la, lb) = (self.local[*a], self.local[*b]);
                    if la > lb {
                        adjacency[lb].insert(la);
                    }
                }
            }
        }
        let mut adj: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (b, set) in adjacency.iter().enumerate() {
            for &a in set {
                adj[a].push(b);
                adj[b].push(a);
            }
        }
        let mut order = Vec::with_capacity(n);
        let dims: Vec<usize> = affected.iter().map(|k| self.dims[*k]).collect();
        nested_dissection(&adj, &dims, (0..n).collect(), &mut vec![usize::MAX; n], &mut order);
        // The newest state last, its first variable (the pose) the very last.
        let last: Vec<usize> = self
            .newest
            .iter()
            .rev()
            .filter(|k| **k < self.local.len() && self.local[**k] != usize::MAX)
            .map(|k| self.local[*k])
            .collect();
        order.retain(|l| !last.contains(l));
        order.extend(last);
        Ok(order)
    }

    /// The whitened, robust-reweighted linearisation of `f` at `theta`, in information form.
    fn linearize(&self, f: &dyn Factor) -> Result<Hessian> {
        let noise = f.noise();
        let m = noise.dim();
        let keys: Vec<usize> = f.keys().iter().map(|k| k.0).collect();
        let mut jac: Vec<DMatrix<f64>> = keys.iter().map(|k| DMatrix::zeros(m, self.dims[*k])).collect();
        let r = f.evaluate(&self.theta, Some(&mut jac))?;
        let cols: usize = keys.iter().map(|k| self.dims[*k]).sum();
        let mut a = DMatrix::zeros(m, cols);
        let mut c0 = 0;
        for j in &jac {
            a.columns_mut(c0, j.ncols()).copy_from(j);
            c0 += j.ncols();
        }
        noise.whiten_jacobian(&mut a);
        let mut rw = noise.whiten(&r);
        let s = noise.robust_scale(&rw);
        if s != 1.0 {
            a *= s;
            rw *= s;
        }
        Ok(Hessian {
            keys,
            h: a.transpose() * &a,
            g: a.transpose() * rw,
        })
    }

    /// Eliminates `j` from the factors `gathered` (all the factors on it that remain).
    fn eliminate_one(&self, j: usize, gathered: &[Hessian], rank: &[usize]) -> Result<Conditional> {
        // Separator: the other variables of the gathered factors, in elimination order.
        let mut sep: Vec<usize> = gathered
            .iter()
            .flat_map(|f| f.keys.iter().copied())
            .filter(|k| *k != j)
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        sep.sort_by_key(|k| rank[self.local[*k]]);
        let dj = self.dims[j];
        let mut offset = vec![0usize; sep.len() + 1];
        for (i, k) in sep.iter().enumerate() {
            offset[i + 1] = offset[i] + self.dims[*k];
        }
        let ds = offset[sep.len()];
        let slot = |k: usize| -> usize {
            if k == j {
                0
            } else {
                dj + offset[sep.iter().position(|s| *s == k).unwrap_or(0)]
            }
        };
        let mut h = DMatrix::zeros(dj + ds, dj + ds);
        let mut g = DVector::zeros(dj + ds);
        for f in gathered {
            let mut fo = 0;
            for a in &f.keys {
                let (sa, da) = (slot(*a), self.dims[*a]);
                let mut seg = g.rows_mut(sa, da);
                seg += f.g.rows(fo, da);
                let mut fo2 = 0;
                for b in &f.keys {
                    let (sb, db) = (slot(*b), self.dims[*b]);
                    let mut block = h.view_mut((sa, sb), (da, db));
                    block += f.h.view((fo, fo2), (da, db));
                    fo2 += db;
                }
                fo += da;
            }
        }
        let hjj = h.view((0, 0), (dj, dj)).into_owned();
        let chol = match hjj.clone().cholesky() {
            Some(c) => c,
            None => {
                // Unobservable from what is known so far (a line seen from one place): a small
                // damping keeps the step finite.
                let scale = hjj.diagonal().amax().max(1.0);
                let damped = hjj + DMatrix::identity(dj, dj) * (1e-9 * scale);
                damped.cholesky().ok_or_else(|| {
                    Error::LinearSolve(format!("variable {j} is singular in the incremental elimination"))
                })?
            }
        };
        let l = chol.l();
        let s = l
            .solve_lower_triangular(&h.view((0, dj), (dj, ds)).into_owned())
            .ok_or_else(|| Error::LinearSolve(format!("variable {j}: triangular solve")))?;
        let d = -l
            .solve_lower_triangular(&g.rows(0, dj).into_owned())
            .ok_or_else(|| Error::LinearSolve(format!("variable {j}: triangular solve")))?;
        let marginal = Hessian {
            h: h.view((dj, dj), (ds, ds)) - s.transpose() * &s,
            g: g.rows(dj, ds) + s.transpose() * &d,
            keys: sep.clone(),
        };
        Ok(Conditional {
            sep,
            r: l.transpose(),
            s,
            d,
            marginal,
        })
    }

    /// Recomputes the steps of `affected` and, where their steps changed, of the subtrees
    /// below, and writes the moved estimates to `values`.
    fn back_substitute(
        &mut self,
        affected: &[usize],
        orphans: &[usize],
        values: &mut Values,
        report: &mut IncrementalReport,
    ) -> Result<()> {
        let mut top: Vec<usize> = affected.to_vec();
        top.sort_by_key(|j| std::cmp::Reverse(self.position[*j]));
        let mut solved = Vec::new();
        for &j in &top {
            if self.solve_one(j)? {
                self.changed[j] = true;
            }
            solved.push(j);
        }
        let mut stack: Vec<usize> = orphans.iter().rev().copied().collect();
        while let Some(c) = stack.pop() {
            let Some(cond) = &self.cond[c] else { continue };
            if !cond.sep.iter().any(|k| self.changed[*k]) {
                continue;
            }
            if self.solve_one(c)? {
                self.changed[c] = true;
            }
            solved.push(c);
            stack.extend(self.children[c].iter().rev());
        }
        report.solved += solved.len();
        for &j in &solved {
            self.changed[j] = false;
        }
        for j in solved {
            let est = self.theta.get(VarId(j))?.retract(self.delta[j].as_view());
            values.set(VarId(j), est)?;
            if self.needs_relinearisation(j)? {
                self.over_threshold.insert(j);
            } else {
                self.over_threshold.remove(&j);
            }
        }
        Ok(())
    }

    /// True when `j`'s step from its linearisation point is past its kind's threshold.
    fn needs_relinearisation(&self, j: usize) -> Result<bool> {
        let p = &self.params;
        let dx = &self.delta[j];
        let over = |range: std::ops::Range<usize>, limit: f64| dx.rows(range.start, range.len()).amax() > limit;
        Ok(match self.theta.get(VarId(j))? {
            Variable::Pose(_) => over(0..3, p.relinearize_rotation_rad) || over(3..6, p.relinearize_translation_m),
            Variable::Velocity(_) => over(0..3, p.relinearize_velocity_mps),
            Variable::Bias(_) => over(0..6, p.relinearize_bias),
            Variable::Line(_) => over(0..1, p.relinearize_translation_m) || over(1..2, p.relinearize_rotation_rad),
        })
    }

    /// Back-substitutes every variable, however little its separator moved, and writes every
    /// estimate to `values`: the updates' back-substitution stops where the steps change by
    /// less than [`IncrementalParams::wildfire_threshold`], and such small changes add up over
    /// many updates (GTSAM's `calculateBestEstimate`). Costs one pass over the whole graph.
    ///
    /// # Errors
    /// Values that do not belong to this smoother.
    pub fn refresh(&mut self, values: &mut Values) -> Result<()> {
        let mut order: Vec<usize> = (0..self.theta.len()).filter(|j| self.cond[*j].is_some()).collect();
        order.sort_unstable_by_key(|j| std::cmp::Reverse(self.position[*j]));
        for &j in &order {
            self.solve_one(j)?;
        }
        for j in order {
            values.set(VarId(j), self.theta.get(VarId(j))?.retract(self.delta[j].as_view()))?;
            if self.needs_relinearisation(j)? {
                self.over_threshold.insert(j);
            } else {
                self.over_threshold.remove(&j);
            }
        }
        Ok(())
    }

    /// `dx_j` from its conditional; true when it moved by more than the wildfire threshold.
    fn solve_one(&mut self, j: usize) -> Result<bool> {
        let cond = self.cond[j].as_ref().ok_or(Error::UnknownVariable(j))?;
        let dj = cond.d.len();
        // Every variable kind has at most 6 dimensions: the step fits on the stack.
        let mut x = [0.0f64; 6];
        x[..dj].copy_from_slice(cond.d.as_slice());
        let mut col = 0;
        for k in &cond.sep {
            for &v in self.delta[*k].iter() {
                if v != 0.0 {
                    let s = &cond.s.as_slice()[col * dj..(col + 1) * dj];
                    for (xi, si) in x[..dj].iter_mut().zip(s) {
                        *xi -= si * v;
                    }
                }
                col += 1;
            }
        }
        // R upper triangular (column-major): back-substitution in place.
        let r = cond.r.as_slice();
        for i in (0..dj).rev() {
            let mut acc = x[i];
            for c in i + 1..dj {
                acc -= r[c * dj + i] * x[c];
            }
            let diag = r[i * dj + i];
            if diag == 0.0 {
                return Err(Error::LinearSolve(format!("variable {j}: singular conditional")));
            }
            x[i] = acc / diag;
        }
        let old = &mut self.delta[j];
        let mut moved = false;
        for (o, n) in old.iter_mut().zip(&x[..dj]) {
            moved |= (*o - n).abs() > self.params.wildfire_threshold;
            *o = *n;
        }
        Ok(moved)
    }

    /// Ends a run: Levenberg-Marquardt on the whole graph from the current estimate.
    ///
    /// # Errors
    /// A factor that cannot be evaluated.
    pub fn finish(&mut self, graph: &FactorGraph, values: &mut Values) -> Result<LmReport> {
        self.refresh(values)?;
        let all: Vec<usize> = (0..graph.len()).collect();
        let ordering = Ordering::all(values);
        levenberg_marquardt(graph, &all, values, &ordering, &LmParams::default(), &mut None)
    }
}

/// Parts of the graph at most this large are ordered by minimum degree.
const DISSECTION_LEAF: usize = 24;

/// Appends `nodes` (a part of the graph `adj`) to `order` in nested-dissection order: a BFS
/// level from a far node splits the part in two, each half is ordered the same way before the
/// level; small parts by minimum degree. On the chain of states with loop closures that the
/// estimator builds, the levels are one or two states, so the elimination tree is balanced:
/// a change anywhere re-eliminates a logarithmic path to the root. `mark` is scratch
/// (`usize::MAX` everywhere between calls).
fn nested_dissection(
    adj: &[Vec<usize>],
    dims: &[usize],
    nodes: Vec<usize>,
    mark: &mut [usize],
    order: &mut Vec<usize>,
) {
    const IN: usize = usize::MAX - 1;
    if nodes.len() <= DISSECTION_LEAF {
        minimum_degree(adj, &nodes, mark, order);
        return;
    }
    for &v in &nodes {
        mark[v] = IN;
    }
    // Connected components of the part, each dissected on its own.
    let mut components = Vec::new();
    for &v in &nodes {
        if mark[v] == IN {
            components.push(bfs_levels(adj, v, mark, IN).concat());
        }
    }
    for &v in &nodes {
        mark[v] = usize::MAX;
    }
    for all in components {
        if all.len() <= DISSECTION_LEAF {
            minimum_degree(adj, &all, mark, order);
            continue;
        }
        // From the node farthest from an arbitrary start (a pseudo-peripheral node).
        for &v in &all {
            mark[v] = IN;
        }
        let first = bfs_levels(adj, all[0], mark, IN);
        let far = first.last().and_then(|l| l.iter().min()).copied().unwrap_or(all[0]);
        for &v in &all {
            mark[v] = IN;
        }
        let levels = bfs_levels(adj, far, mark, IN);
        for &v in &all {
            mark[v] = usize::MAX;
        }
        if levels.len() < 3 {
            minimum_degree(adj, &all, mark, order);
            continue;
        }
        // The smallest level of the middle half (by scalar dimension), nearest the middle.
        let half = levels.len() / 2;
        let mid = ((levels.len() / 4).max(1)..=(3 * levels.len() / 4).min(levels.len() - 2))
            .min_by_key(|l| {
                let size: usize = levels[*l].iter().map(|v| dims[*v]).sum();
                (size, l.abs_diff(half))
            })
            .unwrap_or(half);
        let below: Vec<usize> = levels[..mid].iter().flatten().copied().collect();
        let above: Vec<usize> = levels[mid + 1..].iter().flatten().copied().collect();
        nested_dissection(adj, dims, below, mark, order);
        nested_dissection(adj, dims, above, mark, order);
        order.extend(levels[mid].iter().copied());
    }
}

/// BFS levels from `start` over the nodes marked `inside` (marks each visited node with its
/// level); nodes within a level sorted.
fn bfs_levels(adj: &[Vec<usize>], start: usize, mark: &mut [usize], inside: usize) -> Vec<Vec<usize>> {
    let mut levels = vec![vec![start]];
    mark[start] = 0;
    loop {
        let mut next = Vec::new();
        for &v in levels.last().map_or(&[][..], |l| &l[..]) {
            for &w in &adj[v] {
                if mark[w] == inside {
                    mark[w] = levels.len();
                    next.push(w);
                }
            }
        }
        if next.is_empty() {
            return levels;
        }
        next.sort_unstable();
        levels.push(next);
    }
}

/// Appends `nodes` to `order` by exact minimum degree on the part they induce (ties: the
/// lowest index). For small parts.
fn minimum_degree(adj: &[Vec<usize>], nodes: &[usize], mark: &mut [usize], order: &mut Vec<usize>) {
    for (i, &v) in nodes.iter().enumerate() {
        mark[v] = i;
    }
    let mut nbrs: Vec<BTreeSet<usize>> = nodes
        .iter()
        .map(|&v| {
            adj[v]
                .iter()
                .filter(|w| mark[**w] != usize::MAX && **w != v)
                .map(|w| mark[*w])
                .collect()
        })
        .collect();
    for &v in nodes {
        mark[v] = usize::MAX;
    }
    let mut done = vec![false; nodes.len()];
    for _ in 0..nodes.len() {
        let Some(best) = (0..nodes.len())
            .filter(|i| !done[*i])
            .min_by_key(|i| (nbrs[*i].len(), *i))
        else {
            break;
        };
        done[best] = true;
        order.push(nodes[best]);
        let around: Vec<usize> = std::mem::take(&mut nbrs[best]).into_iter().collect();
        for &a in &around {
            nbrs[a].remove(&best);
            for &b in &around {
                if a != b {
                    nbrs[a].insert(b);
                }
            }
        }
    }
}
