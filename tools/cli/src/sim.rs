//! `gprflow sim`: write a recording from a scenario file.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use gprflow_sim::{Scenario, SimOptions};

/// Output formats of `gprflow sim`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimFormat {
    /// One MCAP recording.
    Mcap,
    /// The MCAP recording and the CMU-GPR folder layout next to it (`OUTPUT` without its
    /// extension: gpr_meas.csv, imu_meas.csv, we_odom_meas.csv, ts_meas.csv).
    CmuGpr,
}

/// Arguments of `gprflow sim`.
#[derive(Debug, Clone)]
pub struct SimArgs {
    /// Scenario file (absent with `schema`).
    pub scenario: Option<PathBuf>,
    /// MCAP file to write.
    pub output: Option<PathBuf>,
    /// Run to simulate.
    pub run: Option<String>,
    /// Output format.
    pub format: SimFormat,
    /// Stop after this many seconds.
    pub duration_s: Option<f64>,
    /// Draw the sensor noise afresh (0: the scenario's own).
    pub repeat: u32,
    /// Print the scenario JSON schema and exit.
    pub schema: bool,
    /// Print the summary as JSON.
    pub json: bool,
}

/// Runs `gprflow sim`.
///
/// # Errors
/// Bad scenario (file, line, key), unknown run, write errors.
pub fn sim(args: &SimArgs) -> Result<ExitCode> {
    let mut out = std::io::stdout().lock();
    if args.schema {
        writeln!(out, "{}", serde_json::to_string_pretty(&Scenario::json_schema())?)?;
        return Ok(ExitCode::SUCCESS);
    }
    let scenario_path = args.scenario.as_ref().context("a scenario file is needed")?;
    let output = args.output.clone().context("an output file is needed (-o rec.mcap)")?;
    let scenario = Scenario::load(scenario_path)?;
    let cmu_gpr = (args.format == SimFormat::CmuGpr).then(|| output.with_extension(""));
    if cmu_gpr.as_ref() == Some(&output) {
        anyhow::bail!(
            "{}: give the output an extension (.mcap) so the CMU-GPR folder can sit beside it",
            output.display()
        );
    }
    let opts = SimOptions {
        run: args.run.clone(),
        output: output.clone(),
        cmu_gpr,
        max_duration_s: args.duration_s,
        repeat: args.repeat,
        scenario_text: std::fs::read_to_string(scenario_path).unwrap_or_default(),
    };
    let bar = indicatif::ProgressBar::with_draw_target(Some(1000), indicatif::ProgressDrawTarget::stderr());
    bar.set_style(
        indicatif::ProgressStyle::with_template("simulating {wide_bar} {percent}% [{elapsed_precise}<{eta_precise}]")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let started = std::time::Instant::now();
    let summary = gprflow_sim::simulate(&scenario, &opts, &mut |f| bar.set_position((f * 1000.0) as u64))
        .with_context(|| format!("simulating {}", scenario_path.display()))?;
    bar.finish_and_clear();
    let wall_s = started.elapsed().as_secs_f64();
    if args.json {
        let mut v = serde_json::to_value(&summary)?;
        v["wall_s"] = serde_json::json!(wall_s);
        v["output"] = serde_json::json!(output);
        writeln!(out, "{v}")?;
    } else {
        writeln!(
            out,
            "{} / {}: {:.1} s of sensor time, {:.1} m driven, written to {} in {:.2} s",
            summary.scenario,
            summary.run,
            summary.duration_s,
            summary.distance_m,
            output.display(),
            wall_s
        )?;
        for (topic, n) in &summary.messages {
            writeln!(out, "  /{topic:<28} {n:>9}")?;
        }
        if let Some(dir) = &opts.cmu_gpr {
            writeln!(out, "  CMU-GPR folder: {}", dir.display())?;
        }
    }
    Ok(ExitCode::SUCCESS)
}
