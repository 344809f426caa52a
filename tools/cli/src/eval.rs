//! `gprflow eval`: a recorded run's accuracy against the truth, and `gprflow convert --to tum`.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::eval::diagnostics::{AttemptReport, CheckReport, attempt_report, check_report};
use gprflow::eval::messages::{
    LINE_MATCH_GATE_M, LineObservationError, RegistrationError, line_observation_error, registration_error,
};
use gprflow::eval::{self, PoseTopicKind, Stats, Trajectory, pose_topics};
use gprflow::msg::{HoughLine, LineMap};
use gprflow::record::Recording;
use serde::Serialize;

/// The topic the simulator writes ground truth to.
pub const TRUTH_TOPIC: &str = "/truth/pose";
const TRUTH_LINES_TOPIC: &str = "/truth/lines";
/// A registration attempt's shift within this of the truth is right, m (the learned
/// model's registration error is a few cm).
const ATTEMPT_TOLERANCE_M: f64 = 0.05;
/// A registration the estimator checked is right within this of the truth, m.
const CHECK_TOLERANCE_M: f64 = 0.1;

/// Output formats of reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ReportFormat {
    /// Aligned text for a terminal.
    Text,
    /// A Markdown table.
    Markdown,
    /// JSON.
    Json,
}

/// Arguments of `gprflow eval`.
#[derive(Debug, Clone)]
pub struct EvalArgs {
    /// The run to evaluate.
    pub run: PathBuf,
    /// Recording with the ground truth (default: the run itself).
    pub truth: Option<PathBuf>,
    /// Estimate topic (default: chosen from the run's pose topics).
    pub topic: Option<String>,
    /// Truth topic.
    pub truth_topic: String,
    /// RPE frame distance.
    pub delta: usize,
    /// Longest truth gap to interpolate over, ms.
    pub max_gap_ms: f64,
    /// Output format.
    pub format: ReportFormat,
    /// Also write the associated poses as `PREFIX_est.txt` and `PREFIX_gt.txt` (TUM).
    pub write_tum: Option<PathBuf>,
    /// Also draw trajectories and errors into this PNG.
    pub plot: Option<PathBuf>,
    /// More pose topics of the run to draw (odometry, another estimator).
    pub also: Vec<String>,
    /// Other runs to evaluate and draw beside it, `FILE` or `LABEL=FILE`.
    pub compare: Vec<String>,
}

/// Picks the estimate among a recording's pose topics: the last trajectory snapshot, else
/// per-state estimates, else odometry, else any other pose topic that is not the truth.
fn pick_estimate(rec: &Recording, truth_topic: &str) -> Result<String> {
    let topics = pose_topics(rec);
    let rank = |k: PoseTopicKind| match k {
        PoseTopicKind::Snapshot => 0,
        PoseTopicKind::StateEstimate => 1,
        PoseTopicKind::Odometry => 2,
        PoseTopicKind::PoseStamped => 3,
    };
    topics
        .iter()
        .filter(|(t, _)| t != truth_topic)
        .min_by_key(|(t, k)| (rank(*k), t.clone()))
        .map(|(t, _)| t.clone())
        .with_context(|| {
            format!(
                "{}: no estimate to evaluate (pose topics: {}); name one with --topic",
                rec.path().display(),
                topics.iter().map(|(t, _)| t.as_str()).collect::<Vec<_>>().join(", ")
            )
        })
}

fn last_line_map(rec: &Recording, topic: Option<&str>) -> Option<(String, Vec<HoughLine>)> {
    let mut found: Option<(String, Vec<HoughLine>)> = None;
    rec.scan(|m| {
        let wanted = match topic {
            Some(t) => m.topic == t,
            None => m.msg_type == LineMap::ROS_NAME && m.topic != TRUTH_LINES_TOPIC,
        };
        if wanted && let Ok(map) = gprflow::msg::decode::<LineMap>(m.data) {
            found = Some((m.topic.to_owned(), map.lines));
        }
    });
    found
}

