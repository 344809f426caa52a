//! `gprflow diff`: two recorded runs compared for regression, and two trajectories.

use std::io::Write as _;
use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use gprflow::diff::{DiffReport, Tolerances, diff_with};
use gprflow::eval::{self, Stats, Trajectory, pose_topics};
use gprflow::record::Recording;
use serde::Serialize;

use crate::eval::TRUTH_TOPIC;

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
