//! The smoothers behind one interface ([`Smoother`]): the fixed-lag smoother of this module
//! (the default) and the [`IncrementalSmoother`] (see [`crate::incremental`]; opt-in until
//! its divergence on long IMU runs is fixed).
//!
//! # The fixed-lag smoother
//!
//! - **On the critical path**, each update solves only a window of the newest
//!   [`SmootherParams::lag_states`] states (a few Levenberg-Marquardt iterations on faer sparse
//!   Cholesky, reusing the symbolic factorisation while the window's shape stays the same).
//!   Older states are held at their current estimate: factors that reach them (the IMU and
//!   odometry factor into the window, loop closures) condition the window on them. Work per
//!   update is bounded by the window, not by the length of the run.
//! - **Optionally** ([`SmootherParams::marginalise`]), a state leaving the window is
//!   marginalised instead (see [`crate::marginal`]): its factors and the prior on it become a
//!   prior on the states it was joined to, so the window is not held against the states behind
//!   it and its covariance is the marginal one. A factor that reaches a state already
//!   marginalised (a loop closure) still holds that state at its estimate.
//! - **Off the critical path**, a factor that reaches behind the window (a loop closure) starts
//!   a full batch solve of the whole graph on a background thread from a snapshot (factors are
//!   shared, so the snapshot costs one copy of the values). When it finishes, the next update
//!   merges it: every variable of the snapshot takes the full solution and the states added
//!   since are moved by the rigid correction of the snapshot's newest pose. A loop closure that
//!   arrives while a solve runs is picked up by the next solve.
//! - **Bounded re-solves**: with [`SmootherParams::resolve_window_states`] a re-solve solves
//!   only the newest states and holds the older ones, as the window does; with
//!   [`SmootherParams::resolve_spacing_growth`] a wide one (the whole graph, or
//!   [`SmootherParams::resolve_wide_states`]) comes only once the graph has grown by that
//!   fraction since the last, so the wide ones cost a multiple of the last one in all.
//!
//! Its limits, which the incremental smoother does not have: a re-solve of the whole graph
//! costs the whole graph (0.1-0.4 s at N = 2000), so fed faster than they finish (a recording
//! replayed as fast as it goes) the estimate falls behind the optimum; in line
//! (`background: false`) and unbounded, the run's cost grows with the square of its length;
//! bounded, the states behind a re-solve's window are held as they were; and unless
//! marginalising, states leaving the window are conditioned on, so the window's covariance is
//! the covariance given the older states, smaller than the true marginal.

use std::collections::BTreeSet;
use std::sync::{Arc, mpsc};
use std::time::Instant;

use nalgebra::DMatrix;

use crate::batch::{LmParams, LmReport, levenberg_marquardt, levenberg_marquardt_keep_hessian};
use crate::factor::Factor;
use crate::graph::FactorGraph;
use crate::incremental::{IncrementalParams, IncrementalReport, IncrementalSmoother};
use crate::linear::{Factorization, HessianStructure, Ordering, marginal_covariance};
use crate::marginal::{MarginalPrior, marginalise, normal_equations};
use crate::values::{Values, VarId, Variable};
use crate::{Error, Result};

/// Which smoother runs the updates (the `estimate` stage's `smoother` parameter:
/// `incremental` or `fixed_lag`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum SmootherMethod {
    /// [`IncrementalSmoother`]: the whole graph, partial re-elimination. Not yet the default:
    /// on a 20.9-minute simulated IMU run its Gauss-Newton steps diverge after about 8.5
    /// minutes (indefinite group information, then a failed run); see the crate's known gaps.
    Incremental,
    /// [`FixedLagSmoother`]: a window of the newest states plus full re-solves (the default).
    #[default]
    FixedLag,
}

/// Smoother settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SmootherParams {
    /// Which smoother.
    pub method: SmootherMethod,
    /// Settings of the incremental smoother.
    pub incremental: IncrementalParams,
    /// States solved per update (the window).
    pub lag_states: usize,
    /// Levenberg-Marquardt iterations per update at most.
    pub iterations_per_update: usize,
    /// Full re-solves on a background thread (`false`: in the update that needs one; for
    /// deterministic tests and offline runs).
    pub background: bool,
    /// Settings of the background full re-solves. They start from the current estimate and
    /// need not converge: the next loop closure starts another one from where this one ended
    /// (default: at most 3 iterations). [`FixedLagSmoother::finish`] solves to convergence.
    pub full_solve: LmParams,
    /// Compute the newest state's covariance after each update.
    pub newest_covariance: bool,
    /// Marginalise the states that leave the window into a prior on the ones they leave
    /// behind (see [`crate::marginal`]), instead of holding them at their estimate: the
    /// window's covariance is then the marginal one. Factors that join the window to a
    /// marginalised state later (loop closures) still hold that state at its estimate.
    pub marginalise: bool,
    /// States added between the starts of two full re-solves at least (default 1: a loop
    /// closure starts one at the next update). Closures that arrive in between are solved
    /// with the window against the states behind it, and the next re-solve takes them all.
    pub resolve_spacing_states: usize,
    /// Wide re-solves (of [`SmootherParams::resolve_wide_states`], by default the whole
    /// graph) at least this fraction of the states there were at the start of the last one
    /// apart (default 0: the spacing alone). A re-solve of the whole graph costs more than its
    /// length, so at a fixed spacing the run's cost grows faster than the square of its
    /// length; spaced in proportion to the graph, their total is a multiple of the last one's
    /// cost (the spacing of a growing vector's reallocations). With
    /// [`SmootherParams::resolve_window_states`] the re-solves in between solve the window.
    pub resolve_spacing_growth: f64,
    /// States a wide re-solve solves, the newest ones (default 0: the whole graph); more than
    /// [`SmootherParams::resolve_window_states`]. On a graph that revisits the same ground lap
    /// after lap the whole graph's factorisation grows faster than its length (13 s at 37,000
    /// states of a 62-minute run), so without this bound the wide re-solves still dominate an
    /// hour's run.
    pub resolve_wide_states: usize,
    /// States a re-solve solves, the newest ones (default 0: the whole graph). Older states
    /// are held at their estimate, as the window holds the states behind it, so a re-solve
    /// costs this many states however long the run. The end-of-run solve
    /// ([`FixedLagSmoother::finish`]) solves the whole graph whatever this is.
    pub resolve_window_states: usize,
}

