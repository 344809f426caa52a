//! `gprflow bench estimate PROBLEM`: thin wrapper over `gprflow_estimate::bench`.

use std::io::Write;
use std::path::Path;
use std::process::ExitCode;

use gprflow_estimate::bench::{BenchOptions, BenchReport, run};
use gprflow_estimate::problem::{LineMode, Problem};
use gprflow_estimate::smoother::{SmootherMethod, SmootherParams};

/// Options of the command.
#[derive(Debug, Clone)]
pub struct BenchEstimateArgs {
    /// Line factors: off, known, estimated.
    pub lines: LineMode,
    /// Skip the incremental run.
    pub batch_only: bool,
    /// The fixed-lag smoother instead of the incremental one.
    pub fixed_lag: bool,
    /// Window of the fixed-lag smoother, states.
    pub lag_states: usize,
    /// Fixed-lag smoother: marginalise the states leaving the window.
    pub marginalise: bool,
    /// Feed one state every `1 / pace_hz` seconds, as a live pipeline would.
    pub pace_hz: Option<f64>,
    /// Threads that linearise in the batch solve.
    pub threads: usize,
    /// JSON output.
    pub json: bool,
}

/// Runs the benchmark and prints its report.
///
/// # Errors
/// Unreadable problem file or a solver failure.
pub fn bench_estimate(problem: &Path, args: &BenchEstimateArgs) -> anyhow::Result<ExitCode> {
    let p = Problem::read(problem)?;
    let smoother = (!args.batch_only).then(|| SmootherParams {
        method: if args.fixed_lag {
            SmootherMethod::FixedLag
        } else {
            SmootherMethod::Incremental
        },
        lag_states: args.lag_states,
        marginalise: args.marginalise,
        ..SmootherParams::default()
    });
    let report = run(
        &p,
        &BenchOptions {
            lines: args.lines,
            smoother,
            pace_hz: args.pace_hz,
            linearize_threads: args.threads,
        },
    )?;
    let mut out = std::io::stdout().lock();
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
    } else {
        print_table(&mut out, &report)?;
    }
    Ok(ExitCode::SUCCESS)
}

fn print_table(out: &mut impl Write, r: &BenchReport) -> std::io::Result<()> {
    writeln!(
        out,
        "problem: {} states, {} factors, {} loop closures, lines {}; dead reckoning ATE {:.3} m",
        r.states, r.factors, r.loop_closures, r.lines, r.dead_reckoning_ate_rmse_m
    )?;
    let b = &r.batch;
    writeln!(
        out,
        "batch LM: {:.3} s ({} linearising thread{}), {} iterations, error {:.4e} -> {:.6e}; ATE {:.4} m (max {:.4})",
        b.seconds,
        b.linearize_threads,
        if b.linearize_threads == 1 { "" } else { "s" },
        b.iterations,
        b.initial_error,
        b.final_error,
        b.ate_rmse_m,
        b.ate_max_m
    )?;
    if let Some(i) = &r.incremental {
        writeln!(
            out,
            "incremental: {} updates, per update ms p50 {:.3} p99 {:.3} max {:.3}",
            i.updates, i.update_ms_p50, i.update_ms_p99, i.update_ms_max
        )?;
        writeln!(
            out,
            "   updates with a loop closure, ms p50 {:.3} p99 {:.3} max {:.3}",
            i.loop_closure_update_ms_p50, i.loop_closure_update_ms_p99, i.loop_closure_update_ms_max
        )?;
        if i.full_solves > 0 {
            writeln!(
                out,
                "   background full solves (fixed-lag): {} merged, ms p50 {:.1} max {:.1}",
                i.full_solves, i.full_solve_ms_p50, i.full_solve_ms_max
            )?;
        }
        writeln!(
            out,
            "   online estimate at the end: error {:.6e}, ATE {:.4} m",
            i.online_error, i.online_ate_rmse_m
        )?;
        writeln!(
            out,
            "   after the final full solve ({:.3} s): error {:.6e}, ATE {:.4} m",
            i.final_solve_seconds, i.final_error, i.ate_rmse_m
        )?;
    }
    Ok(())
}
