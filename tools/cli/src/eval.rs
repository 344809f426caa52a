//! `gprflow eval`, `gprflow convert --to tum` and `gprflow diff`.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::diff::{DiffReport, Tolerances, diff_with};
use gprflow::eval::{self, PoseTopicKind, Stats, Trajectory, pose_topics};
use gprflow::msg::{HoughLine, LineMap};
use gprflow::record::Recording;
use serde::Serialize;

/// The topic the simulator writes ground truth to.
pub const TRUTH_TOPIC: &str = "/truth/pose";
const TRUTH_LINES_TOPIC: &str = "/truth/lines";

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
}

/// Line observations against the truth: each forward distance compared with the one from
/// the true pose at its stamp to the nearest true line (eq. 5.6).
#[derive(Debug, Clone, Serialize)]
pub struct LineObservationError {
    /// Topic.
    pub topic: String,
    /// Observations with a true pose at their stamp.
    pub observations: usize,
    /// Within [`LINE_MATCH_GATE_M`] of a true line's forward distance.
    pub matched: usize,
    /// Not near any true line: false detections.
    pub unmatched: usize,
    /// Forward-distance error of the matched ones (observed - true), m.
    pub forward_distance: Option<Stats>,
}

/// An observation within this of a true line's forward distance is a detection of it, m.
pub const LINE_MATCH_GATE_M: f64 = 0.5;

fn line_observation_error(
    run: &Recording,
    truth: &Trajectory,
    true_lines: &[HoughLine],
    max_gap_ns: i64,
) -> Option<LineObservationError> {
    use gprflow::msg::LineObservation;
    let mut topic = None;
    let (mut observations, mut errors) = (0usize, Vec::new());
    run.scan(|m| {
        if m.msg_type != LineObservation::ROS_NAME {
            return;
        }
        let Ok(o) = gprflow::msg::decode::<LineObservation>(m.data) else {
            return;
        };
        topic.get_or_insert_with(|| m.topic.to_owned());
        let Some(pose) = truth.interpolate(o.header.stamp.to_ns(), max_gap_ns) else {
            return;
        };
        observations += 1;
        let (x, y) = (pose.translation.vector.x, pose.translation.vector.y);
        let yaw = pose.rotation.euler_angles().2;
        let nearest = true_lines
            .iter()
            .filter_map(|l| {
                let c = (yaw - l.theta_rad).cos();
                // driving along a line: no forward distance to it
                (c.abs() > 0.05).then(|| {
                    let predicted = (l.rho_m - x * l.theta_rad.cos() - y * l.theta_rad.sin()) / c;
                    o.forward_distance_m - predicted
                })
            })
            .min_by(|a, b| a.abs().total_cmp(&b.abs()));
        if let Some(e) = nearest.filter(|e| e.abs() <= LINE_MATCH_GATE_M) {
            errors.push(e);
        }
    });
    Some(LineObservationError {
        topic: topic?,
        observations,
        matched: errors.len(),
        unmatched: observations - errors.len(),
        forward_distance: Stats::of(&errors),
    })
}

/// Registration error: each `Registration` against the truth's relative pose between its
/// reference and query stamps.
#[derive(Debug, Clone, Serialize)]
pub struct RegistrationError {
    /// Topic.
    pub topic: String,
    /// Along-track error, m.
    pub along_track: Stats,
    /// Error of the full relative translation, m.
    pub translation: Stats,
}

fn registration_error(run: &Recording, truth: &Trajectory, max_gap_ns: i64) -> Option<RegistrationError> {
    use gprflow::msg::Registration;
    let mut topic = String::new();
    let (mut along, mut full) = (Vec::new(), Vec::new());
    run.scan(|m| {
        if m.msg_type != Registration::ROS_NAME {
            return;
        }
        let Ok(r) = gprflow::msg::decode::<Registration>(m.data) else {
            return;
        };
        let (Some(a), Some(b)) = (
            truth.interpolate(r.reference_stamp.to_ns(), max_gap_ns),
            truth.interpolate(r.query_stamp.to_ns(), max_gap_ns),
        ) else {
            return;
        };
        topic = m.topic.to_owned();
        let rel = a.inverse() * b;
        along.push(r.along_track_m - rel.translation.vector.x);
        let p = &r.reference_from_query.position;
        let t = rel.translation.vector;
        full.push(((p.x - t.x).powi(2) + (p.y - t.y).powi(2) + (p.z - t.z).powi(2)).sqrt());
    });
    Some(RegistrationError {
        topic,
        along_track: Stats::of(&along)?,
        translation: Stats::of(&full)?,
    })
}

