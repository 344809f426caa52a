//! The incremental smoother: partial re-elimination of the whole graph, iSAM2-style.
//!
//! The graph is kept eliminated as a Bayes tree. Variables are eliminated in groups (a state's
//! pose, velocity and bias together; a line on its own): per group `G` a Gaussian conditional
//! `R_G dx_G + S_G dx_sep(G) = d_G` on the variables eliminated after it that share a factor
//! with it (its separator), and the tree links each group to the group of the first of its
//! separator (its parent). The linear system is the graph linearised at a point `theta`; the
//! estimate is `theta` moved by the solution `dx`.
//!
//! One [`IncrementalSmoother::update`]:
//!
//! 1. **Fluid relinearisation**: variables whose `dx` grew past their kind's threshold
//!    ([`IncrementalParams::relinearize_rotation_rad`] and the others) move their
//!    linearisation point to the estimate; the factors on them are linearised again.
//! 2. The groups of the new and relinearised factors, and every ancestor of theirs in the
//!    tree, are **re-eliminated**; nothing else is touched. Subtrees hanging off that top
//!    part (orphans) enter through the marginal factor their elimination left on their
//!    separator, kept with their conditional. The re-eliminated part is ordered by nested
//!    dissection (a breadth-first level as separator, halves first), with the newest state
//!    last, so the next odometry step touches only the newest states and the tree stays
//!    shallow: a loop closure or a relinearisation deep in the past re-eliminates a path of
//!    logarithmic length, not the whole trajectory after it (which an elimination in time
//!    order, or minimum degree on the chain, would).
//! 3. **Back-substitution** from the roots, recomputing `dx` for the re-eliminated groups
//!    and descending into the rest of the tree only where a separator's `dx` changed by more
//!    than [`IncrementalParams::wildfire_threshold`]. Such small changes add up over many
//!    updates: [`IncrementalSmoother::refresh`] back-substitutes everything (for a whole
//!    trajectory, and at the end).
//!
//! The cost of an update follows what its factors touch, not the length of the run. Nothing
//! runs in the background, so the same input always gives the same estimate, at any feed
//! rate.
//!
//! Nothing is conditioned on or dropped: the newest state, eliminated last, is a root whose
//! conditional is its marginal, so [`IncrementalSmoother::newest_covariance`] is the full
//! marginal covariance (at the linearisation point), not the covariance given older states.
//!
//! Factors are linearised on demand at `theta` when their groups are re-eliminated (an IMU
//! factor costs a few microseconds), not cached; what is kept per group is its conditional
//! and its separator's marginal factor.

use std::collections::BTreeSet;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use crate::batch::{LmParams, LmReport, levenberg_marquardt};
use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::linear::{Information, Ordering};
use crate::values::{Values, VarId, Variable};
use crate::{Error, Result};

/// Settings of the incremental smoother (the `estimate` stage's `incremental` parameter).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
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
    /// Back-substitution descends into a group's subtree only when a separator's step
    /// changed by more than this (any unit).
    pub wildfire_threshold: f64,
    /// At most this many variables relinearised per update (0: no limit), those furthest past
    /// their threshold first; the rest wait for the next updates. A loop closure moves a
    /// whole loop's worth of poses past the threshold at once; spreading their
    /// relinearisation keeps each update short. On long IMU runs the whole past keeps
    /// moving (each refinement of the bias turns the trajectory behind it), more variables
    /// cross the threshold per update than this takes, and the waiting ones
    /// ([`IncrementalReport::relinearize_pending`]) pile up (4282 by state 4490 of the
    /// simulator's 20.9-minute basement run) until the estimate diverges (state 4643).
    pub max_relinearized_per_update: usize,
    /// Relinearise no more variables in an update once the part it re-eliminates has this many
    /// groups (0: no limit; always at least one variable, so the waiting ones are worked off).
    /// Variables are relinearised where they lie, scattered over the tree, and each adds its
    /// path to the root: this keeps those updates near the cost of an update without them.
    pub relinearize_budget_groups: usize,
    /// Compute the newest pose's marginal covariance after each update.
    pub newest_covariance: bool,
}