impl Default for SmootherParams {
    fn default() -> Self {
        Self {
            method: SmootherMethod::default(),
            incremental: IncrementalParams::default(),
            lag_states: 30,
            iterations_per_update: 3,
            background: true,
            full_solve: LmParams {
                max_iterations: 3,
                ..LmParams::default()
            },
            newest_covariance: true,
            marginalise: false,
            resolve_spacing_states: 1,
            resolve_spacing_growth: 0.0,
            resolve_wide_states: 0,
            resolve_window_states: 0,
        }
    }
}

/// What a finished full re-solve did.
#[derive(Debug, Clone, PartialEq)]
pub struct FullSolveReport {
    /// States in the snapshot.
    pub states: usize,
    /// The optimiser's report.
    pub lm: LmReport,
    /// From snapshot to merge, seconds (includes waiting for the next update).
    pub latency_s: f64,
}

/// Where a fixed-lag smoother's time went: per kind of solve, how many and their wall time,
/// seconds.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SolveTimes {
    /// The window's solves, one per update.
    pub window: (u64, f64),
    /// Their accepted iterations and linear solves.
    pub window_iterations: (u64, u64),
    /// Re-solves of [`SmootherParams::resolve_window_states`].
    pub narrow: (u64, f64),
    /// Wide re-solves (of [`SmootherParams::resolve_wide_states`], or the whole graph).
    pub wide: (u64, f64),
}

/// What one update did.
#[derive(Debug, Clone, PartialEq)]
pub struct UpdateReport {
    /// The window solve (fixed-lag smoother).
    pub window: Option<LmReport>,
    /// The partial re-elimination (incremental smoother).
    pub incremental: Option<IncrementalReport>,
    /// True when this update started a full re-solve.
    pub started_full_solve: bool,
    /// A full re-solve merged in this update.
    pub merged: Option<FullSolveReport>,
}

struct Running {
    rx: mpsc::Receiver<Result<(Values, LmReport)>>,
    started: Instant,
    states: usize,
    vars: usize,
    newest_pose: Option<VarId>,
    wide: bool,
}

impl std::fmt::Debug for Running {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Running")
            .field("states", &self.states)
            .field("vars", &self.vars)
            .finish_non_exhaustive()
    }
}

/// Fixed-lag smoother with background full re-solves (see the module docs).
#[derive(Debug)]
pub struct FixedLagSmoother {
    params: SmootherParams,
    states: Vec<Vec<VarId>>,
    state_of: Vec<Option<usize>>,
    factors_of: Vec<Vec<usize>>,
    known_factors: usize,
    full_solve_wanted: bool,
    structure: Option<HessianStructure>,
    running: Option<Running>,
    newest_cov: Option<DMatrix<f64>>,
    /// States `0..marginalised` are marginalised (with [`SmootherParams::marginalise`]).
    marginalised: usize,
    /// Per factor: folded into a prior, no longer solved with the window.
    consumed: Vec<bool>,
    /// The priors of the marginalised states.
    priors: Vec<Arc<MarginalPrior>>,
    /// States that could not be marginalised (held at their estimate instead).
    held_instead: usize,
    /// States at the start of the last full re-solve.
    resolved_at: usize,
    /// States at the start of the last wide re-solve.
    wide_resolved_at: usize,
    times: SolveTimes,
}

impl FixedLagSmoother {
    /// An empty smoother.
    #[must_use]
    pub fn new(params: SmootherParams) -> Self {
        Self {
            params,
            states: Vec::new(),
            state_of: Vec::new(),
            factors_of: Vec::new(),
            known_factors: 0,
            full_solve_wanted: false,
            structure: None,
            running: None,
            newest_cov: None,
            marginalised: 0,
            consumed: Vec::new(),
            priors: Vec::new(),
            held_instead: 0,
            resolved_at: 0,
            wide_resolved_at: 0,
            times: SolveTimes::default(),
        }
    }

    /// The settings.
    #[must_use]
    pub fn params(&self) -> &SmootherParams {
        &self.params
    }

    /// Number of states so far.
    #[must_use]
    pub fn state_count(&self) -> usize {
        self.states.len()
    }

    /// Covariance of the newest state's first variable (its pose) after the last update.
    #[must_use]
    pub fn newest_covariance(&self) -> Option<&DMatrix<f64>> {
        self.newest_cov.as_ref()
    }

    /// Where the time went so far.
    #[must_use]
    pub fn solve_times(&self) -> SolveTimes {
        self.times
    }