fn topic_name(t: &str) -> String {
    format!("/{}", t.trim_start_matches('/'))
}

/// Evaluates a run against ground truth.
///
/// # Errors
/// Unreadable recordings, missing topics (named), no overlap with the truth.
pub fn evaluate(args: &EvalArgs) -> Result<EvalReport> {
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
    let a = eval::associate(&estimate, &truth, (args.max_gap_ms * 1e6) as i64);
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
    let lines = match (
        last_line_map(&run, None),
        last_line_map(&truth_rec, Some(TRUTH_LINES_TOPIC)),
    ) {
        (Some((_, est)), Some((_, tru))) => eval::line_error(&est, &tru),
        _ => None,
    };
    let (along, cross) = eval::track_errors(&a);
    let estimated_lines = last_line_map(&run, None);
    let true_lines = last_line_map(&truth_rec, Some(TRUTH_LINES_TOPIC));
    if let Some(png) = &args.plot {
        let hough = |m: &Option<(String, Vec<HoughLine>)>| {
            m.as_ref()
                .map(|(_, l)| l.iter().map(|h| (h.rho_m, h.theta_rad)).collect())
                .unwrap_or_default()
        };
        let plot_lines = crate::plot::Lines {
            truth: hough(&true_lines),
            estimate: hough(&estimated_lines),
        };
        let xy = |poses: &[gprflow::eval::Pose]| {
            poses
                .iter()
                .map(|p| (p.translation.vector.x, p.translation.vector.y))
                .collect()
        };
        let t0 = a.stamps_ns[0];
        let seconds: Vec<f64> = a.stamps_ns.iter().map(|s| (s - t0) as f64 * 1e-9).collect();
        let over_time = |v: Vec<f64>| seconds.iter().copied().zip(v).collect();
        let position_error: Vec<f64> = a
            .estimate
            .iter()
            .zip(&a.truth)
            .map(|(e, t)| (e.translation.vector - t.translation.vector).norm())
            .collect();
        let mut trajectories = vec![
            crate::plot::Series {
                label: format!("truth {truth_topic}"),
                points: xy(&truth.poses),
            },
            crate::plot::Series {
                label: format!("estimate {topic}"),
                points: xy(&a.estimate),
            },
        ];
        for extra in &args.also {
            let t = Trajectory::from_recording(&run, &topic_name(extra))?;
            trajectories.push(crate::plot::Series {
                label: topic_name(extra),
                points: xy(&t.poses),
            });
        }
        crate::plot::trajectory_and_error(
            png,
            &format!("{} against {}", topic, truth_topic),
            &trajectories,
            &plot_lines,
            &[
                crate::plot::Series {
                    label: "position error (3-D)".into(),
                    points: over_time(position_error),
                },
                crate::plot::Series {
                    label: "along track".into(),
                    points: over_time(along.clone()),
                },
                crate::plot::Series {
                    label: "cross track".into(),
                    points: over_time(cross.clone()),
                },
            ],
        )?;
    }
    let registration = registration_error(&run, &truth, (args.max_gap_ms * 1e6) as i64);
    let line_observations = true_lines
        .as_ref()
        .and_then(|(_, l)| line_observation_error(&run, &truth, l, (args.max_gap_ms * 1e6) as i64));
    Ok(EvalReport {
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
    })
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

/// Trajectory comparison between two runs.
#[derive(Debug, Clone, Serialize)]
pub struct TrajectoryDiff {
    /// Topic.
    pub topic: String,
    /// ATE of B against A, m.
    pub b_against_a: Option<Stats>,
    /// ATE of A against truth, m.
    pub a_against_truth: Option<Stats>,
    /// ATE of B against truth, m.
    pub b_against_truth: Option<Stats>,
}

/// Runs `gprflow diff A B`: exit 0 within tolerance, 1 on a regression.
///
/// # Errors
/// Unreadable recordings (the caller exits 2).
pub fn diff_command(a: &Path, b: &Path, tol: &Tolerances, json: bool) -> Result<ExitCode> {
    let (ra, rb) = (Recording::open(a)?, Recording::open(b)?);
    let report = diff_with(&ra, &rb, tol)?;
    // trajectories: every pose topic in both recordings
    let (ta, tb) = (pose_topics(&ra), pose_topics(&rb));
    let truth_a = Trajectory::from_recording(&ra, TRUTH_TOPIC).ok();
    let gap = 200_000_000;
    let mut trajectories = Vec::new();
    for (topic, _) in ta
        .iter()
        .filter(|(t, _)| t != TRUTH_TOPIC && tb.iter().any(|(u, _)| u == t))
    {
        let (Ok(pa), Ok(pb)) = (
            Trajectory::from_recording(&ra, topic),
            Trajectory::from_recording(&rb, topic),
        ) else {
            continue;
        };
        let against = |x: &Trajectory, reference: &Trajectory| eval::ate(&eval::associate(x, reference, gap), false);
        trajectories.push(TrajectoryDiff {
            topic: topic.clone(),
            b_against_a: against(&pb, &pa),
            a_against_truth: truth_a.as_ref().and_then(|t| against(&pa, t)),
            b_against_truth: truth_a.as_ref().and_then(|t| against(&pb, t)),
        });
    }
    let mut out = std::io::stdout().lock();
    if json {
        let v = serde_json::json!({ "a": a, "b": b, "report": report, "trajectories": trajectories });
        writeln!(out, "{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        print_diff(&mut out, a, b, &report, &trajectories)?;
    }
    Ok(if report.regression {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

fn print_diff(
    out: &mut impl std::io::Write,
    a: &Path,
    b: &Path,
    r: &DiffReport,
    trajectories: &[TrajectoryDiff],
) -> std::io::Result<()> {
    writeln!(out, "A = {}\nB = {}\n", a.display(), b.display())?;
    writeln!(out, "{:<34} {:>9} {:>9} {:>10}", "topic", "A", "B", "differing")?;
    for t in &r.topics {
        let mark = if t.count_a != t.count_b || t.type_a != t.type_b {
            "  <-"
        } else {
            ""
        };
        writeln!(
            out,
            "{:<34} {:>9} {:>9} {:>10}{mark}",
            t.topic, t.count_a, t.count_b, t.differing_messages
        )?;
        if t.type_a != t.type_b {
            writeln!(out, "    type: {} vs {}", t.type_a, t.type_b)?;
        }
        for (path, s) in &t.fields {
            writeln!(
                out,
                "    {path:<30} max |a-b| {:.3e}  max rel {:.3e}  beyond tolerance {}",
                s.max_abs, s.max_rel, s.beyond_tolerance
            )?;
        }
        for (path, n) in &t.structural {
            writeln!(out, "    {path:<30} differs in {n} message(s)")?;
        }
    }
    if let Some(d) = &r.first_divergence {
        writeln!(
            out,
            "\nfirst divergence: {} message {} (seq {}, stamp {} ns) at `{}`: A = {} B = {}",
            d.topic, d.index, d.seq, d.stamp_ns, d.path, d.a, d.b
        )?;
    }
    for t in trajectories {
        let f = |s: &Option<Stats>| s.map_or("-".to_owned(), |s| format!("{:.4} m", s.rmse));
        writeln!(
            out,
            "trajectory {}: ATE B vs A {}, A vs truth {}, B vs truth {}",
            t.topic,
            f(&t.b_against_a),
            f(&t.a_against_truth),
            f(&t.b_against_truth)
        )?;
    }
    for (k, (va, vb)) in &r.metadata {
        writeln!(out, "metadata {k}: {va:?} vs {vb:?}")?;
    }
    for n in &r.attachments {
        writeln!(out, "attachment {n} differs")?;
    }
    writeln!(
        out,
        "\n{}",
        if r.regression { "REGRESSION" } else { "within tolerance" }
    )
}

/// What `gprflow radargram` draws.
#[derive(Debug, Clone)]
pub struct RadargramRequest<'a> {
    /// Recording or radar file.
    pub input: &'a Path,
    /// Trace, sweep or submap topic.
    pub topic: &'a str,
    /// Seconds after the first trace: from, to.
    pub window_s: (f64, Option<f64>),
    /// Submap topics: the id to draw (default the most salient).
    pub submap: Option<u32>,
    /// Line observations to draw over it: a topic, or `None` for the recording's first
    /// `LineObservation` topic if any.
    pub features: Option<&'a str>,
    /// Draw no features.
    pub no_features: bool,
    /// PNG to write.
    pub output: &'a Path,
}

/// Where a submap lies along track, for placing features on it.
#[derive(Debug, Clone, Copy)]
struct SubmapFrame {
    start_distance_m: f64,
    end_distance_m: f64,
    resolution_m: f64,
    sample_interval_ns: f64,
    cols: usize,
    rows: usize,
}

impl SubmapFrame {
    /// The observation drawn on this submap, when its apex lies inside.
    fn feature(&self, o: &gprflow::msg::LineObservation) -> Option<crate::plot::Feature> {
        let span = self.end_distance_m - self.start_distance_m;
        if span == 0.0 || self.cols < 2 {
            return None;
        }
        let c = (o.along_distance_m - self.start_distance_m) / span * (self.cols - 1) as f64;
        if !(0.0..=(self.cols - 1) as f64).contains(&c) {
            return None;
        }
        let row = |col: f64| {
            let dx_m = (col - c) * self.resolution_m;
            o.apex_time_ns.hypot(2.0 * dx_m / o.velocity_m_per_ns) / self.sample_interval_ns
        };
        let curve = (0..self.cols)
            .map(|j| (j as f64, row(j as f64)))
            .filter(|&(_, r)| r < self.rows as f64)
            .collect();
        Some(crate::plot::Feature {
            apex: (c, o.apex_time_ns / self.sample_interval_ns),
            curve,
            label: format!("line {}", o.line_id),
        })
    }
}

/// The observation drawn on trace columns stamped `stamps_ns` (with wheel distances
/// `distances_m` and sample interval `dt_ns`), when its apex falls between them.
fn trace_feature(
    o: &gprflow::msg::LineObservation,
    stamps_ns: &[i64],
    distances_m: &[f64],
    dt_ns: f64,
) -> Option<crate::plot::Feature> {
    let apex_ns = o.apex_stamp.to_ns();
    let (first, last) = (*stamps_ns.first()?, *stamps_ns.last()?);
    if apex_ns < first || apex_ns > last || dt_ns.is_nan() || dt_ns <= 0.0 {
        return None;
    }
    let col = stamps_ns.partition_point(|&t| t < apex_ns).min(stamps_ns.len() - 1);
    let d0 = distances_m[col];
    let moving = distances_m.iter().any(|&d| d != d0);
    let curve = if moving && o.velocity_m_per_ns > 0.0 {
        distances_m
            .iter()
            .enumerate()
            .map(|(j, d)| {
                (
                    j as f64,
                    o.apex_time_ns.hypot(2.0 * (d - d0) / o.velocity_m_per_ns) / dt_ns,
                )
            })
            .filter(|&(j, r)| (j - col as f64).abs() < 400.0 && r < 4096.0)
            .collect()
    } else {
        Vec::new()
    };
    Some(crate::plot::Feature {
        apex: (col as f64, o.apex_time_ns / dt_ns),
        curve,
        label: format!("line {}", o.line_id),
    })
}

/// Runs `gprflow radargram REC -o OUT.png`: the traces of `topic` between `from_s` and
/// `to_s` seconds after the first one, or one submap, as a picture; with the recording's
/// line observations (detected hyperbolas) drawn over it.
///
/// # Errors
/// Unreadable recording, no traces on the topic, unwritable output.
pub fn radargram_command(req: &RadargramRequest<'_>) -> Result<ExitCode> {
    use gprflow::msg::{LineObservation, Message, Samples, Submap, Sweep, Trace};
    let RadargramRequest {
        input,
        topic,
        window_s: (from_s, to_s),
        submap,
        output,
        ..
    } = *req;
    let as_columns = |trace: &Trace<'_>| -> Vec<f32> {
        match trace.samples() {
            Samples::I16(s) => s.iter().map(|&v| f32::from(v)).collect(),
            Samples::I32(s) => s.iter().map(|&v| v as f32).collect(),
            Samples::F32(s) => s.to_vec(),
        }
    };
    let is_recording = input.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
    let mut traces = Vec::new();
    let topic = topic_name(topic);
    let mut what = topic.clone();
    // line observations to draw, and what places them: the submap drawn or the traces' stamps
    let mut features_topic: Option<String> = None;
    let mut observations: Vec<LineObservation> = Vec::new();
    let mut frame: Option<SubmapFrame> = None;
    let (mut stamps_ns, mut distances_m, mut sample_interval_ns) = (Vec::new(), Vec::new(), 0.0);
    if !is_recording {
        // a radar file: its traces, as the ingest stage reads them
        let params = crate::convert::ingest_params(input, gprflow_ingest::node::SourceFormat::Auto);
        let loaded =
            gprflow_ingest::node::load(&params).with_context(|| format!("{}: cannot read", input.display()))?;
        let first = loaded.messages.first().map_or(0, |m| m.1);
        for (port, stamp, data) in &loaded.messages {
            let t = (stamp - first) as f64 * 1e-9;
            if *port != gprflow_ingest::node::Port::Gpr || t < from_s || to_s.is_some_and(|end| t > end) {
                continue;
            }
            let trace: Trace = gprflow::msg::decode(data)?;
            traces.push(as_columns(&trace));
        }
        what = "traces".into();
    } else {
        let rec = Recording::open(input)?;
        let topics = rec.topics();
        let ty = topics.iter().find(|(t, _)| *t == topic).map(|(_, ty)| ty.clone());
        features_topic = match (req.no_features, req.features) {
            (true, _) => None,
            (false, Some(f)) => {
                let f = topic_name(f);
                if !topics.iter().any(|(t, ty)| *t == f && ty == LineObservation::TYPE_NAME) {
                    bail!("{}: no {} topic `{f}`", input.display(), LineObservation::TYPE_NAME);
                }
                Some(f)
            }
            (false, None) => topics
                .iter()
                .find(|(_, ty)| ty == LineObservation::TYPE_NAME)
                .map(|(t, _)| t.clone()),
        };
        let mut first: Option<u64> = None;
        let mut failure = None;
        let mut best: Option<(f32, u32, Vec<Vec<f32>>)> = None;
        let is_submap = ty.as_deref() == Some(Submap::TYPE_NAME);
        let is_sweep = ty.as_deref() == Some(Sweep::TYPE_NAME);
        rec.scan(|m| {
            if failure.is_some() {
                return;
            }
            if features_topic.as_deref() == Some(m.topic) {
                match gprflow::msg::decode::<LineObservation>(m.data) {
                    Ok(o) => observations.push(o),
                    Err(e) => failure = Some(format!("{}: {} seq {}: {e}", input.display(), m.topic, m.sequence)),
                }
                return;
            }
            if m.topic != topic {
                return;
            }
            if is_submap {
                match gprflow::msg::decode::<Submap>(m.data) {
                    Ok(s) => {
                        let wanted = match submap {
                            Some(id) => s.id == id,
                            None => best.as_ref().is_none_or(|b| s.saliency > b.0),
                        };
                        if wanted {
                            let (rows, cols) = (s.rows as usize, s.cols as usize);
                            frame = Some(SubmapFrame {
                                start_distance_m: s.start_distance_m,
                                end_distance_m: s.end_distance_m,
                                resolution_m: s.resolution_m,
                                sample_interval_ns: s.sample_interval_ns,
                                cols,
                                rows,
                            });
                            let columns = (0..cols)
                                .map(|c| {
                                    (0..rows)
                                        .map(|r| s.pixels.get(r * cols + c).copied().unwrap_or(0.0))
                                        .collect()
                                })
                                .collect();
                            best = Some((s.saliency, s.id, columns));
                        }
                    }
                    Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
                }
                return;
            }
            let t0 = *first.get_or_insert(m.log_time);
            let t = (m.log_time - t0) as f64 * 1e-9;
            if t < from_s || to_s.is_some_and(|end| t > end) {
                return;
            }
            if is_sweep {
                // time-domain sweeps: the middle channel
                match gprflow::msg::decode::<Sweep>(m.data) {
                    Ok(s) if s.domain == Sweep::DOMAIN_TIME && s.channel_count > 0 => {
                        let n = s.bin_count as usize;
                        let ch = s.channel_count as usize / 2;
                        traces.push(
                            s.values
                                .get(ch * n..(ch + 1) * n)
                                .map(<[f32]>::to_vec)
                                .unwrap_or_default(),
                        );
                    }
                    Ok(_) => {
                        failure = Some(format!(
                            "{}: {topic}: frequency-domain sweeps (run them through lgpr_dsp first)",
                            input.display()
                        ))
                    }
                    Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
                }
                return;
            }
            match gprflow::msg::decode::<Trace>(m.data) {
                Ok(trace) => {
                    stamps_ns.push(trace.header.stamp.to_ns());
                    distances_m.push(trace.distance_m);
                    sample_interval_ns = trace.sample_interval_ns;
                    traces.push(as_columns(&trace));
                }
                Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
            }
        });
        if let Some(f) = failure {
            bail!(f);
        }
        if is_submap {
            let Some((saliency, id, columns)) = best else {
                bail!(
                    "{}: no submap{} on {topic}",
                    input.display(),
                    submap.map(|i| format!(" with id {i}")).unwrap_or_default()
                );
            };
            traces = columns;
            what = format!("submap {id} (saliency {saliency:.3}) of {topic}");
        }
    }
    if traces.is_empty() {
        bail!("{}: no traces on {topic} in that time window", input.display());
    }
    let features: Vec<crate::plot::Feature> = match frame {
        Some(f) => observations.iter().filter_map(|o| f.feature(o)).collect(),
        None if stamps_ns.len() == traces.len() => observations
            .iter()
            .filter_map(|o| trace_feature(o, &stamps_ns, &distances_m, sample_interval_ns))
            .collect(),
        None => Vec::new(),
    };
    // a submap is small: three pixels per value
    crate::plot::radargram(output, &traces, &features, if frame.is_some() { 3 } else { 1 })?;
    let drawn = match &features_topic {
        Some(t) => format!(" with {} line observations of {t}", features.len()),
        None => String::new(),
    };
    writeln!(
        std::io::stdout().lock(),
        "{} columns of {what}{drawn} drawn to {}",
        traces.len(),
        output.display()
    )?;
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gprflow::msg::{Header, Point, Pose, PoseStamped, Quaternion, Registration, Time};
    use gprflow::record::{Recorder, RunMetadata};

    fn pose(x: f64) -> Pose {
        Pose {
            position: Point { x, y: 0.0, z: 0.0 },
            orientation: Quaternion {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 1.0,
            },
        }
    }

    #[test]
    fn registrations_are_checked_against_the_truth_motion() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("r.mcap");
        let mut rec = Recorder::create(&path, &RunMetadata::this_build()).expect("create");
        let truth = rec.add_topic("truth/pose", PoseStamped::ROS_NAME).expect("topic");
        let regs = rec
            .add_topic("register/registration", Registration::ROS_NAME)
            .expect("topic");
        let s = 1_000_000_000i64;
        for i in 0..=10 {
            let m = PoseStamped {
                header: Header::new(i * s, "world"),
                pose: pose(i as f64), // 1 m/s along x
            };
            rec.write(truth, i as u64, i * s, &gprflow::msg::encode(&m))
                .expect("write");
        }
        for (k, (from, to, measured)) in [(2, 5, 3.1), (1, 9, 7.7)].into_iter().enumerate() {
            let r = Registration {
                header: Header::new(to * s, "base_link"),
                reference_submap: k as u32,
                query_submap: 100,
                reference_stamp: Time::from_ns(from * s),
                query_stamp: Time::from_ns(to * s),
                reference_from_query: pose(measured),
                covariance: gprflow::msg::Covariance6([0.0; 36]),
                along_track_m: measured,
                along_track_variance_m2: 0.01,
                score: 1.0,
                method: "test".into(),
            };
            rec.write(regs, k as u64, to * s, &gprflow::msg::encode(&r))
                .expect("write");
        }
        rec.finish().expect("finish");
        let run = Recording::open(&path).expect("open");
        let t = Trajectory::from_recording(&run, TRUTH_TOPIC).expect("truth");
        let e = registration_error(&run, &t, 2 * s).expect("registrations");
        assert_eq!(e.topic, "/register/registration");
        assert_eq!(e.along_track.count, 2);
        // errors +0.1 and -0.3
        assert!(
            (e.along_track.rmse - (0.05f64).sqrt()).abs() < 1e-9,
            "{:?}",
            e.along_track
        );
        assert!((e.along_track.mean + 0.1).abs() < 1e-9);
    }
}
