//! `gprflow lgpr-eval`: LGPR tracking runs measured as seed 001 §3 does (eq. 11; Tables IV-V,
//! Figs. 15, 17, 18, 19), against the mapping pass they were tracked on.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::eval::Trajectory;
use gprflow::eval::lgpr::{Fixes, Options, Sample, Summary, Tracks, evaluate, summarise};
use gprflow::msg::{Odometry, PoseStamped};
use gprflow::record::Recording;
use serde::Serialize;

use crate::eval::ReportFormat;
use crate::plot::{Series, Style, chart};

/// Arguments of `gprflow lgpr-eval`.
#[derive(Debug, Clone)]
pub struct LgprEvalArgs {
    /// Tracking runs: recordings with the map fixes, the pass's truth and its GPS/INS.
    pub runs: Vec<PathBuf>,
    /// The mapping pass (its truth and GPS/INS).
    pub baseline: PathBuf,
    /// Largest true lateral offset from the baseline kept, m.
    pub max_offset_m: f64,
    /// Evaluate this pose topic (a fused estimate) instead of the map fixes, from the
    /// run's first locked map fix on (as the fixes are) when the run holds them.
    pub topic: Option<String>,
    /// Output format.
    pub format: ReportFormat,
    /// Write the figures (PNG) into this directory.
    pub plot_dir: Option<PathBuf>,
    /// Write each run's evaluated fixes as CSV into this directory.
    pub samples_dir: Option<PathBuf>,
}

/// One run's row.
#[derive(Debug, Clone, Serialize)]
struct Row {
    run: String,
    #[serde(flatten)]
    summary: Summary,
}

/// The truth (a PoseStamped topic named `truth`) and the GPS/INS (an Odometry topic) of a
/// recording.
fn truth_and_gps(path: &Path) -> Result<(Trajectory, Trajectory)> {
    let rec = Recording::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
    let topics = rec.topics();
    let find = |ty: &str, want: &dyn Fn(&str) -> bool, what: &str| {
        topics
            .iter()
            .find(|(t, ty2)| ty2 == ty && want(t))
            .map(|(t, _)| t.clone())
            .with_context(|| format!("{}: no {what} topic", path.display()))
    };
    let truth = find(
        PoseStamped::ROS_NAME,
        &|t: &str| t.contains("truth"),
        "ground-truth (PoseStamped)",
    )?;
    let gps = find(Odometry::ROS_NAME, &|_: &str| true, "GPS/INS (Odometry)")?;
    Ok((
        Trajectory::from_recording(&rec, &truth)?,
        Trajectory::from_recording(&rec, &gps)?,
    ))
}

fn cm(v: f64) -> String {
    format!("{:.1}", v * 100.0)
}