    /// True while a full re-solve runs in the background.
    #[must_use]
    pub fn full_solve_running(&self) -> bool {
        self.running.is_some()
    }

    /// True when a re-solve now would be a wide one: its spacing after the last wide one has
    /// passed, grown with the graph.
    fn wide_resolve_due(&self) -> bool {
        // Truncation is intended: a fraction of a state count.
        #[allow(
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss,
            clippy::cast_precision_loss
        )]
        let grown = (self.params.resolve_spacing_growth * self.wide_resolved_at as f64) as usize;
        self.states.len() >= self.wide_resolved_at + self.params.resolve_spacing_states.max(grown)
    }

    /// Whether a re-solve may start now, and if so whether it is a wide one.
    fn resolve_due(&self) -> Option<bool> {
        if self.params.resolve_window_states == 0 {
            // Every re-solve is a wide one.
            return self.wide_resolve_due().then_some(true);
        }
        (self.states.len() >= self.resolved_at + self.params.resolve_spacing_states)
            .then(|| self.params.resolve_spacing_growth > 0.0 && self.wide_resolve_due())
    }

    fn window_start(&self) -> usize {
        self.states.len().saturating_sub(self.params.lag_states.max(1))
    }

    /// Whether a factor already on `landmark` (a variable of no state) reaches a state behind
    /// `start`.
    fn landmark_seen_behind(&self, graph: &FactorGraph, landmark: VarId, start: usize) -> bool {
        self.factors_of[landmark.0].iter().any(|&fi| {
            graph.factors()[fi]
                .keys()
                .iter()
                .any(|k| self.state_of[k.0].is_some_and(|s| s < start))
        })
    }

    fn register(&mut self, graph: &FactorGraph, values: &Values, new_state: &[VarId]) -> Result<()> {
        self.state_of.resize(values.len(), None);
        self.factors_of.resize(values.len(), Vec::new());
        if !new_state.is_empty() {
            let s = self.states.len();
            for v in new_state {
                *self.state_of.get_mut(v.0).ok_or(Error::UnknownVariable(v.0))? = Some(s);
            }
            self.states.push(new_state.to_vec());
        }
        let start = self.window_start();
        for fi in self.known_factors..graph.len() {
            for k in graph.factors()[fi].keys() {
                let behind = match self.state_of[k.0] {
                    Some(s) => s < start,
                    // a landmark (a line): seen again, it closes a loop when it was seen
                    // from a state behind the window
                    None => self.landmark_seen_behind(graph, *k, start),
                };
                self.full_solve_wanted |= behind;
                let list = self.factors_of.get_mut(k.0).ok_or(Error::UnknownVariable(k.0))?;
                list.push(fi);
            }
        }
        self.known_factors = graph.len();
        Ok(())
    }

    /// Adds the new state's variables (already in `values`) and every factor added to `graph`
    /// since the last update, then solves the window. Merges a finished background solve first.
    ///
    /// # Errors
    /// A factor that cannot be evaluated, or a failed full solve.
    pub fn update(&mut self, graph: &FactorGraph, values: &mut Values, new_state: &[VarId]) -> Result<UpdateReport> {
        let merged = self.poll(graph, values, false)?;
        self.register(graph, values, new_state)?;
        if self.params.marginalise {
            self.marginalise_old(graph, values)?;
        }
        let t = Instant::now();
        let window = self.solve_window(graph, values)?;
        self.times.window.0 += 1;
        self.times.window.1 += t.elapsed().as_secs_f64();
        self.times.window_iterations.0 += window.iterations as u64;
        self.times.window_iterations.1 += window.linear_solves as u64;
        let mut started = false;
        if self.full_solve_wanted
            && self.running.is_none()
            && let Some(wide) = self.resolve_due()
        {
            self.full_solve_wanted = false;
            self.resolved_at = self.states.len();
            let window = if wide {
                self.wide_resolved_at = self.states.len();
                self.params.resolve_wide_states
            } else {
                self.params.resolve_window_states
            };
            started = true;
            self.start_full_solve(graph, values, window, wide);
        }
        let merged = match merged {
            Some(m) => Some(m),
            None if !self.params.background => self.poll(graph, values, true)?,
            None => None,
        };
        Ok(UpdateReport {
            window: Some(window),
            incremental: None,
            started_full_solve: started,
            merged,
        })
    }

    /// The factors on `vars` not folded into a prior, in graph order.
    fn live_factors(&self, vars: &[VarId]) -> Vec<usize> {
        let mut found: Vec<usize> = vars
            .iter()
            .flat_map(|v| self.factors_of[v.0].iter().copied())
            .filter(|f| !self.consumed.get(*f).copied().unwrap_or(false))
            .collect();
        found.sort_unstable();
        found.dedup();
        found
    }

    /// Marginalises the states that have left the window, oldest first: each one's factors
    /// not yet folded into a prior (and the priors on it) become one prior on the later states
    /// they reach; older states and variables of no state are held at their estimate.
    fn marginalise_old(&mut self, graph: &FactorGraph, values: &Values) -> Result<()> {
        self.consumed.resize(graph.len(), false);
        while self.marginalised < self.window_start() {
            let s = self.marginalised;
            self.marginalised += 1;
            let gone = &self.states[s];
            let taken = self.live_factors(gone);
            let (on_it, others): (Vec<_>, Vec<_>) = self
                .priors
                .drain(..)
                .partition(|p| p.variables().iter().any(|k| gone.contains(k)));
            self.priors = others;
            let later = |k: &VarId| !gone.contains(k) && self.state_of[k.0].is_some_and(|t| t > s);
            let mut kept: Vec<VarId> = taken
                .iter()
                .flat_map(|f| graph.factors()[*f].keys().iter().copied())
                .chain(on_it.iter().flat_map(|p| p.variables().iter().copied()))
                .filter(|k| later(k))
                .collect();
            kept.sort_unstable_by_key(|k| k.0);
            kept.dedup();
            let mut list: Vec<&dyn Factor> = taken.iter().map(|f| graph.factors()[*f].as_ref()).collect();
            list.extend(on_it.iter().map(|p| p.as_ref() as &dyn Factor));
            match marginalise(&list, values, gone, &kept) {
                Ok(prior) => {
                    for f in taken {
                        self.consumed[f] = true;
                    }
                    self.priors.extend(prior.map(Arc::new));
                }
                Err(e) => {
                    // Held at its estimate instead, as without marginalisation.
                    if self.held_instead == 0 {
                        tracing::warn!(
                            state = s,
                            "cannot marginalise a state leaving the window, held instead: {e}"
                        );
                    }
                    self.held_instead += 1;
                    self.priors.extend(on_it);
                }
            }
        }
        Ok(())
    }

    /// Re-centres the priors on `values` after a whole-graph solve moved them, balanced against
    /// the gradient of the window's other factors so that the solve's values stay a stationary
    /// point of the window.
    fn recentre_priors(&mut self, graph: &FactorGraph, values: &Values) -> Result<()> {
        let mut recentred = Vec::with_capacity(self.priors.len());
        for p in &self.priors {
            let on = self.live_factors(p.variables());
            let mut list: Vec<&dyn Factor> = on.iter().map(|f| graph.factors()[*f].as_ref()).collect();
            for q in &self.priors {
                if !Arc::ptr_eq(p, q) && q.variables().iter().any(|k| p.variables().contains(k)) {
                    list.push(q.as_ref());
                }
            }
            let (_, balance) = normal_equations(&list, values, p.variables())?;
            recentred.push(Arc::new(p.recentred(values, &balance)?));
        }
        self.priors = recentred;
        Ok(())
    }

    fn solve_window(&mut self, graph: &FactorGraph, values: &mut Values) -> Result<LmReport> {
        let start = self.window_start();
        let mut free: Vec<VarId> = self.states[start..].iter().flatten().copied().collect();
        let factors = self.live_factors(&free);
        // Variables of no state (map lines) are solved with the window when it observes them.
        let mut globals = BTreeSet::new();
        for &fi in &factors {
            for k in graph.factors()[fi].keys() {
                if self.state_of.get(k.0).copied().flatten().is_none() {
                    globals.insert(*k);
                }
            }
        }
        free.extend(globals);
        let ordering = Ordering::free(values, &free);
        let lm = LmParams {
            max_iterations: self.params.iterations_per_update,
            ..LmParams::default()
        };
        let (report, kept) = if self.priors.is_empty() {
            levenberg_marquardt_keep_hessian(graph, &factors, values, &ordering, &lm, &mut self.structure)?
        } else {
            // The window's factors and the priors, as one small graph (shared factors).
            let mut local = FactorGraph::new();
            for &f in &factors {
                local.add_shared(graph.factors()[f].clone());
            }
            for p in &self.priors {
                local.add_shared(p.clone());
            }
            let all: Vec<usize> = (0..local.len()).collect();
            levenberg_marquardt_keep_hessian(&local, &all, values, &ordering, &lm, &mut self.structure)?
        };
        self.newest_cov = None;
        // From the solver's last linearisation (at most one accepted step from the solution),
        // weakly damped where a direction is free (a line seen from one side only): the
        // solver's own factorisation of it when its damping is no more than that.
        if self.params.newest_covariance
            && let (Some(st), Some(newest)) = (&self.structure, self.states.last().and_then(|s| s.first()))
            && let Ok(f) = Factorization::for_covariance_reusing(st, &kept.equations.hessian, kept.factorization)
        {
            self.newest_cov = Some(marginal_covariance(&f, st.ordering(), *newest)?);
        }
        Ok(report)
    }

    /// The graph a re-solve solves and its free variables: the whole graph (`window` 0), or the
    /// newest `window` states, the variables of no state
    /// that their factors reach (map lines), and every factor on any of them (the older states
    /// those reach held at their estimate).
    fn resolve_problem(&self, graph: &FactorGraph, values: &Values, window: usize) -> (FactorGraph, Ordering) {
        if window == 0 || window >= self.states.len() {
            return (graph.clone(), Ordering::all(values));
        }
        let mut free: Vec<VarId> = self.states[self.states.len() - window..]
            .iter()
            .flatten()
            .copied()
            .collect();
        let of = |vars: &[VarId]| -> BTreeSet<usize> {
            vars.iter().flat_map(|v| self.factors_of[v.0].iter().copied()).collect()
        };
        let mut factors = of(&free);
        let globals: Vec<VarId> = factors
            .iter()
            .flat_map(|&f| graph.factors()[f].keys().iter().copied())
            .filter(|k| self.state_of.get(k.0).copied().flatten().is_none())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        factors.extend(of(&globals));
        free.extend(globals);
        let mut local = FactorGraph::new();
        for f in factors {
            local.add_shared(graph.factors()[f].clone());
        }
        (local, Ordering::free(values, &free))
    }

    fn start_full_solve(&mut self, graph: &FactorGraph, values: &Values, window: usize, wide: bool) {
        let (snapshot_graph, ordering) = self.resolve_problem(graph, values, window);
        let mut snapshot_values = values.clone();
        let params = self.params.full_solve;
        let (tx, rx) = mpsc::sync_channel(1);
        let job = move || {
            let all: Vec<usize> = (0..snapshot_graph.len()).collect();
            let r = levenberg_marquardt(
                &snapshot_graph,
                &all,
                &mut snapshot_values,
                &ordering,
                &params,
                &mut None,
            );
            // The receiver may be gone (smoother dropped); nothing to do then.
            let _ = tx.send(r.map(|rep| (snapshot_values, rep)));
        };
        self.running = Some(Running {
            rx,
            started: Instant::now(),
            states: self.states.len(),
            vars: values.len(),
            newest_pose: self.states.last().and_then(|s| s.first()).copied(),
            wide,
        });
        if self.params.background {
            let spawned = std::thread::Builder::new()
                .name("estimate-full-solve".into())
                .spawn(job);
            if let Err(e) = spawned {
                tracing::warn!("cannot start the background solve ({e}); skipping it");
                self.running = None;
            }
        } else {
            job();
        }
    }

    /// Merges a finished full solve; with `wait`, waits for a running one.
    fn poll(&mut self, graph: &FactorGraph, values: &mut Values, wait: bool) -> Result<Option<FullSolveReport>> {
        let Some(run) = &self.running else { return Ok(None) };
        let got = if wait {
            run.rx
                .recv()
                .map_err(|_| Error::LinearSolve("background solve thread ended without a result".into()))
        } else {
            match run.rx.try_recv() {
                Ok(r) => Ok(r),
                Err(mpsc::TryRecvError::Empty) => return Ok(None),
                Err(mpsc::TryRecvError::Disconnected) => Err(Error::LinearSolve(
                    "background solve thread ended without a result".into(),
                )),
            }
        };
        let Some(run) = self.running.take() else {
            return Ok(None);
        };
        let (solved, lm) = got??;
        let kind = if run.wide {
            &mut self.times.wide
        } else {
            &mut self.times.narrow
        };
        kind.0 += 1;
        kind.1 += lm.seconds;
        // Rigid correction of the snapshot's newest pose, applied to the states added since.
        let correction = match run.newest_pose {
            Some(id) => match (values.get(id)?, solved.get(id)?) {
                (Variable::Pose(now), Variable::Pose(full)) => Some(full.compose(&now.inverse())),
                _ => None,
            },
            None => None,
        };
        for (k, v) in solved.as_slice().iter().enumerate().take(run.vars) {
            values.set(VarId(k), *v)?;
        }
        if let Some(c) = correction {
            for s in &self.states[run.states..] {
                for id in s {
                    let moved = match values.get(*id)? {
                        Variable::Pose(p) => Variable::Pose(c.compose(p)),
                        Variable::Velocity(v) => Variable::Velocity(c.rot * v),
                        other => *other,
                    };
                    values.set(*id, moved)?;
                }
            }
        }
        if !self.priors.is_empty() {
            self.recentre_priors(graph, values)?;
        }
        Ok(Some(FullSolveReport {
            states: run.states,
            lm,
            latency_s: run.started.elapsed().as_secs_f64(),
        }))
    }

    /// Ends a run: waits for a running background solve, merges it, and solves the whole graph
    /// once more (warm-started), returning that solve's report.
    ///
    /// # Errors
    /// A factor that cannot be evaluated.
    pub fn finish(&mut self, graph: &FactorGraph, values: &mut Values) -> Result<LmReport> {
        self.poll(graph, values, true)?;
        if self.held_instead > 0 {
            tracing::warn!(
                states = self.held_instead,
                "states held at their estimate because they could not be marginalised"
            );
        }
        let all: Vec<usize> = (0..graph.len()).collect();
        let ordering = Ordering::all(values);
        levenberg_marquardt(graph, &all, values, &ordering, &LmParams::default(), &mut None)
    }
}