/// What `gprflow eval` reports.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Estimate: file and topic.
    pub estimate: String,
    /// Truth: file and topic.
    pub truth: String,
    /// Estimated poses.
    pub estimate_poses: usize,
    /// Truth poses.
    pub truth_poses: usize,
    /// Poses paired with truth.
    pub associated: usize,
    /// ATE without alignment, m.
    pub ate: Option<Stats>,
    /// ATE after SE(3) alignment, m.
    pub ate_aligned: Option<Stats>,
    /// RPE, translation part, m.
    pub rpe: Option<Stats>,
    /// RPE frame distance.
    pub rpe_delta: usize,
    /// Along-track error in the truth's heading frame (signed), m.
    pub along_track: Option<Stats>,
    /// Cross-track error in the truth's heading frame (signed), m.
    pub cross_track: Option<Stats>,
    /// Registrations against the truth's relative motion.
    pub registration: Option<RegistrationError>,
    /// Hough-line error against the truth's lines.
    pub lines: Option<eval::LineError>,
    /// Line observations (detected hyperbolas) against the truth's poses and lines.
    pub line_observations: Option<LineObservationError>,
    /// The register stage's attempts (its `diagnostics` output), against the truth.
    pub attempts: Option<AttemptReport>,
    /// The estimator's registration checks (its `diagnostics` output), against the truth.
    pub registration_checks: Option<CheckReport>,
    /// The runs given with `--compare`, evaluated alike.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub compared: Vec<Compared>,
}

/// A run evaluated beside the main one (`--compare`).
#[derive(Debug, Clone, Serialize)]
pub struct Compared {
    /// Its label (the file's stem unless given).
    pub label: String,
    /// Its report.
    pub report: EvalReport,
}

/// What one run's evaluation leaves for the pictures.
struct Drawn {
    topic: String,
    /// The run's last line map and the truth's lines.
    lines: crate::plot::Lines,
    truth: Trajectory,
    associated: eval::Associated,
    along: Vec<f64>,
    cross: Vec<f64>,
}

/// `LABEL=FILE` or `FILE` (labelled by its stem).
fn compare_spec(spec: &str) -> (String, PathBuf) {
    match spec.split_once('=') {
        Some((label, file)) if !label.is_empty() && !label.contains('/') => (label.to_owned(), PathBuf::from(file)),
        _ => {
            let path = PathBuf::from(spec);
            let label = path
                .file_stem()
                .map_or_else(|| spec.to_owned(), |s| s.to_string_lossy().into_owned());
            (label, path)
        }
    }
}

pub(crate) fn topic_name(t: &str) -> String {
    format!("/{}", t.trim_start_matches('/'))
}

/// Evaluates a run against ground truth, and the runs to compare it with; draws them when
/// asked.
///
/// # Errors
/// Unreadable recordings, missing topics (named), no overlap with the truth, unwritable
/// pictures.
pub fn evaluate(args: &EvalArgs) -> Result<EvalReport> {
    let (mut report, drawn) = evaluate_one(args)?;
    let mut others = Vec::with_capacity(args.compare.len());
    for spec in &args.compare {
        let (label, run) = compare_spec(spec);
        let one = EvalArgs {
            run,
            topic: None,
            write_tum: None,
            plot: None,
            also: Vec::new(),
            compare: Vec::new(),
            ..args.clone()
        };
        let (r, d) = evaluate_one(&one).with_context(|| format!("--compare {spec}"))?;
        report.compared.push(Compared {
            label: label.clone(),
            report: r,
        });
        others.push((label, d));
    }
    if let Some(png) = &args.plot {
        draw(args, png, &report, &drawn, &others)?;
    }
    Ok(report)
}