impl Default for IncrementalParams {
    /// Chosen on the GTSAM peer's default problem (N = 2000, seed 1, lap 500, radius 15):
    /// rotation is what needs relinearising; the online estimate ends within 0.2 % of the
    /// batch optimum's error. A budget of 48 groups took the per-update p99 from 8-10 ms to
    /// 4 ms there (32: 0.75 % from the optimum; 64: p99 5-7 ms).
    fn default() -> Self {
        Self {
            relinearize_rotation_rad: 0.001,
            relinearize_translation_m: 0.1,
            relinearize_velocity_mps: 0.1,
            relinearize_bias: 0.1,
            wildfire_threshold: 1e-2,
            max_relinearized_per_update: 32,
            relinearize_budget_groups: 48,
            newest_covariance: true,
        }
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct IncrementalReport {
    /// Groups re-eliminated.
    pub eliminated: usize,
    /// Variables relinearised.
    pub relinearized: usize,
    /// Factors linearised.
    pub linearized: usize,
    /// Groups whose step was recomputed in back-substitution.
    pub solved: usize,
    /// Largest separator of a re-eliminated group (scalar dimension).
    pub max_separator: usize,
    /// Variables past their relinearisation threshold left for later updates (see
    /// [`IncrementalParams::max_relinearized_per_update`]).
    pub relinearize_pending: usize,
}

/// A Gaussian conditional `r dx_G + s dx_sep = d` of a group, and the marginal factor on
/// `sep` that the elimination of the group (with its subtree) left behind.
#[derive(Debug, Clone)]
struct Conditional {
    sep: Vec<usize>,
    r: DMatrix<f64>,
    s: DMatrix<f64>,
    d: DVector<f64>,
    /// Shared with the pool of the elimination that made it and of later ones that take this
    /// group as an orphan: a separator's marginal can be hundreds of rows.
    marginal: Arc<Hessian>,
}

/// A factor in information form over the variables `keys`: `0.5 dx' h dx + g' dx`.
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
    // Per variable.
    theta: Values,
    delta: Vec<DVector<f64>>,
    dims: Vec<usize>,
    factors_of: Vec<Vec<usize>>,
    group_of: Vec<usize>,
    /// Whether back-substitution moved the step (all false between updates).
    changed: Vec<bool>,
    /// Variables whose step exceeds the relinearisation threshold.
    over_threshold: BTreeSet<usize>,
    known_factors: usize,
    // Per group.
    groups: Vec<Vec<usize>>,
    group_dim: Vec<usize>,
    cond: Vec<Option<Conditional>>,
    parent: Vec<Option<usize>>,
    children: Vec<Vec<usize>>,
    position: Vec<u64>,
    /// Scratch: the group's place in the part being re-eliminated (`usize::MAX`: none).
    local: Vec<usize>,
    next_position: u64,
    newest: Option<usize>,
    newest_cov: Option<DMatrix<f64>>,
    /// The group of every state, in order.
    state_groups: Vec<usize>,
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
        self.state_groups.len()
    }

    /// Marginal covariance `[rot x3, trans x3]` of the newest state's pose after the last
    /// update.
    #[must_use]
    pub fn newest_covariance(&self) -> Option<&DMatrix<f64>> {
        self.newest_cov.as_ref()
    }

    fn new_group(&mut self, vars: Vec<usize>) -> usize {
        let g = self.groups.len();
        for &v in &vars {
            self.group_of[v] = g;
        }
        self.group_dim.push(vars.iter().map(|v| self.dims[*v]).sum());
        self.groups.push(vars);
        self.cond.push(None);
        self.parent.push(None);
        self.children.push(Vec::new());
        self.position.push(0);
        self.local.push(usize::MAX);
        g
    }