/// The smoother [`SmootherParams::method`] picks, behind one interface.
// One per estimator: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Smoother {
    /// The whole graph, partial re-elimination.
    Incremental(IncrementalSmoother),
    /// A window plus full re-solves.
    FixedLag(FixedLagSmoother),
}

impl Smoother {
    /// An empty smoother of the method `params` names.
    #[must_use]
    pub fn new(params: SmootherParams) -> Self {
        match params.method {
            SmootherMethod::Incremental => Self::Incremental(IncrementalSmoother::new(params.incremental)),
            SmootherMethod::FixedLag => Self::FixedLag(FixedLagSmoother::new(params)),
        }
    }

    /// Covariance of the newest state's pose after the last update: the marginal one for the
    /// incremental smoother; for the fixed-lag one, the one given the states behind the window,
    /// or with [`SmootherParams::marginalise`] the marginal one (but for loop closures to
    /// marginalised states).
    #[must_use]
    pub fn newest_covariance(&self) -> Option<&DMatrix<f64>> {
        match self {
            Self::Incremental(s) => s.newest_covariance(),
            Self::FixedLag(s) => s.newest_covariance(),
        }
    }

    /// One update (see [`IncrementalSmoother::update`] and [`FixedLagSmoother::update`]).
    ///
    /// # Errors
    /// As theirs.
    pub fn update(&mut self, graph: &FactorGraph, values: &mut Values, new_state: &[VarId]) -> Result<UpdateReport> {
        match self {
            Self::Incremental(s) => Ok(UpdateReport {
                window: None,
                incremental: Some(s.update(graph, values, new_state)?),
                started_full_solve: false,
                merged: None,
            }),
            Self::FixedLag(s) => s.update(graph, values, new_state),
        }
    }