/// Draws the run (and the compared ones) into `png`, and next to it `STEM-registration.png`
/// and `STEM-lines.png` when the runs hold registrations or line observations.
fn draw(args: &EvalArgs, png: &Path, report: &EvalReport, main: &Drawn, others: &[(String, Drawn)]) -> Result<()> {
    let truth_topic = topic_name(&args.truth_topic);
    let xy = |poses: &[gprflow::eval::Pose]| -> Vec<(f64, f64)> {
        poses
            .iter()
            .map(|p| (p.translation.vector.x, p.translation.vector.y))
            .collect()
    };
    let t0 = main.associated.stamps_ns[0];
    let seconds = |stamps: &[i64]| -> Vec<f64> { stamps.iter().map(|s| (s - t0) as f64 * 1e-9).collect() };
    let track = |label: String, d: &Drawn| crate::plot::RunTrack {
        label,
        xy: xy(&d.associated.estimate),
        truth_xy: xy(&d.associated.truth),
        seconds: seconds(&d.associated.stamps_ns),
    };
    let main_label = args.run.file_stem().map_or_else(
        || main.topic.clone(),
        |s| format!("{} {}", s.to_string_lossy(), main.topic),
    );
    let mut runs = vec![track(main_label.clone(), main)];
    runs.extend(others.iter().map(|(label, d)| track(format!("{label} {}", d.topic), d)));
    let mut extra = Vec::new();
    if !args.also.is_empty() {
        let run = Recording::open(&args.run)?;
        for topic in &args.also {
            let t = Trajectory::from_recording(&run, &topic_name(topic))?;
            extra.push(crate::plot::Series {
                label: topic_name(topic),
                points: xy(&t.poses),
            });
        }
    }
    let main_seconds = seconds(&main.associated.stamps_ns);
    let over_time = |label: &str, v: &[f64]| crate::plot::Series {
        label: format!("{label} of {main_label}"),
        points: main_seconds.iter().copied().zip(v.iter().copied()).collect(),
    };
    crate::plot::trajectory_figure(
        png,
        &crate::plot::TrajectoryFigure {
            title: &format!("{} against the truth {truth_topic}", args.run.display()),
            truth: crate::plot::Series {
                label: format!("truth {truth_topic}"),
                points: xy(&main.truth.poses),
            },
            runs,
            extra,
            along_cross: Some((
                over_time("along track", &main.along),
                over_time("cross track", &main.cross),
            )),
            lines: main.lines.clone(),
        },
    )?;
    // registrations and line observations, each run's as one series
    let mut reports: Vec<(&str, &EvalReport)> = vec![(&main_label, report)];
    reports.extend(report.compared.iter().map(|c| (c.label.as_str(), &c.report)));
    type Samples<'r> = Option<&'r [(i64, f64)]>;
    let series = |pick: &dyn Fn(&EvalReport) -> Samples<'_>| -> Vec<crate::plot::Series> {
        reports
            .iter()
            .filter_map(|(label, r)| {
                let samples = pick(r).filter(|s| !s.is_empty())?;
                Some(crate::plot::Series {
                    label: (*label).to_owned(),
                    points: samples.iter().map(|&(t, e)| ((t - t0) as f64 * 1e-9, e)).collect(),
                })
            })
            .collect()
    };
    let beside = |suffix: &str| {
        let stem = png
            .file_stem()
            .map_or_else(String::new, |s| s.to_string_lossy().into_owned());
        png.with_file_name(format!("{stem}-{suffix}.png"))
    };
    let registrations = series(&|r| r.registration.as_ref().map(|g| g.samples.as_slice()));
    if !registrations.is_empty() {
        crate::plot::error_figure(
            &beside("registration"),
            "registrations against the truth's relative motion",
            "along-track error (m)",
            &registrations,
        )?;
    }
    let observations = series(&|r| r.line_observations.as_ref().map(|o| o.samples.as_slice()));
    if !observations.is_empty() {
        crate::plot::error_figure(
            &beside("lines"),
            "line observations against the true lines",
            "forward-distance error (m)",
            &observations,
        )?;
    }
    Ok(())
}

