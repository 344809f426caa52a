//! The estimation benchmark without the runtime (for quick optimised builds):
//! `cargo run --release -p gprflow-estimate --no-default-features --example bench_estimate -- problem.txt [lag]`.
//! Prints the same JSON as `gprflow bench estimate problem.txt --json`.

use std::io::Write;

use gprflow_estimate::bench::{BenchOptions, run};
use gprflow_estimate::incremental::IncrementalParams;
use gprflow_estimate::problem::{LineMode, Problem};
use gprflow_estimate::smoother::{SmootherMethod, SmootherParams};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = args
        .next()
        .ok_or("usage: bench_estimate problem.txt [lag_states, 0: batch only] [off|known|estimated] [pace_hz, 0: unpaced] [incremental|fixed_lag]")?;
    let lag_states = args
        .next()
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(SmootherParams::default().lag_states);
    let lines = match args.next().as_deref() {
        Some("known") => LineMode::Known,
        Some("estimated") => LineMode::Estimated,
        _ => LineMode::Off,
    };
    let pace_hz = args.next().map(|s| s.parse()).transpose()?.filter(|hz: &f64| *hz > 0.0);
    let method = match args.next().as_deref() {
        Some("fixed_lag") => SmootherMethod::FixedLag,
        _ => SmootherMethod::Incremental,
    };
    let problem = Problem::read(std::path::Path::new(&path))?;
    // A lag of 0 runs the batch solve only.
    let d = IncrementalParams::default();
    let smoother = (lag_states > 0).then(|| SmootherParams {
        lag_states,
        method,
        incremental: IncrementalParams {
            relinearize_rotation_rad: env("RELIN_ROT", d.relinearize_rotation_rad),
            relinearize_translation_m: env("RELIN_TRANS", d.relinearize_translation_m),
            relinearize_velocity_mps: env("RELIN_VEL", d.relinearize_velocity_mps),
            relinearize_bias: env("RELIN_BIAS", d.relinearize_bias),
            wildfire_threshold: env("WILD", d.wildfire_threshold),
            max_relinearized_per_update: env("RELIN_CAP", d.max_relinearized_per_update as f64) as usize,
            ..IncrementalParams::default()
        },
        ..SmootherParams::default()
    });
    let report = run(
        &problem,
        &BenchOptions {
            lines,
            smoother,
            pace_hz,
            linearize_threads: 1,
        },
    )?;
    writeln!(std::io::stdout().lock(), "{}", serde_json::to_string_pretty(&report)?)?;
    Ok(())
}

fn env(name: &str, default: f64) -> f64 {
    std::env::var(name).ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}
