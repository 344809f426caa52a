//! `gprflow bench estimate`: the peer's exported problem solved in batch and incrementally.

use std::time::Instant;

use serde::Serialize;

use crate::Result;
use crate::batch::{LmParams, levenberg_marquardt};
use crate::linear::Ordering;
use crate::problem::{LineMode, Problem, ProblemGraph};
use crate::smoother::{Smoother, SmootherParams};
use crate::values::ImuBias;

/// Batch Levenberg-Marquardt from the dead-reckoning guess.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BatchFigures {
    /// Graph error before.
    pub initial_error: f64,
    /// Graph error after (GTSAM's definition: sum of 0.5 ||whitened||^2, robust losses).
    pub final_error: f64,
    /// Accepted iterations.
    pub iterations: usize,
    /// Wall time, s.
    pub seconds: f64,
    /// Linear solves (accepted and rejected steps).
    pub linear_solves: usize,
    /// Time linearising, s.
    pub linearize_s: f64,
    /// Time in numeric Cholesky and solves, s.
    pub solve_s: f64,
    /// Time evaluating candidate steps, s.
    pub evaluate_s: f64,
    /// Threads that linearised.
    pub linearize_threads: usize,
    /// ATE RMSE, no alignment, m.
    pub ate_rmse_m: f64,
    /// ATE max, m.
    pub ate_max_m: f64,
}

/// One update per state with the smoother.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct IncrementalFigures {
    /// Updates (= states).
    pub updates: usize,
    /// Per-update wall time (add the state, solve the window, read the estimate), ms.
    pub update_ms_p50: f64,
    /// 99th percentile, ms.
    pub update_ms_p99: f64,
    /// Maximum, ms.
    pub update_ms_max: f64,
    /// Per-update wall time of the updates that carry a loop closure, ms (median).
    pub loop_closure_update_ms_p50: f64,
    /// 99th percentile, ms.
    pub loop_closure_update_ms_p99: f64,
    /// Maximum, ms.
    pub loop_closure_update_ms_max: f64,
    /// Full re-solves merged during the run (fixed-lag smoother).
    pub full_solves: usize,
    /// Longest full re-solve (solver time on its thread), ms.
    pub full_solve_ms_max: f64,
    /// Median full re-solve, ms.
    pub full_solve_ms_p50: f64,
    /// The back-substitution of every variable at the end of the run (the incremental
    /// smoother's `refresh`), ms.
    pub refresh_ms: f64,
    /// The newest pose's covariance `[rot x3, trans x3]` after the last update (rows), if the
    /// smoother computed one: the marginal one for the incremental smoother.
    pub newest_pose_covariance: Option<Vec<Vec<f64>>>,
    /// ATE RMSE of the estimate at the end of the run, before the final solve, m.
    pub online_ate_rmse_m: f64,
    /// Batch-graph error at that estimate.
    pub online_error: f64,
    /// The final warm-started full solve, s.
    pub final_solve_seconds: f64,
    /// Its iterations.
    pub final_solve_iterations: usize,
    /// Batch-graph error after the final solve.
    pub final_error: f64,
    /// ATE RMSE after the final solve, m.
    pub ate_rmse_m: f64,
}

/// Everything the bench prints.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BenchReport {
    /// States.
    pub states: usize,
    /// Factors of the batch graph.
    pub factors: usize,
    /// Loop closures.
    pub loop_closures: usize,
    /// Lines mode.
    pub lines: String,
    /// Dead-reckoning ATE RMSE, m.
    pub dead_reckoning_ate_rmse_m: f64,
    /// Batch solve.
    pub batch: BatchFigures,
    /// Incremental run.
    pub incremental: Option<IncrementalFigures>,
}

/// Nearest-rank percentile of sorted data.
#[must_use]
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p / 100.0 * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// What to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchOptions {
    /// Line factors.
    pub lines: LineMode,
    /// The incremental run's smoother (`None`: batch only).
    pub smoother: Option<SmootherParams>,
    /// Feed the incremental run one state every `1 / pace_hz` seconds, as a live pipeline
    /// would (`None`: as fast as the updates go, which starves the background re-solves of
    /// the states they would otherwise span).
    pub pace_hz: Option<f64>,
    /// Threads that linearise in the batch solve (1: single-threaded).
    pub linearize_threads: usize,
}