/// Evaluates one run.
fn evaluate_one(args: &EvalArgs) -> Result<(EvalReport, Drawn)> {
    let run = Recording::open(&args.run)?;
    let truth_rec = match &args.truth {
        Some(p) => Recording::open(p)?,
        None => Recording::open(&args.run)?,
    };
    let truth_topic = topic_name(&args.truth_topic);
    let topic = match &args.topic {
        Some(t) => topic_name(t),
        None => pick_estimate(&run, &truth_topic)?,
    };
    let estimate = Trajectory::from_recording(&run, &topic)?;
    let truth = Trajectory::from_recording(&truth_rec, &truth_topic)
        .with_context(|| format!("{}: no ground truth on {truth_topic}", truth_rec.path().display()))?;
    let max_gap_ns = (args.max_gap_ms * 1e6) as i64;
    let a = eval::associate(&estimate, &truth, max_gap_ns);
    if a.stamps_ns.is_empty() {
        bail!(
            "{} {topic}: none of its {} poses falls inside the truth's time span ({} poses on {truth_topic})",
            args.run.display(),
            estimate.len(),
            truth.len()
        );
    }
    if let Some(prefix) = &args.write_tum {
        for (suffix, poses) in [("_est.txt", &a.estimate), ("_gt.txt", &a.truth)] {
            let path = PathBuf::from(format!("{}{suffix}", prefix.display()));
            let t = Trajectory {
                stamps_ns: a.stamps_ns.clone(),
                poses: poses.clone(),
            };
            std::fs::write(&path, eval::write_tum(&t)).with_context(|| format!("{}: cannot write", path.display()))?;
        }
    }
    let true_lines = last_line_map(&truth_rec, Some(TRUTH_LINES_TOPIC));
    let estimated_lines = last_line_map(&run, None);
    let lines = match (&estimated_lines, &true_lines) {
        (Some((_, est)), Some((_, tru))) => eval::line_error(est, tru),
        _ => None,
    };
    let hough = |m: &Option<(String, Vec<HoughLine>)>| {
        m.as_ref()
            .map(|(_, l)| l.iter().map(|h| (h.rho_m, h.theta_rad)).collect())
            .unwrap_or_default()
    };
    let drawn_lines = crate::plot::Lines {
        truth: hough(&true_lines),
        estimate: hough(&estimated_lines),
    };
    let (along, cross) = eval::track_errors(&a);
    let registration = registration_error(&run, &truth, max_gap_ns);
    let line_observations = true_lines
        .as_ref()
        .and_then(|(_, l)| line_observation_error(&run, &truth, l, max_gap_ns));
    let report = EvalReport {
        estimate: format!("{} {topic}", args.run.display()),
        truth: format!("{} {truth_topic}", truth_rec.path().display()),
        estimate_poses: estimate.len(),
        truth_poses: truth.len(),
        associated: a.stamps_ns.len(),
        ate: eval::ate(&a, false),
        ate_aligned: eval::ate(&a, true),
        rpe: eval::rpe(&a, args.delta),
        rpe_delta: args.delta,
        along_track: Stats::of(&along),
        cross_track: Stats::of(&cross),
        registration,
        lines,
        line_observations,
        attempts: attempt_report(&run, &truth, max_gap_ns, ATTEMPT_TOLERANCE_M),
        registration_checks: check_report(&run, &truth, max_gap_ns, CHECK_TOLERANCE_M),
        compared: Vec::new(),
    };
    Ok((
        report,
        Drawn {
            topic,
            lines: drawn_lines,
            truth,
            associated: a,
            along,
            cross,
        },
    ))
}

/// The diagnostics topics' summaries, as text lines (the same in both formats).
fn diagnostics_summary(r: &EvalReport) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(a) = &r.attempts {
        lines.push(format!(
            "registration attempts on {} (a shift within {} m of the truth is right):",
            a.topic, a.tolerance_m
        ));
        for row in &a.rows {
            lines.push(format!(
                "  {:<40} {:>6} pairs, {:>6} with a shift, {:>6} right",
                row.label, row.pairs, row.with_shift, row.right
            ));
        }
    }
    if let Some(c) = &r.registration_checks {
        lines.push(format!(
            "registration checks on {} (right within {} m): accepted {} ({} right, {} wrong), gated {} ({} right, {} wrong)",
            c.topic,
            c.tolerance_m,
            c.accepted.count,
            c.accepted.right,
            c.accepted.wrong,
            c.gated.count,
            c.gated.right,
            c.gated.wrong
        ));
        let bases: Vec<String> = c
            .gate_bases
            .iter()
            .map(|g| format!("{:.3} m at {} m/s", g.base_m, g.growth_mps))
            .collect();
        lines.push(format!("  smallest gate keeping every right one: {}", bases.join(", ")));
        if let Some(k) = c.right_sigmas_max {
            let wrong = match c.wrong_sigmas.first() {
                Some(w) => format!("; the wrong ones from {w:.2} sigma down"),
                None => String::new(),
            };
            lines.push(format!(
                "  smallest Mahalanobis gate keeping every right one: {k:.2} sigma{wrong}"
            ));
        }
    }
    lines
}

