//! `gprflow calibrate-wheel`: the wheel's scale against ground truth, over one or more
//! recordings of a rig.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Result, bail};
use gprflow::eval::{Stats, Trajectory, WheelFit, WheelTrack, fit_wheel, wheel_period_errors};
use gprflow::record::Recording;
use serde::Serialize;

/// Arguments of `gprflow calibrate-wheel`.
#[derive(Debug, Clone)]
pub struct CalibrateWheelArgs {
    /// Recordings with wheel odometry and ground truth.
    pub recordings: Vec<PathBuf>,
    /// Wheel topic (default: the recording's `WheelOdometry` topic).
    pub wheel_topic: Option<String>,
    /// Ground-truth topic.
    pub truth_topic: String,
    /// Longest truth gap to interpolate over, ms.
    pub max_gap_ms: f64,
    /// Period of the along-track error figure, ms.
    pub period_ms: f64,
    /// Print JSON instead of text.
    pub json: bool,
}

/// One recording's fit, and all of them together.
#[derive(Debug, Serialize)]
struct Report {
    recordings: Vec<(String, WheelFit, Option<f64>)>,
    combined: WheelFit,
    /// `ingest`'s `wheel_scale` for this rig.
    wheel_scale: f64,
    /// Period of the error figure, ms.
    period_ms: f64,
    /// RMS over every recording's periods of the scaled wheel's along-track error against the
    /// truth, m (the truth's noise included).
    period_error_rms_m: Option<f64>,
    /// Periods in it.
    periods: usize,
}

/// Fits the wheel scale over `args.recordings` and prints it per recording and combined.
///
/// # Errors
/// An unreadable recording, a missing wheel or truth topic, or a wheel that never moved
/// while the truth covered it.
pub fn calibrate_wheel(args: &CalibrateWheelArgs) -> Result<ExitCode> {
    if !(args.max_gap_ms.is_finite() && args.max_gap_ms > 0.0) {
        bail!("--max-gap-ms must be finite and > 0, got {}", args.max_gap_ms);
    }
    if !(args.period_ms.is_finite() && args.period_ms > 0.0) {
        bail!("--period-ms must be finite and > 0, got {}", args.period_ms);
    }
    if args.recordings.is_empty() {
        bail!("no recording given");
    }
    let max_gap_ns = (args.max_gap_ms * 1e6) as i64;
    let mut recordings = Vec::new();
    let mut tracks = Vec::new();
    let mut combined = WheelFit::default();
    for path in &args.recordings {
        let rec = Recording::open(path)?;
        let wheel = WheelTrack::from_recording(&rec, args.wheel_topic.as_deref())?;
        let truth = Trajectory::from_recording(&rec, &args.truth_topic)?;
        let fit = fit_wheel(&wheel, &truth, max_gap_ns);
        recordings.push((path.display().to_string(), fit, fit.scale()));
        combined = combined.with(fit);
        tracks.push((wheel, truth));
    }
    let Some(wheel_scale) = combined.scale() else {
        bail!("the wheel never moved while the truth covered it: nothing to calibrate against");
    };
    let period_ns = (args.period_ms * 1e6) as i64;
    let errors: Vec<f64> = tracks
        .iter()
        .flat_map(|(wheel, truth)| wheel_period_errors(wheel, truth, wheel_scale, period_ns, max_gap_ns))
        .collect();
    let report = Report {
        recordings,
        combined,
        wheel_scale,
        period_ms: args.period_ms,
        period_error_rms_m: Stats::of(&errors).map(|s| s.rmse),
        periods: errors.len(),
    };
    let mut out = std::io::stdout().lock();
    if args.json {
        writeln!(out, "{}", serde_json::to_string_pretty(&report)?)?;
        return Ok(ExitCode::SUCCESS);
    }
    for (path, fit, scale) in &report.recordings {
        let scale = scale.map_or_else(|| "-".to_owned(), |s| format!("{s:.5}"));
        writeln!(
            out,
            "{path}: scale {scale} (ground {:.3} m over wheel {:.3} m, {} steps, {} in truth gaps)",
            fit.ground_m, fit.wheel_m, fit.intervals, fit.skipped
        )?;
    }
    writeln!(
        out,
        "combined: scale {:.5} over {:.3} m of wheel travel\n--set wheel_scale={:.5}  (ingest's wheel_scale)",
        report.wheel_scale, report.combined.wheel_m, report.wheel_scale
    )?;
    if let Some(rms) = report.period_error_rms_m {
        writeln!(
            out,
            "along-track error per {} ms with that scale: RMS {:.2} mm over {} periods (the truth's noise included: a bound for the estimator's wheel_sigma_m)",
            report.period_ms,
            rms * 1e3,
            report.periods
        )?;
    }
    Ok(ExitCode::SUCCESS)
}
