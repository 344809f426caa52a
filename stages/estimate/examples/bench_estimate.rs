//! The estimation benchmark without the runtime (for quick optimised builds):
//! `cargo run --release -p gprflow-estimate --no-default-features --example bench_estimate -- problem.txt [lag]`.
//! Prints the same JSON as `gprflow bench estimate problem.txt --json`.

use std::io::Write;

use gprflow_estimate::bench::{BenchOptions, run};
use gprflow_estimate::problem::{LineMode, Problem};
use gprflow_estimate::smoother::SmootherParams;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = args
        .next()
        .ok_or("usage: bench_estimate problem.txt [lag_states, 0: batch only] [off|known|estimated] [pace_hz]")?;
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
    let pace_hz = args.next().map(|s| s.parse()).transpose()?;
    let problem = Problem::read(std::path::Path::new(&path))?;
    // A lag of 0 runs the batch solve only.
    let smoother = (lag_states > 0).then(|| SmootherParams {
        lag_states,
        ..SmootherParams::default()
    });
    let report = run(
        &problem,
        &BenchOptions {
            lines,
            smoother,
            pace_hz,
        },
    )?;
    writeln!(std::io::stdout().lock(), "{}", serde_json::to_string_pretty(&report)?)?;
    Ok(())
}