fn line_observation_summary(o: &LineObservationError) -> String {
    let error = o.forward_distance.as_ref().map_or(String::new(), |s| {
        format!(", forward-distance error RMSE {:.4} m, mean {:+.4} m", s.rmse, s.mean)
    });
    format!(
        "line observations on {}: {} of {} on a true line (within {LINE_MATCH_GATE_M} m), {} not{error}",
        o.topic, o.matched, o.observations, o.unmatched
    )
}

fn stats_row(name: &str, s: &Option<Stats>, markdown: bool) -> String {
    match s {
        Some(s) if markdown => format!(
            "| {name} | {:.4} | {:.4} | {:.4} | {:.4} | {} |",
            s.rmse, s.mean, s.median, s.max, s.count
        ),
        Some(s) => format!(
            "{name:<28} {:>9.4} {:>9.4} {:>9.4} {:>9.4} {:>7}",
            s.rmse, s.mean, s.median, s.max, s.count
        ),
        None if markdown => format!("| {name} | - | - | - | - | 0 |"),
        None => format!("{name:<28} {:>9}", "-"),
    }
}

/// The main run and the compared ones, labelled, for the comparison table.
fn compared_rows(r: &EvalReport) -> Vec<(String, &EvalReport)> {
    let main = Path::new(r.estimate.split(' ').next().unwrap_or_default())
        .file_stem()
        .map_or_else(|| "run".to_owned(), |s| s.to_string_lossy().into_owned());
    std::iter::once((main, r))
        .chain(r.compared.iter().map(|c| (c.label.clone(), &c.report)))
        .collect()
}

/// The RMSE of a report's ATE, aligned ATE, along- and cross-track error, `-` where absent.
fn rmse_cells(r: &EvalReport) -> [String; 4] {
    [&r.ate, &r.ate_aligned, &r.along_track, &r.cross_track]
        .map(|s| s.as_ref().map_or("-".to_owned(), |s| format!("{:.4}", s.rmse)))
}