    /// Adds the variables pushed to `values` and the factors added to `graph` since the last
    /// update (`new_state`: the newest state's variables, pose first, or empty; they are
    /// eliminated together), re-eliminates what they touch and writes the new estimate of
    /// every variable that moved to `values`.
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
        let first_new = self.theta.len();
        for k in first_new..values.len() {
            let v = *values.get(VarId(k))?;
            self.theta.push(v);
            self.dims.push(v.dim());
            self.delta.push(DVector::zeros(v.dim()));
            self.factors_of.push(Vec::new());
            self.group_of.push(usize::MAX);
            self.changed.push(false);
        }
        let state: Vec<usize> = new_state.iter().map(|v| v.0).filter(|v| *v >= first_new).collect();
        if !state.is_empty() {
            let g = self.new_group(state);
            marked.insert(g);
            self.newest = Some(g);
            self.state_groups.push(g);
            // Odometry alone stacks each new state on the root: the tree above the last
            // re-dissected part is a path. Re-dissecting the newest states at doubling
            // scales (64 and 128 states, every state twice in all: blocks of at most
            // `REBALANCE_MAX`) keeps it shallow, so that a factor deep in the past
            // re-eliminates a short path even in a run without loop closures.
            let u = self.state_groups.len();
            if u.is_multiple_of(REBALANCE_MIN) {
                let k = (1usize << u.trailing_zeros()).min(REBALANCE_MAX);
                marked.extend(self.state_groups[u - k..].iter().copied());
            }
        }
        for k in first_new..values.len() {
            if self.group_of[k] == usize::MAX {
                marked.insert(self.new_group(vec![k]));
            }
        }
        for fi in self.known_factors..graph.len() {
            for k in graph.factors()[fi].keys() {
                let list = self.factors_of.get_mut(k.0).ok_or(Error::UnknownVariable(k.0))?;
                list.push(fi);
                marked.insert(self.group_of[k.0]);
            }
        }
        self.known_factors = graph.len();
        // The affected part: the marked groups and their ancestors.
        let mut affected = Vec::new();
        for &m in &marked {
            self.add_with_ancestors(m, &mut affected);
        }
        // Fluid relinearisation: the step so far becomes part of the linearisation point.
        report.relinearized = match self.relinearise(graph, &mut affected) {
            Ok(n) => n,
            Err(e) => {
                for &j in &affected {
                    self.local[j] = usize::MAX;
                }
                return Err(e);
            }
        };
        if affected.is_empty() {
            return Ok(report);
        }
        let result = self.reeliminate(graph, &affected, &mut report);
        for &j in &affected {
            self.local[j] = usize::MAX;
        }
        let orphans = result?;
        self.back_substitute(&affected, &orphans, values, &mut report)?;
        report.relinearize_pending = self.over_threshold.len();
        self.newest_cov = None;
        if self.params.newest_covariance
            && let Some(g) = self.newest
            && let Some(c) = &self.cond[g]
            && c.sep.is_empty()
            && let Some(rinv) = c.r.clone().try_inverse()
        {
            // The group's marginal; the pose is its first variable.
            let cov = &rinv * rinv.transpose();
            let dp = self.dims[self.groups[g][0]];
            self.newest_cov = Some(cov.view((0, 0), (dp, dp)).into_owned());
        }
        Ok(report)
    }

    /// Re-eliminates the groups `affected` (closed under parents; `self.local` maps them to
    /// their index in it). Returns the orphans: groups outside it whose parent was in it.
    fn reeliminate(
        &mut self,
        graph: &FactorGraph,
        affected: &[usize],
        report: &mut IncrementalReport,
    ) -> Result<Vec<usize>> {
        let n = affected.len();
        // The pool: factors whose variables are all affected (linearised now), and the
        // marginal factors of the orphan subtrees.
        let mut pool: Vec<Arc<Hessian>> = Vec::new();
        let mut taken = BTreeSet::new();
        let mut orphans = Vec::new();
        for &g in affected {
            for &j in &self.groups[g] {
                for &fi in &self.factors_of[j] {
                    if taken.contains(&fi) {
                        continue;
                    }
                    let keys = graph.factors()[fi].keys();
                    if keys.iter().all(|k| self.local[self.group_of[k.0]] != usize::MAX) {
                        taken.insert(fi);
                        pool.push(Arc::new(self.linearize(graph.factors()[fi].as_ref())?));
                    }
                }
            }
            for &c in &self.children[g] {
                if self.local[c] == usize::MAX {
                    orphans.push(c);
                }
            }
        }
        report.linearized += pool.len();
        orphans.sort_unstable();
        for &c in &orphans {
            let cond = self.cond[c]
                .as_ref()
                .ok_or_else(|| Error::LinearSolve(format!("group {c} has a parent but no conditional")))?;
            pool.push(Arc::clone(&cond.marginal));
            self.parent[c] = None;
        }
        for &g in affected {
            self.cond[g] = None;
            self.parent[g] = None;
            self.children[g].clear();
        }
        let order = self.elimination_order(affected, &pool);
        let mut rank = vec![0usize; n];
        for (r, &l) in order.iter().enumerate() {
            rank[l] = r;
        }
        // Factors by the rank of their first group to be eliminated.
        let first = |f: &Hessian, this: &Self| {
            f.keys
                .iter()
                .map(|k| rank[this.local[this.group_of[*k]]])
                .min()
                .unwrap_or(0)
        };
        let mut waiting: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (i, f) in pool.iter().enumerate() {
            waiting[first(f, self)].push(i);
        }
        let mut pool: Vec<Option<Arc<Hessian>>> = pool.into_iter().map(Some).collect();
        for r in 0..n {
            let g = affected[order[r]];
            let gathered: Vec<Arc<Hessian>> = std::mem::take(&mut waiting[r])
                .into_iter()
                .filter_map(|i| pool[i].take())
                .collect();
            let cond = self.eliminate_group(g, &gathered, &rank)?;
            report.max_separator = report.max_separator.max(cond.s.ncols());
            self.position[g] = self.next_position;
            self.next_position += 1;
            if let Some(&p) = cond.sep.first() {
                let pg = self.group_of[p];
                self.parent[g] = Some(pg);
                self.children[pg].push(g);
            }
            if !cond.marginal.keys.is_empty() {
                waiting[first(&cond.marginal, self)].push(pool.len());
                pool.push(Some(Arc::clone(&cond.marginal)));
            }
            self.cond[g] = Some(cond);
        }
        report.eliminated += n;
        // Each orphan hangs off the group of the first of its separator to be eliminated.
        for &c in &orphans {
            let cond = self.cond[c].as_ref().ok_or(Error::UnknownVariable(c))?;
            if let Some(pg) = cond
                .sep
                .iter()
                .map(|k| self.group_of[*k])
                .min_by_key(|g| self.position[*g])
            {
                self.parent[c] = Some(pg);
                self.children[pg].push(c);
            }
        }
        Ok(orphans)
    }

    /// Places in `affected` in elimination order: nested dissection on the groups' graph,
    /// the newest state last.
    fn elimination_order(&self, affected: &[usize], pool: &[Arc<Hessian>]) -> Vec<usize> {
        let n = affected.len();
        let mut adjacency: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); n];
        let mut locals = Vec::new();
        for f in pool {
            locals.clear();
            locals.extend(f.keys.iter().map(|k| self.local[self.group_of[*k]]));
            for &a in &locals {
                for &b in &locals {
                    if a != b {
                        adjacency[a].insert(b);
                    }
                }
            }
        }
        let adj: Vec<Vec<usize>> = adjacency.into_iter().map(|s| s.into_iter().collect()).collect();
        let dims: Vec<usize> = affected.iter().map(|g| self.group_dim[*g]).collect();
        let mut order = Vec::with_capacity(n);
        nested_dissection(&adj, &dims, (0..n).collect(), &mut vec![usize::MAX; n], &mut order);
        if let Some(last) = self.newest.map(|g| self.local[g]).filter(|l| *l != usize::MAX) {
            order.retain(|l| *l != last);
            order.push(last);
        }
        order
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
        let (mut h, mut g) = (DMatrix::zeros(cols, cols), DVector::zeros(cols));
        crate::linear::whitened_gram(noise, &a, &r, &mut Information::default(), &mut h, &mut g);
        Ok(Hessian { keys, h, g })
    }

    /// Eliminates the group `g` from the factors `gathered` (all the factors on it that
    /// remain).
    fn eliminate_group(&self, g: usize, gathered: &[Arc<Hessian>], rank: &[usize]) -> Result<Conditional> {
        let frontal = &self.groups[g];
        // Separator: the other variables of the gathered factors, in elimination order.
        let mut sep: Vec<usize> = gathered
            .iter()
            .flat_map(|f| f.keys.iter().copied())
            .filter(|k| self.group_of[*k] != g)
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        sep.sort_by_key(|k| (rank[self.local[self.group_of[*k]]], *k));
        let dg = self.group_dim[g];
        // Slots: the frontal variables first, then the separator.
        let mut slot_of: Vec<(usize, usize)> = Vec::with_capacity(frontal.len() + sep.len());
        let mut at = 0;
        for &v in frontal.iter().chain(&sep) {
            slot_of.push((v, at));
            at += self.dims[v];
        }
        let total = at;
        let ds = total - dg;
        slot_of.sort_unstable();
        let slot = |k: usize| -> usize {
            slot_of
                .binary_search_by_key(&k, |(v, _)| *v)
                .map_or(0, |i| slot_of[i].1)
        };
        // The system split at the frontal block: `[hgg hgs; hgs' hss]`, `[gg; gs]`. The
        // separator's block is accumulated where the marginal will be made, so the largest
        // matrix is neither copied nor multiplied into a new one.
        let mut hgg = DMatrix::zeros(dg, dg);
        let mut hgs = DMatrix::zeros(dg, ds);
        let mut hss = DMatrix::zeros(ds, ds);
        let mut gg = DVector::zeros(dg);
        let mut gs = DVector::zeros(ds);
        for f in gathered {
            let mut fo = 0;
            for a in &f.keys {
                let (sa, da) = (slot(*a), self.dims[*a]);
                let src = &f.g.as_slice()[fo..fo + da];
                let dst = if sa < dg {
                    &mut gg.as_mut_slice()[sa..sa + da]
                } else {
                    &mut gs.as_mut_slice()[sa - dg..sa - dg + da]
                };
                dst.iter_mut().zip(src).for_each(|(x, v)| *x += v);
                let mut fo2 = 0;
                for b in &f.keys {
                    let (sb, db) = (slot(*b), self.dims[*b]);
                    match (sa < dg, sb < dg) {
                        (true, true) => add_block(&mut hgg, (sa, sb), &f.h, (fo, fo2), (da, db)),
                        (true, false) => add_block(&mut hgs, (sa, sb - dg), &f.h, (fo, fo2), (da, db)),
                        (false, false) => add_block(&mut hss, (sa - dg, sb - dg), &f.h, (fo, fo2), (da, db)),
                        // The transpose of a block of `hgs`.
                        (false, true) => {}
                    }
                    fo2 += db;
                }
                fo += da;
            }
        }
        let chol = match hgg.clone().cholesky() {
            Some(c) => c,
            None => {
                // Unobservable from what is known so far (a line seen from one place), or not
                // positive definite by round-off: information-form elimination squares the
                // condition number, and a long IMU chain under a tight first-state prior has
                // a wide one (GTSAM's iSAM2 needs QR on such graphs). The smallest damping
                // that factorises keeps the step finite; it acts on this group only.
                let scale = hgg.diagonal().amax().max(1.0);
                let mut damped = None;
                for eps in [1e-12, 1e-9, 1e-6, 1e-3] {
                    damped = (hgg.clone() + DMatrix::identity(dg, dg) * (eps * scale)).cholesky();
                    if damped.is_some() {
                        tracing::debug!(group = g, damping = eps * scale, "incremental: damped a group");
                        break;
                    }
                }
                match damped {
                    Some(c) => c,
                    None => {
                        // Indefinite: seen on a 20-minute IMU run (eigenvalues -1e6 to 2e8)
                        // only after its estimate had diverged (velocities of 1e5 m/s: the
                        // relinearisation backlog, see `max_relinearized_per_update`); a
                        // square-root (QR) elimination removed these warnings there but not
                        // the divergence, at 2-4x the cost. Mirror the negative eigenvalues
                        // (a modified Cholesky) so that the run goes on; the final batch
                        // solve corrects what this step gets wrong.
                        let eig = hgg.clone().symmetric_eigen();
                        let floor = 1e-9 * eig.eigenvalues.amax().max(1.0);
                        tracing::warn!(
                            group = g,
                            min_eigenvalue = eig.eigenvalues.min(),
                            max_eigenvalue = eig.eigenvalues.max(),
                            "incremental: a group's information is indefinite; its negative directions mirrored"
                        );
                        let fixed = eig.eigenvalues.map(|v| v.abs().max(floor));
                        let repaired =
                            &eig.eigenvectors * DMatrix::from_diagonal(&fixed) * eig.eigenvectors.transpose();
                        repaired.cholesky().ok_or_else(|| {
                            Error::LinearSolve(format!("group {g} is singular in the incremental elimination"))
                        })?
                    }
                }
            }
        };
        let l = chol.l();
        // S = L^-1 hgs and d = -L^-1 gg in place; the marginal is hss - S'S (lower triangle by
        // rank-one updates with the rows of S, contiguous in S', then mirrored) and gs + S'd.
        let mut s = hgs;
        if !solve_lower_in_place(&l, s.as_mut_slice()) || !solve_lower_in_place(&l, gg.as_mut_slice()) {
            return Err(Error::LinearSolve(format!("group {g}: triangular solve")));
        }
        let d = -gg;
        let st = s.transpose();
        let h = hss.as_mut_slice();
        for k in 0..dg {
            let row = st.column(k);
            let row = row.as_slice();
            for c in 0..ds {
                let a = row[c];
                if a != 0.0 {
                    for (x, v) in h[c * ds + c..(c + 1) * ds].iter_mut().zip(&row[c..]) {
                        *x -= a * v;
                    }
                }
            }
        }
        for c in 0..ds {
            for r in c + 1..ds {
                h[r * ds + c] = h[c * ds + r];
            }
        }
        gs.gemv(1.0, &st, &d, 1.0);
        let marginal = Arc::new(Hessian {
            h: hss,
            g: gs,
            keys: sep.clone(),
        });
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
        top.sort_by_key(|g| std::cmp::Reverse(self.position[*g]));
        let mut solved = Vec::new();
        for &g in &top {
            self.solve_group(g)?;
            solved.push(g);
        }
        let mut stack: Vec<usize> = orphans.iter().rev().copied().collect();
        while let Some(c) = stack.pop() {
            let Some(cond) = &self.cond[c] else { continue };
            if !cond.sep.iter().any(|k| self.changed[*k]) {
                continue;
            }
            self.solve_group(c)?;
            solved.push(c);
            stack.extend(self.children[c].iter().rev());
        }
        report.solved += solved.len();
        self.publish(&solved, values)
    }

    /// Writes the estimates of the groups `solved` (whose steps were just recomputed) to
    /// `values`, clears their `changed` marks and notes what needs relinearising.
    fn publish(&mut self, solved: &[usize], values: &mut Values) -> Result<()> {
        for &g in solved {
            for i in 0..self.groups[g].len() {
                let j = self.groups[g][i];
                self.changed[j] = false;
                values.set(VarId(j), self.theta.get(VarId(j))?.retract(self.delta[j].as_view()))?;
                if self.needs_relinearisation(j)? {
                    self.over_threshold.insert(j);
                } else {
                    self.over_threshold.remove(&j);
                }
            }
        }
        Ok(())
    }

    /// Back-substitutes every group, however little its separator moved, and writes every
    /// estimate to `values`: the updates' back-substitution stops where the steps change by
    /// less than [`IncrementalParams::wildfire_threshold`], and such small changes add up over
    /// many updates (GTSAM's `calculateBestEstimate`). One pass over the whole graph.
    ///
    /// # Errors
    /// Values that do not belong to this smoother.
    pub fn refresh(&mut self, values: &mut Values) -> Result<()> {
        let mut order: Vec<usize> = (0..self.groups.len()).filter(|g| self.cond[*g].is_some()).collect();
        order.sort_unstable_by_key(|g| std::cmp::Reverse(self.position[*g]));
        for &g in &order {
            self.solve_group(g)?;
        }
        self.publish(&order, values)
    }

    /// Adds `g` and its ancestors that are not in `affected` yet to it (`self.local` maps
    /// the groups of `affected` to their index there).
    fn add_with_ancestors(&mut self, g: usize, affected: &mut Vec<usize>) {
        let mut g = Some(g);
        while let Some(j) = g {
            if self.local[j] != usize::MAX {
                break;
            }
            self.local[j] = affected.len();
            affected.push(j);
            g = self.parent[j];
        }
    }

    /// Relinearises the variables furthest past their thresholds first, while what they add
    /// to the re-eliminated part (the groups of their factors, and those groups' ancestors)
    /// keeps it within [`IncrementalParams::relinearize_budget_groups`], and at most
    /// [`IncrementalParams::max_relinearized_per_update`] of them; always at least one, so
    /// that the waiting ones are worked off. Their groups join `affected`. Returns how many.
    fn relinearise(&mut self, graph: &FactorGraph, affected: &mut Vec<usize>) -> Result<usize> {
        if self.over_threshold.is_empty() {
            return Ok(0);
        }
        let p = self.params;
        let cap = if p.max_relinearized_per_update == 0 {
            usize::MAX
        } else {
            p.max_relinearized_per_update
        };
        let budget = if p.relinearize_budget_groups == 0 {
            usize::MAX
        } else {
            p.relinearize_budget_groups
        };
        let mut by_excess: Vec<(f64, usize)> = self
            .over_threshold
            .iter()
            .map(|j| self.excess(*j).map(|e| (e, *j)))
            .collect::<Result<_>>()?;
        by_excess.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut chosen = Vec::new();
        for &(_, j) in &by_excess {
            if chosen.len() >= cap || (!chosen.is_empty() && affected.len() >= budget) {
                break;
            }
            let before = affected.len();
            for i in 0..self.factors_of[j].len() {
                for k in graph.factors()[self.factors_of[j][i]].keys() {
                    self.add_with_ancestors(self.group_of[k.0], affected);
                }
            }
            if affected.len() <= budget || chosen.is_empty() {
                chosen.push(j);
            } else {
                for g in affected.drain(before..) {
                    self.local[g] = usize::MAX;
                }
            }
        }
        for &j in &chosen {
            self.over_threshold.remove(&j);
            let moved = self.theta.get(VarId(j))?.retract(self.delta[j].as_view());
            self.theta.set(VarId(j), moved)?;
            self.delta[j].fill(0.0);
        }
        Ok(chosen.len())
    }

    /// True when `j`'s step from its linearisation point is past its kind's threshold.
    fn needs_relinearisation(&self, j: usize) -> Result<bool> {
        Ok(self.excess(j)? > 1.0)
    }

    /// The largest component of `j`'s step over its kind's threshold.
    fn excess(&self, j: usize) -> Result<f64> {
        let p = &self.params;
        let dx = &self.delta[j];
        let over = |range: std::ops::Range<usize>, limit: f64| dx.rows(range.start, range.len()).amax() / limit;
        Ok(match self.theta.get(VarId(j))? {
            Variable::Pose(_) => over(0..3, p.relinearize_rotation_rad).max(over(3..6, p.relinearize_translation_m)),
            Variable::Velocity(_) => over(0..3, p.relinearize_velocity_mps),
            Variable::Bias(_) => over(0..6, p.relinearize_bias),
            Variable::Line(_) => over(0..1, p.relinearize_translation_m).max(over(1..2, p.relinearize_rotation_rad)),
        })
    }

    /// `dx` of the group `g` from its conditional; marks its variables that moved by more
    /// than the wildfire threshold.
    fn solve_group(&mut self, g: usize) -> Result<()> {
        let cond = self.cond[g].as_ref().ok_or(Error::UnknownVariable(g))?;
        let dg = cond.d.len();
        let mut x = cond.d.clone();
        let mut col = 0;
        for k in &cond.sep {
            for &v in self.delta[*k].iter() {
                if v != 0.0 {
                    let s = &cond.s.as_slice()[col * dg..(col + 1) * dg];
                    for (xi, si) in x.iter_mut().zip(s) {
                        *xi -= si * v;
                    }
                }
                col += 1;
            }
        }
        // R upper triangular (column-major): back-substitution in place.
        let r = cond.r.as_slice();
        for i in (0..dg).rev() {
            let mut acc = x[i];
            for c in i + 1..dg {
                acc -= r[c * dg + i] * x[c];
            }
            let diag = r[i * dg + i];
            if diag == 0.0 {
                return Err(Error::LinearSolve(format!("group {g}: singular conditional")));
            }
            x[i] = acc / diag;
        }
        let mut at = 0;
        for &j in &self.groups[g] {
            let dj = self.dims[j];
            let mut moved = false;
            for (o, n) in self.delta[j].iter_mut().zip(x.rows(at, dj).iter()) {
                moved |= (*o - n).abs() > self.params.wildfire_threshold;
                *o = *n;
            }
            self.changed[j] |= moved;
            at += dj;
        }
        Ok(())
    }

    /// Ends a run: a full back-substitution, then Levenberg-Marquardt on the whole graph
    /// from that estimate.
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