/// Runs `gprflow lgpr-eval`.
///
/// # Errors
/// Unreadable recordings, missing topics, no evaluable fix, unwritable figures.
pub fn lgpr_eval_command(args: &LgprEvalArgs) -> Result<ExitCode> {
    let (base_truth, base_gps) = truth_and_gps(&args.baseline)?;
    let opts = Options {
        max_offset_m: args.max_offset_m,
        ..Options::default()
    };
    let mut rows = Vec::new();
    let mut skipped = Vec::new();
    let mut all: Vec<(String, Vec<Sample>)> = Vec::new();
    for run in &args.runs {
        let rec = Recording::open(run).with_context(|| format!("{}: cannot open", run.display()))?;
        let fixes = match &args.topic {
            Some(t) => {
                let fused = Fixes::from_trajectory(&Trajectory::from_recording(&rec, t)?);
                // over the span of the run's own map fixes, when it holds them
                let whole = |why: &str| {
                    eprintln!("{}: {why}: {t} evaluated over the whole run", run.display());
                };
                match Fixes::from_recording_if_any(&rec)?.map(|f| f.first_lock_ns()) {
                    Some(Some(first)) => fused.from_lock(first),
                    Some(None) => {
                        whole("its map fixes never lock");
                        fused
                    }
                    None => {
                        whole("no map fixes (no MapFix topic)");
                        fused
                    }
                }
            }
            None => Fixes::from_recording(&rec, None)?,
        };
        let (track_truth, track_gps) = truth_and_gps(run)?;
        let tracks = Tracks {
            track_truth: &track_truth,
            track_gps: &track_gps,
            base_truth: &base_truth,
            base_gps: &base_gps,
        };
        let samples = evaluate(&fixes, tracks, opts);
        let name = run
            .file_stem()
            .map_or_else(|| run.display().to_string(), |s| s.to_string_lossy().into_owned());
        let Some(summary) = summarise(&samples) else {
            // a pass that never locks (one beyond the overlap limit) is a result, not an error
            eprintln!(
                "{}: no fix to evaluate ({} fixes; none locked, or none within {} m of the baseline): left out",
                run.display(),
                fixes.stamps_ns.len(),
                args.max_offset_m
            );
            skipped.push(run.display().to_string());
            continue;
        };
        rows.push(Row {
            run: name.clone(),
            summary,
        });
        all.push((name, samples));
    }
    if rows.is_empty() {
        bail!(
            "no run has a fix to evaluate (none locked, or none within {} m of the baseline): {}",
            args.max_offset_m,
            skipped.join(", ")
        );
    }
    let pooled: Vec<Sample> = all.iter().flat_map(|(_, s)| s.iter().copied()).collect();
    if rows.len() > 1
        && let Some(summary) = summarise(&pooled)
    {
        rows.push(Row {
            run: "all".into(),
            summary,
        });
    }
    if args.topic.is_some() {
        // every pose of a fused estimate counts as a fix: its lock share says nothing
        for r in &mut rows {
            r.summary.locked_pct = f64::NAN;
        }
    }
    let mut out = std::io::stdout().lock();
    match args.format {
        ReportFormat::Json => {
            serde_json::to_writer_pretty(&mut out, &rows)?;
            writeln!(out)?;
        }
        ReportFormat::Text | ReportFormat::Markdown => {
            let md = args.format == ReportFormat::Markdown;
            let header = [
                "run",
                "km/h",
                "fixes",
                "dist m",
                "lock %",
                "LGPR cross",
                "along",
                "total",
                "68% cross",
                "95% cross",
                "GPS/INS cross",
                "along",
                "total",
            ];
            if md {
                writeln!(out, "| {} |", header.join(" | "))?;
                writeln!(out, "|{}", "---|".repeat(header.len()))?;
            } else {
                writeln!(out, "RMS errors in cm over distance (seed 001 eq. 11)")?;
                writeln!(out, "{}", header.map(|h| format!("{h:>14}")).join(""))?;
            }
            for r in &rows {
                let s = &r.summary;
                let cells = [
                    r.run.clone(),
                    format!("{:.0}", s.mean_speed_mps * 3.6),
                    s.fixes.to_string(),
                    format!("{:.0}", s.distance_m),
                    if s.locked_pct.is_nan() {
                        "-".into()
                    } else {
                        format!("{:.2}", s.locked_pct)
                    },
                    cm(s.lgpr.cross_m),
                    cm(s.lgpr.along_m),
                    cm(s.lgpr.total_m),
                    cm(s.cross_p68_m),
                    cm(s.cross_p95_m),
                    cm(s.gps.cross_m),
                    cm(s.gps.along_m),
                    cm(s.gps.total_m),
                ];
                if md {
                    writeln!(out, "| {} |", cells.join(" | "))?;
                } else {
                    writeln!(out, "{}", cells.map(|c| format!("{c:>14}")).join(""))?;
                }
            }
        }
    }
    if let Some(dir) = &args.samples_dir {
        for (name, samples) in &all {
            write_samples(&dir.join(format!("{name}.csv")), samples)?;
        }
        writeln!(out, "samples in {}", dir.display())?;
    }
    if let Some(dir) = &args.plot_dir {
        figures(dir, &all)?;
        writeln!(out, "figures in {}", dir.display())?;
    }
    Ok(ExitCode::SUCCESS)
}