/// Runs `gprflow eval`.
///
/// # Errors
/// As [`evaluate`].
pub fn eval_command(args: &EvalArgs) -> Result<ExitCode> {
    let r = evaluate(args)?;
    let mut out = std::io::stdout().lock();
    let rpe_name = format!("RPE (delta {} frames)", r.rpe_delta);
    match args.format {
        ReportFormat::Json => writeln!(out, "{}", serde_json::to_string_pretty(&r)?)?,
        ReportFormat::Markdown => {
            writeln!(
                out,
                "Estimate `{}` against `{}`: {} of {} poses associated.\n",
                r.estimate, r.truth, r.associated, r.estimate_poses
            )?;
            writeln!(
                out,
                "| metric (m) | RMSE | mean | median | max | n |\n|---|---:|---:|---:|---:|---:|"
            )?;
            writeln!(out, "{}", stats_row("ATE", &r.ate, true))?;
            writeln!(out, "{}", stats_row("ATE, SE(3) aligned", &r.ate_aligned, true))?;
            writeln!(out, "{}", stats_row(&rpe_name, &r.rpe, true))?;
            writeln!(out, "{}", stats_row("along-track error", &r.along_track, true))?;
            writeln!(out, "{}", stats_row("cross-track error", &r.cross_track, true))?;
            if let Some(g) = &r.registration {
                writeln!(
                    out,
                    "{}",
                    stats_row("registration, along track", &Some(g.along_track), true)
                )?;
                writeln!(
                    out,
                    "{}",
                    stats_row("registration, translation", &Some(g.translation), true)
                )?;
            }
            if let Some(l) = r.lines {
                writeln!(
                    out,
                    "\nLines ({} matched): rho RMSE {:.4} m, theta RMSE {:.4} rad",
                    l.matched, l.rho_rmse_m, l.theta_rmse_rad
                )?;
            }
            if let Some(o) = &r.line_observations {
                writeln!(out, "\n{}", line_observation_summary(o))?;
            }
            let diagnostics = diagnostics_summary(&r);
            if !diagnostics.is_empty() {
                writeln!(out, "\n```\n{}\n```", diagnostics.join("\n"))?;
            }
            if !r.compared.is_empty() {
                writeln!(
                    out,
                    "\n| run | ATE RMSE (m) | ATE aligned RMSE (m) | along-track RMSE (m) | cross-track RMSE (m) |\n|---|---:|---:|---:|---:|"
                )?;
                for (label, c) in compared_rows(&r) {
                    let [ate, aligned, along, cross] = rmse_cells(c);
                    writeln!(out, "| {label} | {ate} | {aligned} | {along} | {cross} |")?;
                }
            }
        }
        ReportFormat::Text => {
            writeln!(out, "estimate  {} ({} poses)", r.estimate, r.estimate_poses)?;
            writeln!(out, "truth     {} ({} poses)", r.truth, r.truth_poses)?;
            writeln!(out, "associated {}\n", r.associated)?;
            writeln!(
                out,
                "{:<28} {:>9} {:>9} {:>9} {:>9} {:>7}",
                "metric (m)", "rmse", "mean", "median", "max", "n"
            )?;
            writeln!(out, "{}", stats_row("ATE", &r.ate, false))?;
            writeln!(out, "{}", stats_row("ATE, SE(3) aligned", &r.ate_aligned, false))?;
            writeln!(out, "{}", stats_row(&rpe_name, &r.rpe, false))?;
            writeln!(out, "{}", stats_row("along-track error", &r.along_track, false))?;
            writeln!(out, "{}", stats_row("cross-track error", &r.cross_track, false))?;
            if let Some(g) = &r.registration {
                writeln!(
                    out,
                    "{}",
                    stats_row("registration, along track", &Some(g.along_track), false)
                )?;
                writeln!(
                    out,
                    "{}",
                    stats_row("registration, translation", &Some(g.translation), false)
                )?;
            }
            if let Some(l) = r.lines {
                writeln!(
                    out,
                    "lines ({} matched): rho RMSE {:.4} m, theta RMSE {:.4} rad",
                    l.matched, l.rho_rmse_m, l.theta_rmse_rad
                )?;
            }
            if let Some(o) = &r.line_observations {
                writeln!(out, "{}", line_observation_summary(o))?;
            }
            for line in diagnostics_summary(&r) {
                writeln!(out, "{line}")?;
            }
            if !r.compared.is_empty() {
                writeln!(
                    out,
                    "\n{:<28} {:>9} {:>12} {:>11} {:>11}   (RMSE, m)",
                    "run", "ATE", "ATE aligned", "along", "cross"
                )?;
                for (label, c) in compared_rows(&r) {
                    let [ate, aligned, along, cross] = rmse_cells(c);
                    writeln!(out, "{label:<28} {ate:>9} {aligned:>12} {along:>11} {cross:>11}")?;
                }
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Runs `gprflow convert FILE --to tum -o OUT [--topic T]`.
///
/// # Errors
/// Unreadable recording, missing topic, unwritable output.
pub fn convert_to_tum(input: &Path, topic: Option<&str>, output: &Path) -> Result<ExitCode> {
    let rec = Recording::open(input)?;
    let topic = match topic {
        Some(t) => topic_name(t),
        None => pick_estimate(&rec, "").context("name the topic with --topic")?,
    };
    let t = Trajectory::from_recording(&rec, &topic)?;
    std::fs::write(output, eval::write_tum(&t)).with_context(|| format!("{}: cannot write", output.display()))?;
    writeln!(
        std::io::stdout().lock(),
        "{} poses of {topic} written to {}",
        t.len(),
        output.display()
    )?;
    Ok(ExitCode::SUCCESS)
}