/// `dst[at..] += src[from..]` over a block of `size` (rows, columns); column-major slices.
fn add_block(
    dst: &mut DMatrix<f64>,
    at: (usize, usize),
    src: &DMatrix<f64>,
    from: (usize, usize),
    size: (usize, usize),
) {
    let (dn, sn) = (dst.nrows(), src.nrows());
    let (d, s) = (dst.as_mut_slice(), src.as_slice());
    for c in 0..size.1 {
        let dc = (at.1 + c) * dn + at.0;
        let sc = (from.1 + c) * sn + from.0;
        for (x, v) in d[dc..dc + size.0].iter_mut().zip(&s[sc..sc + size.0]) {
            *x += v;
        }
    }
}

/// Solves `l x = b` in place for every column of `b` (column-major, `l.nrows()` rows each),
/// `l` lower triangular. False on a zero pivot.
fn solve_lower_in_place(l: &DMatrix<f64>, b: &mut [f64]) -> bool {
    let n = l.nrows();
    let ls = l.as_slice();
    if n == 0 {
        return true;
    }
    for col in b.chunks_exact_mut(n) {
        for i in 0..n {
            let pivot = ls[i * n + i];
            if pivot == 0.0 {
                return false;
            }
            let xi = col[i] / pivot;
            col[i] = xi;
            for (x, v) in col[i + 1..].iter_mut().zip(&ls[i * n + i + 1..(i + 1) * n]) {
                *x -= v * xi;
            }
        }
    }
    true
}