/// Solves `problem` in batch and (unless `options.smoother` is `None`) incrementally.
///
/// # Errors
/// A factor that cannot be evaluated or a solver failure.
pub fn run(problem: &Problem, options: &BenchOptions) -> Result<BenchReport> {
    let lines = options.lines;
    let mut batch = ProblemGraph::batch(problem, lines)?;
    let dr = batch.ate(problem)?;
    let all: Vec<usize> = (0..batch.graph.len()).collect();
    let ordering = Ordering::all(&batch.values);
    let lm = levenberg_marquardt(
        &batch.graph,
        &all,
        &mut batch.values,
        &ordering,
        &LmParams {
            linearize_threads: options.linearize_threads,
            ..LmParams::default()
        },
        &mut None,
    )?;
    let ate = batch.ate(problem)?;
    let batch_figs = BatchFigures {
        initial_error: lm.initial_error,
        final_error: lm.final_error,
        iterations: lm.iterations,
        seconds: lm.seconds,
        linear_solves: lm.linear_solves,
        linearize_s: lm.linearize_s,
        solve_s: lm.solve_s,
        evaluate_s: lm.evaluate_s,
        linearize_threads: options.linearize_threads.max(1),
        ate_rmse_m: ate.0,
        ate_max_m: ate.1,
    };
    let incremental = match options.smoother {
        Some(p) => Some(run_incremental(problem, lines, p, options.pace_hz, &batch)?),
        None => None,
    };
    Ok(BenchReport {
        states: problem.params.states,
        factors: batch.graph.len(),
        loop_closures: problem.loop_closures.len(),
        lines: format!("{lines:?}").to_lowercase(),
        dead_reckoning_ate_rmse_m: dr.0,
        batch: batch_figs,
        incremental,
    })
}

fn run_incremental(
    problem: &Problem,
    lines: LineMode,
    params: SmootherParams,
    pace_hz: Option<f64>,
    batch: &ProblemGraph,
) -> Result<IncrementalFigures> {
    let start = Instant::now();
    let mut pg = ProblemGraph::new(problem, lines)?;
    let mut smoother = Smoother::new(params);
    let mut times_ms = Vec::with_capacity(problem.params.states);
    let mut full_ms = Vec::new();
    let mut closure_ms = Vec::new();
    for i in 0..problem.params.states {
        if let Some(hz) = pace_hz.filter(|hz| hz.is_finite() && *hz > 0.0) {
            let due = std::time::Duration::from_secs_f64(i as f64 / hz);
            std::thread::sleep(due.saturating_sub(start.elapsed()));
        }
        let t0 = Instant::now();
        let (init, bias_hat) = if i == 0 {
            let gt = problem.ground_truth[0];
            ((gt.pose, gt.velocity_mps, ImuBias::default()), ImuBias::default())
        } else {
            // Preintegrated at zero bias like the batch graph, so that both runs end on the same
            // graph (the bias estimate enters through the first-order correction).
            let prev = pg.states[i - 1];
            let bias = *pg.values.bias(prev.bias)?;
            let pim = problem.preintegrate(i, ImuBias::default())?;
            let (pose, vel) = pim.predict(pg.values.pose(prev.pose)?, pg.values.velocity(prev.velocity)?, &bias);
            ((pose, vel, bias), ImuBias::default())
        };
        pg.add_state(problem, i, init, bias_hat)?;
        let keys = pg.states[i];
        let rep = smoother.update(&pg.graph, &mut pg.values, &[keys.pose, keys.velocity, keys.bias])?;
        let _estimate = pg.values.pose(keys.pose)?;
        times_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        if problem.loop_closures.iter().any(|lc| lc.to == i && lc.from < i) {
            closure_ms.push(times_ms[i]);
        }
        if let Some(m) = rep.merged {
            full_ms.push(m.lm.seconds * 1e3);
        }
    }
    let newest_pose_covariance = smoother
        .newest_covariance()
        .map(|c| c.row_iter().map(|r| r.iter().copied().collect()).collect());
    let t = Instant::now();
    smoother.refresh(&mut pg.values)?;
    let refresh_ms = t.elapsed().as_secs_f64() * 1e3;
    let online_ate = pg.ate(problem)?;
    let online_error = batch.graph.error(&pg.values)?;
    let fin = smoother.finish(&pg.graph, &mut pg.values)?;
    let ate = pg.ate(problem)?;
    let final_error = batch.graph.error(&pg.values)?;
    times_ms.sort_by(f64::total_cmp);
    full_ms.sort_by(f64::total_cmp);
    closure_ms.sort_by(f64::total_cmp);
    Ok(IncrementalFigures {
        updates: times_ms.len(),
        update_ms_p50: percentile(&times_ms, 50.0),
        update_ms_p99: percentile(&times_ms, 99.0),
        update_ms_max: times_ms.last().copied().unwrap_or(f64::NAN),
        loop_closure_update_ms_p50: percentile(&closure_ms, 50.0),
        loop_closure_update_ms_p99: percentile(&closure_ms, 99.0),
        loop_closure_update_ms_max: closure_ms.last().copied().unwrap_or(f64::NAN),
        full_solves: full_ms.len(),
        full_solve_ms_max: full_ms.last().copied().unwrap_or(0.0),
        full_solve_ms_p50: if full_ms.is_empty() {
            0.0
        } else {
            percentile(&full_ms, 50.0)
        },
        refresh_ms,
        newest_pose_covariance,
        online_ate_rmse_m: online_ate.0,
        online_error,
        final_solve_seconds: fin.seconds,
        final_solve_iterations: fin.iterations,
        final_error,
        ate_rmse_m: ate.0,
    })
}