    /// Writes the best estimate of every variable to `values` (the incremental smoother's
    /// [`IncrementalSmoother::refresh`]; the fixed-lag smoother's are always written).
    ///
    /// # Errors
    /// Values that do not belong to this smoother.
    pub fn refresh(&mut self, values: &mut Values) -> Result<()> {
        match self {
            Self::Incremental(s) => s.refresh(values),
            Self::FixedLag(_) => Ok(()),
        }
    }

    /// Where the fixed-lag smoother's time went (`None` for the incremental one).
    #[must_use]
    pub fn solve_times(&self) -> Option<SolveTimes> {
        match self {
            Self::Incremental(_) => None,
            Self::FixedLag(s) => Some(s.solve_times()),
        }
    }

    /// Ends a run with a solve of the whole graph to convergence.
    ///
    /// # Errors
    /// A factor that cannot be evaluated.
    pub fn finish(&mut self, graph: &FactorGraph, values: &mut Values) -> Result<LmReport> {
        match self {
            Self::Incremental(s) => s.finish(graph, values),
            Self::FixedLag(s) => s.finish(graph, values),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BiasRandomWalk, VectorPrior};
    use crate::noise::NoiseModel;
    use crate::values::ImuBias;
    use nalgebra::Vector6;

    /// A linear chain: one IMU bias per state, a random walk between consecutive ones and a
    /// noisy measurement of every third. Returns the newest state's covariance after each
    /// update, and the batch marginal covariance of the same graph.
    fn linear_chain(marginalise: bool, lag_states: usize) -> Vec<(DMatrix<f64>, DMatrix<f64>, f64)> {
        let params = SmootherParams {
            method: SmootherMethod::FixedLag,
            lag_states,
            background: false,
            marginalise,
            ..SmootherParams::default()
        };
        let mut smoother = FixedLagSmoother::new(params);
        let mut graph = FactorGraph::new();
        let mut values = Values::new();
        let walk = NoiseModel::diagonal(&[0.05, 0.05, 0.05, 0.01, 0.01, 0.01]).expect("noise");
        let seen = NoiseModel::diagonal(&[0.3, 0.2, 0.3, 0.05, 0.05, 0.1]).expect("noise");
        let mut out = Vec::new();
        let mut ids: Vec<VarId> = Vec::new();
        for k in 0..40 {
            let id = values.push(Variable::Bias(ImuBias::default()));
            if k == 0 {
                let first = NoiseModel::isotropic(6, 0.1).expect("noise");
                graph.add(VectorPrior::bias(id, ImuBias::default(), first).expect("f"));
            } else {
                graph.add(BiasRandomWalk::new(ids[k - 1], id, walk.clone()).expect("f"));
            }
            if k % 3 == 1 {
                let x = f64::from(k as u32);
                let z = Vector6::new((0.3 * x).sin(), 0.1 * x, -0.2, 0.01 * x, (0.2 * x).cos() * 0.01, 0.0);
                graph.add(VectorPrior::bias(id, ImuBias::from_vector(&z), seen.clone()).expect("f"));
            }
            ids.push(id);
            smoother.update(&graph, &mut values, &[id]).expect("update");
            let ours = smoother.newest_covariance().expect("covariance").clone();
            // The batch marginal and estimate of the graph so far.
            let mut batch_values = values.clone();
            let all: Vec<usize> = (0..graph.len()).collect();
            let ordering = Ordering::all(&batch_values);
            let mut st = None;
            levenberg_marquardt(
                &graph,
                &all,
                &mut batch_values,
                &ordering,
                &LmParams::default(),
                &mut st,
            )
            .expect("batch");
            let st = st.expect("structure");
            let ne = crate::linear::linearize(&graph, &all, &batch_values, &st).expect("linearise");
            let f = Factorization::new(&st, &ne.hessian, 0.0).expect("factor");
            let batch = marginal_covariance(&f, st.ordering(), id).expect("marginal");
            let moved = (values.bias(id).expect("b").vector() - batch_values.bias(id).expect("b").vector()).norm();
            out.push((ours, batch, moved));
        }
        out
    }

    /// The fixed-lag smoother with a window of 4 states, re-solving in line.
    fn four_state_window() -> SmootherParams {
        SmootherParams {
            method: SmootherMethod::FixedLag,
            lag_states: 4,
            background: false,
            ..SmootherParams::default()
        }
    }

    #[test]
    fn a_window_with_a_free_direction_still_gives_the_pose_covariance() {
        use crate::factors::{BetweenPose, PosePrior, TrackOffset};
        use crate::lie::Pose3;
        // Poses in a chain; with `other`, the newest is also tied along-track to a pose that is
        // no state and that nothing else constrains: five of its six directions are free, so the
        // window has no Cholesky factor undamped.
        let newest_cov = |other: bool| {
            let mut smoother = FixedLagSmoother::new(four_state_window());
            let (mut graph, mut values) = (FactorGraph::new(), Values::new());
            let odo = NoiseModel::isotropic(6, 0.05).expect("noise");
            let step = Pose3::exp(&Vector6::new(0.0, 0.0, 0.05, 1.0, 0.0, 0.0));
            let mut prev: Option<VarId> = None;
            for _ in 0..6 {
                let guess = prev.map_or(Pose3::identity(), |p| values.pose(p).expect("pose").compose(&step));
                let id = values.push(Variable::Pose(guess));
                match prev {
                    None => graph.add(PosePrior::new(id, Pose3::identity(), odo.clone()).expect("f")),
                    Some(p) => graph.add(BetweenPose::new(p, id, step, odo.clone()).expect("f")),
                };
                prev = Some(id);
                smoother.update(&graph, &mut values, &[id]).expect("update");
            }
            if other {
                let pose = prev.expect("a pose");
                let at = values.pose(pose).expect("pose").compose(&step);
                let o = values.push(Variable::Pose(at));
                let noise = NoiseModel::isotropic(1, 0.01).expect("noise");
                // Measured as the estimate has it, so that the solve leaves the poses in place.
                let probe = TrackOffset::along(pose, o, 0.0, noise.clone()).expect("f");
                let seen = probe.evaluate(&values, None).expect("evaluate")[0];
                graph.add(TrackOffset::along(pose, o, seen, noise).expect("f"));
            }
            // An update without a new state: the other pose, if any, joins the window.
            smoother.update(&graph, &mut values, &[]).expect("update");
            smoother.newest_covariance().cloned()
        };
        let without = newest_cov(false).expect("covariance alone");
        let with = newest_cov(true).expect("covariance beside a free pose");
        // The free pose takes up the factor: the newest pose's covariance is the one without it.
        assert!((&with - &without).norm() < 1e-6 * without.norm(), "{with} vs {without}");
    }

    /// What a fixed-lag run on a pose chain whose odometry is 5 % long, with a loop closure
    /// from every state past the 12th to the state 10 before it (behind the 4-state window),
    /// did: the states whose update started a re-solve, the states each such update moved, and
    /// the values after the final solve.
    fn closure_chain(
        spacing: usize,
        resolve_window: usize,
        growth: f64,
        wide: usize,
    ) -> (Vec<usize>, Vec<Vec<usize>>, Values) {
        use crate::factors::{BetweenPose, PosePrior};
        use crate::lie::Pose3;
        let mut smoother = FixedLagSmoother::new(SmootherParams {
            resolve_spacing_states: spacing,
            resolve_window_states: resolve_window,
            resolve_spacing_growth: growth,
            resolve_wide_states: wide,
            ..four_state_window()
        });
        let (mut graph, mut values) = (FactorGraph::new(), Values::new());
        let noise = NoiseModel::isotropic(6, 0.05).expect("noise");
        let step = |scale: f64| Pose3::exp(&Vector6::new(0.0, 0.0, 0.1, scale, 0.0, 0.0));
        let (mut ids, mut started, mut moved): (Vec<VarId>, Vec<usize>, Vec<Vec<usize>>) = Default::default();
        for k in 0..40 {
            let guess = ids.last().map_or(Pose3::identity(), |p| {
                values.pose(*p).expect("pose").compose(&step(1.05))
            });
            let id = values.push(Variable::Pose(guess));
            match ids.last() {
                None => graph.add(PosePrior::new(id, Pose3::identity(), noise.clone()).expect("f")),
                Some(p) => graph.add(BetweenPose::new(*p, id, step(1.05), noise.clone()).expect("f")),
            };
            if k > 12 {
                let truth = (0..10).fold(Pose3::identity(), |acc, _| acc.compose(&step(1.0)));
                graph.add(BetweenPose::new(ids[k - 10], id, truth, noise.clone()).expect("f"));
            }
            ids.push(id);
            let before = values.clone();
            if smoother
                .update(&graph, &mut values, &[id])
                .expect("update")
                .started_full_solve
            {
                started.push(k);
                moved.push(
                    (0..k)
                        .filter(|&i| values.get(ids[i]).expect("pose") != before.get(ids[i]).expect("pose"))
                        .collect(),
                );
            }
        }
        smoother.finish(&graph, &mut values).expect("finish");
        (started, moved, values)
    }

    #[test]
    fn a_re_solve_window_holds_the_states_before_it_and_the_final_solve_is_the_same() {
        let (started, moved, whole) = closure_chain(1, 0, 0.0, 0);
        let (started_w, moved_w, windowed) = closure_chain(1, 10, 0.0, 0);
        assert_eq!(started, started_w);
        for ((k, all), window) in started.iter().zip(&moved).zip(&moved_w) {
            // a re-solve of the whole graph moves states older than the newest 10; with the
            // window, none of them moves (the update's state `k` is the newest, its re-solve
            // frees `k - 9 ..= k`)
            assert!(all.iter().any(|&i| i + 10 <= *k), "state {k}: {all:?}");
            assert!(window.iter().all(|&i| i + 10 > *k), "state {k}: {window:?}");
            assert!(!window.is_empty(), "state {k}");
        }
        assert_same_poses(&whole, &windowed);
    }

    /// Two runs' poses agree to the solver's stopping tolerance (a relative 1e-6 of the error:
    /// some 1e-6 m on the 40 m chain of [`closure_chain`]).
    fn assert_same_poses(a: &Values, b: &Values) {
        for (a, b) in a.as_slice().iter().zip(b.as_slice()) {
            let (Variable::Pose(a), Variable::Pose(b)) = (a, b) else {
                panic!("poses")
            };
            assert!(a.local(b).norm() < 1e-5, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn a_landmark_seen_again_from_the_window_is_a_loop_closure() {
        use crate::factors::{BetweenPose, LineDistance, PosePrior};
        use crate::lie::Pose3;
        use crate::values::HoughLine;
        // A pose chain along x (window of 4 states) and the wall x = 30, observed ahead from
        // the states `seen`: returns the states whose update started a re-solve.
        let run = |seen: &[usize]| {
            let mut smoother = FixedLagSmoother::new(four_state_window());
            let (mut graph, mut values) = (FactorGraph::new(), Values::new());
            let noise = NoiseModel::isotropic(6, 0.05).expect("noise");
            let step = Pose3::exp(&Vector6::new(0.0, 0.0, 0.0, 1.0, 0.0, 0.0));
            let wall = values.push(Variable::Line(HoughLine {
                rho_m: 30.0,
                theta_rad: 0.0,
            }));
            let (mut prev, mut started) = (None::<VarId>, Vec::new());
            for k in 0..12 {
                let pose = (0..k).fold(Pose3::identity(), |acc, _| acc.compose(&step));
                let id = values.push(Variable::Pose(pose));
                match prev {
                    None => graph.add(PosePrior::new(id, Pose3::identity(), noise.clone()).expect("f")),
                    Some(p) => graph.add(BetweenPose::new(p, id, step, noise.clone()).expect("f")),
                };
                if seen.contains(&k) {
                    let along = NoiseModel::isotropic(1, 0.05).expect("noise");
                    graph.add(LineDistance::new(id, wall, 30.0 - k as f64, along).expect("f"));
                }
                prev = Some(id);
                if smoother
                    .update(&graph, &mut values, &[id])
                    .expect("update")
                    .started_full_solve
                {
                    started.push(k);
                }
            }
            started
        };
        // seen from state 1, again from state 10 (state 1 is then 9 states back)
        assert_eq!(run(&[1, 10]), vec![10]);
        // seen from states 8 and 10 only: both in the window at state 10
        assert!(run(&[8, 10]).is_empty());
    }

    #[test]
    fn re_solves_are_spaced_and_the_closures_between_wait_for_the_next() {
        let (every, _, at_one) = closure_chain(1, 0, 0.0, 0);
        let (spaced, _, at_ten) = closure_chain(10, 0, 0.0, 0);
        assert_eq!(every, (13..40).collect::<Vec<_>>());
        // The first closure re-solves at once, the next ones at least 10 states later.
        assert_eq!(spaced, vec![13, 23, 33]);
        // The final solve reaches the same optimum either way.
        assert_same_poses(&at_one, &at_ten);
    }

    #[test]
    fn whole_graph_re_solves_are_spaced_in_proportion_to_the_graph() {
        // The first closure (state 13, 14 states) re-solves at once; the next whole re-solves
        // wait half the states there were at the last one: 7 (state 20), then 10 (state 30).
        let (whole, _, at_one) = closure_chain(1, 0, 0.0, 0);
        let (grown, _, at_grown) = closure_chain(1, 0, 0.5, 0);
        assert_eq!(grown, vec![13, 20, 30]);
        assert_same_poses(&at_one, &at_grown);
        // With a re-solve window, the updates in between still re-solve, the window only.
        let (hybrid, moved, at_hybrid) = closure_chain(1, 10, 0.5, 0);
        assert_eq!(hybrid, whole);
        for (k, moved) in hybrid.iter().zip(&moved) {
            let behind = moved.iter().any(|&i| i + 10 <= *k);
            assert_eq!(behind, grown.contains(k), "state {k}: {moved:?}");
        }
        assert_same_poses(&at_one, &at_hybrid);
        // Wide re-solves of the newest 15 states: the older ones stay where they were.
        let (bounded, moved, at_bounded) = closure_chain(1, 5, 0.5, 15);
        assert_eq!(bounded, whole);
        for (k, moved) in bounded.iter().zip(&moved) {
            // (state 13's wide re-solve, of 14 states, is of the whole graph)
            let reach = if grown.contains(k) { 15.min(k + 1) } else { 5 };
            assert!(moved.iter().all(|&i| i + reach > *k), "state {k}: {moved:?}");
            assert!(moved.iter().any(|&i| i + reach == *k + 1), "state {k}: {moved:?}");
        }
        assert_same_poses(&at_one, &at_bounded);
    }

    #[test]
    fn marginalising_a_linear_chain_gives_the_batch_marginal_and_estimate() {
        for lag in [1, 4, 10] {
            for (k, (ours, batch, moved)) in linear_chain(true, lag).iter().enumerate() {
                assert!(
                    (ours - batch).norm() < 1e-6 * batch.norm(),
                    "lag {lag} state {k}: {ours} vs {batch}"
                );
                assert!(
                    *moved < 1e-6,
                    "lag {lag} state {k}: newest estimate {moved} from the batch one"
                );
            }
        }
        // Held at their estimate instead, the states behind the window make the newest state's
        // covariance the one given them: far smaller than the marginal once the chain is longer
        // than the window.
        let (ours, batch, _) = &linear_chain(false, 4)[39];
        assert!(ours.trace() < 0.5 * batch.trace(), "{ours} vs {batch}");
    }
}