/// Re-dissect the newest states every this many states (see [`IncrementalSmoother::update`]).
const REBALANCE_MIN: usize = 64;
/// ... at most this many at once: a re-dissection of 256 states was the longest update on the
/// peer's problems (11-17 ms at N = 2000), one of 128 takes about half that.
const REBALANCE_MAX: usize = 128;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenPose, PosePrior};
    use crate::lie::Pose3;
    use crate::linear::{Factorization, HessianStructure, linearize};
    use crate::noise::NoiseModel;
    use nalgebra::Vector6;

    /// A pose chain driven one state per update (a step of 1 m and 0.05 rad yaw, measured
    /// with a small bias so that the loop closures pull), with a loop closure from every
    /// 25th state to the one `lap` before; initial values from dead reckoning.
    fn drive(
        smoother: &mut IncrementalSmoother,
        states: usize,
        lap: usize,
        mut each: impl FnMut(usize, IncrementalReport),
    ) -> (FactorGraph, Values, Vec<VarId>) {
        let mut graph = FactorGraph::new();
        let mut values = Values::new();
        let noise = NoiseModel::diagonal(&[0.01, 0.01, 0.01, 0.05, 0.05, 0.05]).expect("noise");
        let truth_step = Pose3::exp(&Vector6::new(
            0.0,
            0.0,
            2.0 * std::f64::consts::PI / lap as f64,
            1.0,
            0.0,
            0.0,
        ));
        let measured = Pose3::exp(&Vector6::new(0.0, 0.0, 0.003, 0.0, 0.02, 0.0)).compose(&truth_step);
        let mut ids = Vec::new();
        for i in 0..states {
            let guess = match ids.last() {
                Some(prev) => values.pose(*prev).expect("pose").compose(&measured),
                None => Pose3::identity(),
            };
            let id = values.push(Variable::Pose(guess));
            if let Some(prev) = ids.last() {
                graph.add(BetweenPose::new(*prev, id, measured, noise.clone()).expect("factor"));
            } else {
                graph.add(PosePrior::new(id, Pose3::identity(), noise.clone()).expect("factor"));
            }
            if i >= lap && i % 25 == 0 {
                // the same place a lap ago
                graph.add(BetweenPose::new(ids[i - lap], id, Pose3::identity(), noise.clone()).expect("factor"));
            }
            ids.push(id);
            let report = smoother.update(&graph, &mut values, &[id]).expect("update");
            each(i, report);
        }
        (graph, values, ids)
    }

    fn batch(graph: &FactorGraph, values: &Values) -> Values {
        let mut v = values.clone();
        let all: Vec<usize> = (0..graph.len()).collect();
        let ordering = Ordering::all(&v);
        levenberg_marquardt(graph, &all, &mut v, &ordering, &LmParams::default(), &mut None).expect("lm");
        v
    }

    #[test]
    fn reaches_the_batch_optimum_and_its_marginal_covariance() {
        let mut smoother = IncrementalSmoother::new(IncrementalParams::default());
        let (graph, mut values, ids) = drive(&mut smoother, 300, 100, |_, _| {});
        smoother.refresh(&mut values).expect("refresh");
        let optimum = batch(&graph, &values);
        let (online, best) = (graph.error(&values).expect("e"), graph.error(&optimum).expect("e"));
        assert!(online <= best * 1.01, "online error {online}, optimum {best}");
        // The newest pose's covariance is its marginal: the block of the inverse Hessian at
        // the smoother's linearisation point.
        let last = *ids.last().expect("states");
        let all: Vec<usize> = (0..graph.len()).collect();
        let ordering = Ordering::all(&smoother.theta);
        let st = HessianStructure::new(&graph, &all, &smoother.theta, &ordering).expect("structure");
        let ne = linearize(&graph, &all, &smoother.theta, &st).expect("linearize");
        let f = Factorization::new(&st, &ne.hessian, 0.0).expect("llt");
        let dense = crate::linear::marginal_covariance(&f, st.ordering(), last).expect("cov");
        let ours = smoother.newest_covariance().expect("covariance");
        assert!((ours - &dense).norm() < 1e-9 * dense.norm(), "{ours} vs {dense}");
        // and grows along the chain: the last pose is far less certain than the prior's 5 cm
        assert!(ours[(3, 3)].sqrt() > 0.1, "{ours}");
    }

    #[test]
    fn relinearisation_stays_within_its_budget_of_groups_and_still_reaches_the_optimum() {
        let budget = 12;
        let mut smoother = IncrementalSmoother::new(IncrementalParams {
            relinearize_budget_groups: budget,
            ..IncrementalParams::default()
        });
        let (mut several, mut single) = (0, 0);
        let (graph, mut values, _) = drive(&mut smoother, 300, 100, |i, r| {
            // A second variable joins only while the part stays within the budget; the
            // first one always does, so that the waiting ones are worked off.
            if r.relinearized >= 2 {
                several += 1;
                assert!(r.eliminated <= budget, "update {i}: {r:?}");
            } else if r.relinearized == 1 && r.eliminated > budget {
                single += 1;
            }
        });
        assert!(
            several > 10 && single > 0,
            "{several} updates with several, {single} with one past the budget"
        );
        smoother.refresh(&mut values).expect("refresh");
        let optimum = batch(&graph, &values);
        let (online, best) = (graph.error(&values).expect("e"), graph.error(&optimum).expect("e"));
        assert!(online <= best * 1.01, "online error {online}, optimum {best}");
    }

    #[test]
    fn an_update_re_eliminates_what_it_touches_not_the_run() {
        // Odometry steps touch the newest states; a loop closure deep into the past a
        // logarithmic path of the tree, not the states since.
        let mut eliminated = Vec::new();
        let mut smoother = IncrementalSmoother::new(IncrementalParams {
            relinearize_rotation_rad: 10.0,
            relinearize_translation_m: 10.0,
            ..IncrementalParams::default()
        });
        let (mut graph, mut values, ids) = drive(&mut smoother, 2000, 100_000, |_, r| eliminated.push(r.eliminated));
        for (i, e) in eliminated.iter().enumerate().skip(100) {
            let u = i + 1;
            // the newest two states, and every 64 states the re-dissection of the newest ones
            let most = if u.is_multiple_of(REBALANCE_MIN) {
                (1usize << u.trailing_zeros()).min(REBALANCE_MAX) + 2
            } else {
                2
            };
            assert!(*e <= most, "update {i}: {e} groups re-eliminated");
        }
        let noise = NoiseModel::isotropic(6, 0.1).expect("noise");
        let rel = values
            .pose(ids[100])
            .expect("pose")
            .between(values.pose(ids[101]).expect("pose"));
        graph.add(BetweenPose::new(ids[100], ids[101], rel, noise.clone()).expect("factor"));
        let deep = smoother.update(&graph, &mut values, &[]).expect("update");
        // Its path to the root crosses every re-dissected block of at most 128 states above
        // it (each some 30 groups deep: a few separators and a minimum-degree leaf of up to
        // 24) and the newest, not yet re-dissected states: an eighth of the run at most,
        // where an elimination in time order would redo all 1900 states after it.
        assert!(deep.eliminated < 250, "{deep:?}");
        let rel = values
            .pose(ids[10])
            .expect("pose")
            .between(values.pose(ids[1990]).expect("pose"));
        graph.add(BetweenPose::new(ids[10], ids[1990], rel, noise).expect("factor"));
        let closure = smoother.update(&graph, &mut values, &[]).expect("update");
        // The same for a loop closure from the newest states back to the start.
        assert!(closure.eliminated < 250, "{closure:?}");
    }

    #[test]
    fn the_same_input_gives_the_same_estimate() {
        let run = || {
            let mut smoother = IncrementalSmoother::new(IncrementalParams::default());
            let (_, mut values, _) = drive(&mut smoother, 200, 60, |_, _| {});
            smoother.refresh(&mut values).expect("refresh");
            values
        };
        let (a, b) = (run(), run());
        assert_eq!(a.as_slice(), b.as_slice());
    }

    #[test]
    fn nested_dissection_orders_every_node_once() {
        // a ring of 500 with chords, and a few isolated nodes
        let n = 510;
        let mut adj = vec![Vec::new(); n];
        for i in 0..500 {
            for j in [(i + 1) % 500, (i + 37) % 500] {
                adj[i].push(j);
                adj[j].push(i);
            }
        }
        let dims = vec![6; n];
        let mut order = Vec::new();
        nested_dissection(&adj, &dims, (0..n).collect(), &mut vec![usize::MAX; n], &mut order);
        let mut seen = order.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..n).collect::<Vec<_>>());
    }
}