/// One run's evaluated fixes as CSV, one row per fix.
fn write_samples(path: &Path, samples: &[Sample]) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    let file = std::fs::File::create(path).with_context(|| format!("{}: cannot create", path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    let write = |w: &mut std::io::BufWriter<std::fs::File>| -> std::io::Result<()> {
        writeln!(
            w,
            "stamp_ns,step_m,speed_mps,offset_m,lgpr_along_m,lgpr_cross_m,gps_along_m,gps_cross_m,correlation,locked"
        )?;
        for s in samples {
            writeln!(
                w,
                "{},{},{},{},{},{},{},{},{},{}",
                s.stamp_ns,
                s.weight_m,
                s.speed_mps,
                s.offset_m,
                s.lgpr[0],
                s.lgpr[1],
                s.gps[0],
                s.gps[1],
                s.correlation,
                u8::from(s.locked)
            )?;
        }
        w.flush()
    };
    write(&mut w).with_context(|| format!("{}: cannot write", path.display()))
}

/// Figs. 15, 17, 18 and 19 of seed 001 from the runs' samples.
fn figures(dir: &Path, runs: &[(String, Vec<Sample>)]) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let pooled: Vec<&Sample> = runs.iter().flat_map(|(_, s)| s.iter()).collect();
    let points = |label: &str, f: &dyn Fn(&Sample) -> (f64, f64)| Series {
        label: label.into(),
        points: pooled.iter().map(|s| f(s)).collect(),
    };
    // Fig. 15: error against speed, with the RMS per 8 km/h bin
    let mut bins: std::collections::BTreeMap<i64, (f64, f64)> = std::collections::BTreeMap::new();
    for s in &pooled {
        let b = bins.entry((s.speed_mps * 3.6 / 8.0).floor() as i64).or_default();
        b.0 += s.weight_m * (s.lgpr[0].powi(2) + s.lgpr[1].powi(2));
        b.1 += s.weight_m;
    }
    let rms_bins = Series {
        label: "LGPR total RMS per 8 km/h".into(),
        points: bins
            .iter()
            .filter(|(_, (_, w))| *w > 0.0)
            .map(|(b, (e, w))| ((*b as f64 + 0.5) * 8.0, 100.0 * (e / w).sqrt()))
            .collect(),
    };
    chart(
        &dir.join("fig15-error-vs-speed.png"),
        "LGPR error vs speed (Fig. 15)",
        "true speed (km/h)",
        "error (cm)",
        &[
            (
                points("LGPR total error", &|s| {
                    (s.speed_mps * 3.6, 100.0 * s.lgpr[0].hypot(s.lgpr[1]))
                }),
                Style::Points,
            ),
            (rms_bins, Style::Lines),
        ],
    )?;
    // Fig. 17: cumulative distribution of |cross| and |along| over distance
    let cdf = |label: &str, pick: fn(&Sample) -> f64| {
        let mut v: Vec<(f64, f64)> = pooled.iter().map(|s| (100.0 * pick(s).abs(), s.weight_m)).collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        let total: f64 = v.iter().map(|x| x.1).sum::<f64>().max(1e-12);
        let mut acc = 0.0;
        Series {
            label: label.into(),
            points: v
                .into_iter()
                .map(|(x, w)| {
                    acc += w;
                    (x, 100.0 * acc / total)
                })
                .collect(),
        }
    };
    chart(
        &dir.join("fig17-error-cdf.png"),
        "Cumulative distribution of LGPR error over distance (Fig. 17)",
        "|error| (cm)",
        "% of distance",
        &[
            (cdf("cross-track", |s| s.lgpr[1]), Style::Lines),
            (cdf("along-track", |s| s.lgpr[0]), Style::Lines),
            (cdf("GPS/INS cross-track", |s| s.gps[1]), Style::Lines),
        ],
    )?;
    chart(
        &dir.join("fig18-error-vs-correlation.png"),
        "Cross-track error vs correlation (Fig. 18)",
        "correlation",
        "|cross-track error| (cm)",
        &[(
            Series {
                label: "LGPR".into(),
                points: pooled
                    .iter()
                    .filter(|s| s.correlation.is_finite())
                    .map(|s| (s.correlation, 100.0 * s.lgpr[1].abs()))
                    .collect(),
            },
            Style::Points,
        )],
    )?;
    chart(
        &dir.join("fig19-error-vs-offset.png"),
        "Error vs lateral offset from the mapping pass (Fig. 19)",
        "lateral offset (m)",
        "|error| (cm)",
        &[
            (
                points("cross-track", &|s| (s.offset_m, 100.0 * s.lgpr[1].abs())),
                Style::Points,
            ),
            (
                points("along-track", &|s| (s.offset_m, 100.0 * s.lgpr[0].abs())),
                Style::Points,
            ),
        ],
    )?;
    Ok(())
}
