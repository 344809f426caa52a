//! The stages' diagnostics topics against the truth: the register stage's attempts (every
//! candidate pair, registered or refused and why) and the estimator's registration checks
//! (taken, or dropped by its gate, with the residual). They answer "were the refusals
//! right?" and "which gate keeps every right registration?" from recorded data.

use gprflow_msg::{self as msg, RegistrationAttempt, RegistrationCheck};
use gprflow_record::Recording;
use serde::Serialize;

use crate::Trajectory;

/// Gate growth rates (m/s) for which [`CheckReport::gate_bases`] gives the smallest base.
pub const GATE_GROWTH_RATES_MPS: [f64; 4] = [0.0, 0.005, 0.01, 0.02];

/// The truth's along-track and across-track offset (m) of `query_ns` from `reference_ns`
/// in the reference's frame, and the heading difference (deg, absolute).
fn truth_offset(truth: &Trajectory, reference_ns: i64, query_ns: i64, max_gap_ns: i64) -> Option<(f64, f64, f64)> {
    let a = truth.interpolate(reference_ns, max_gap_ns)?;
    let b = truth.interpolate(query_ns, max_gap_ns)?;
    let rel = a.inverse() * b;
    let heading = rel.rotation.euler_angles().2.to_degrees().abs();
    Some((rel.translation.vector.x, rel.translation.vector.y, heading))
}

/// Pairs of one kind and how many of them had a shift within the tolerance of the truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AttemptRow {
    /// An outcome (`registered`, a refusal reason), or a bin of the refused pairs
    /// (`refused, across-track 0-0.05 m`).
    pub label: String,
    /// Pairs with the truth at both anchors.
    pub pairs: u64,
    /// Of them, those whose method found a shift.
    pub with_shift: u64,
    /// Of those, the shifts within the tolerance of the truth's along-track offset.
    pub right: u64,
}

/// The register stage's attempts against the truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AttemptReport {
    /// Topic.
    pub topic: String,
    /// A shift within this of the truth is right, m.
    pub tolerance_m: f64,
    /// Per outcome, then the refused pairs binned by across-track offset and heading
    /// difference (the conditions a refusal is meant to catch).
    pub rows: Vec<AttemptRow>,
}

/// One attempt with the truth's offsets between its anchors.
struct Tried {
    outcome: String,
    shift_m: f64,
    along: f64,
    across: f64,
    heading: f64,
}

const ACROSS_BINS_M: [f64; 5] = [0.0, 0.05, 0.1, 0.2, f64::INFINITY];
const HEADING_BINS_DEG: [f64; 5] = [0.0, 2.0, 4.0, 8.0, f64::INFINITY];

/// The attempts recorded in `run` against the truth; `None` when the run has no attempt
/// with the truth at both anchors.
pub fn attempt_report(run: &Recording, truth: &Trajectory, max_gap_ns: i64, tolerance_m: f64) -> Option<AttemptReport> {
    let mut topic = String::new();
    let mut seen: Vec<Tried> = Vec::new();
    run.scan(|m| {
        if m.msg_type != RegistrationAttempt::ROS_NAME {
            return;
        }
        let Ok(a) = msg::decode::<RegistrationAttempt>(m.data) else {
            return;
        };
        let Some((along, across, heading)) =
            truth_offset(truth, a.reference_stamp.to_ns(), a.query_stamp.to_ns(), max_gap_ns)
        else {
            return;
        };
        topic = m.topic.to_owned();
        seen.push(Tried {
            outcome: a.outcome,
            shift_m: a.shift_m,
            along,
            across,
            heading,
        });
    });
    if seen.is_empty() {
        return None;
    }
    let row = |label: String, sel: &dyn Fn(&Tried) -> bool| {
        let chosen: Vec<_> = seen.iter().filter(|s| sel(s)).collect();
        let with_shift: Vec<_> = chosen.iter().filter(|s| s.shift_m.is_finite()).collect();
        AttemptRow {
            label,
            pairs: chosen.len() as u64,
            with_shift: with_shift.len() as u64,
            right: with_shift
                .iter()
                .filter(|s| (s.shift_m - s.along).abs() <= tolerance_m)
                .count() as u64,
        }
    };
    let mut outcomes: Vec<&str> = seen.iter().map(|s| s.outcome.as_str()).collect();
    outcomes.sort_unstable();
    outcomes.dedup();
    let mut rows: Vec<AttemptRow> = outcomes
        .iter()
        .map(|o| row((*o).to_owned(), &|s| s.outcome == *o))
        .collect();
    let refused = |s: &Tried| s.outcome != "registered";
    for w in ACROSS_BINS_M.windows(2) {
        let label = format!("refused, across-track {}-{} m", w[0], w[1]);
        rows.push(row(label, &|s| refused(s) && (w[0]..w[1]).contains(&s.across.abs())));
    }
    for w in HEADING_BINS_DEG.windows(2) {
        let label = format!("refused, heading difference {}-{} deg", w[0], w[1]);
        rows.push(row(label, &|s| refused(s) && (w[0]..w[1]).contains(&s.heading)));
    }
    Some(AttemptReport {
        topic,
        tolerance_m,
        rows,
    })
}

/// Registrations of one verdict, right or wrong against the truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default)]
pub struct Verdicts {
    /// Registrations.
    pub count: u64,
    /// Measured along-track distance within the tolerance of the truth's.
    pub right: u64,
    /// The others.
    pub wrong: u64,
}

/// The smallest gate base under which every right registration fell, for one growth rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GateBase {
    /// Growth rate, m/s.
    pub growth_mps: f64,
    /// `max(|residual| - growth * gap)` over the right registrations, m.
    pub base_m: f64,
}

/// The estimator's registration checks against the truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CheckReport {
    /// Topic.
    pub topic: String,
    /// A registration within this of the truth is right, m.
    pub tolerance_m: f64,
    /// Taken into the graph.
    pub accepted: Verdicts,
    /// Dropped by the gate.
    pub gated: Verdicts,
    /// `|residual|` of the wrong registrations, m, largest first.
    pub wrong_residuals_m: Vec<f64>,
    /// For each rate of [`GATE_GROWTH_RATES_MPS`], the smallest base that keeps every right
    /// registration, the gap being the time since the newest earlier query the estimate
    /// took (or the truth's start).
    pub gate_bases: Vec<GateBase>,
    /// `max(|residual| / sigma)` over the right registrations with a predicted sigma: the
    /// smallest Mahalanobis gate (standard deviations) that keeps every right one (`None`:
    /// no sigmas recorded).
    pub right_sigmas_max: Option<f64>,
    /// `|residual| / sigma` of the wrong registrations with a predicted sigma, largest first.
    pub wrong_sigmas: Vec<f64>,
}

/// The registration checks recorded in `run` against the truth; `None` when the run has
/// none with the truth at both stamps.
pub fn check_report(run: &Recording, truth: &Trajectory, max_gap_ns: i64, tolerance_m: f64) -> Option<CheckReport> {
    let mut topic = String::new();
    // (accepted, right, |residual|, query stamp, sigma)
    let mut rows: Vec<(bool, bool, f64, i64, f64)> = Vec::new();
    run.scan(|m| {
        if m.msg_type != RegistrationCheck::ROS_NAME {
            return;
        }
        let Ok(c) = msg::decode::<RegistrationCheck>(m.data) else {
            return;
        };
        let (r, q) = (c.reference_stamp.to_ns(), c.query_stamp.to_ns());
        let Some((along, _, _)) = truth_offset(truth, r, q, max_gap_ns) else {
            return;
        };
        topic = m.topic.to_owned();
        let right = (c.along_track_m - along).abs() <= tolerance_m;
        rows.push((c.accepted, right, c.residual_m.abs(), q, c.sigma_m));
    });
    if rows.is_empty() {
        return None;
    }
    let verdicts = |accepted: bool| {
        let of: Vec<_> = rows.iter().filter(|r| r.0 == accepted).collect();
        let right = of.iter().filter(|r| r.1).count() as u64;
        Verdicts {
            count: of.len() as u64,
            right,
            wrong: of.len() as u64 - right,
        }
    };
    let mut wrong_residuals_m: Vec<f64> = rows.iter().filter(|r| !r.1).map(|r| r.2).collect();
    wrong_residuals_m.sort_by(|a, b| b.total_cmp(a));
    // the gap each registration's gate had widened over: since the newest earlier query
    // the estimate took (the registrations of one batch arrive together)
    let start_ns = truth.stamps_ns.first().copied().unwrap_or(0);
    let gaps_s: Vec<f64> = rows
        .iter()
        .enumerate()
        .map(|(k, row)| {
            let newest = rows[..k]
                .iter()
                .filter(|r| r.0 && r.3 < row.3)
                .map(|r| r.3)
                .max()
                .unwrap_or(start_ns);
            (row.3 - newest) as f64 * 1e-9
        })
        .collect();
    let gate_bases = GATE_GROWTH_RATES_MPS
        .iter()
        .map(|&growth_mps| GateBase {
            growth_mps,
            base_m: rows
                .iter()
                .zip(&gaps_s)
                .filter(|(r, _)| r.1)
                .map(|(r, gap)| r.2 - growth_mps * gap)
                .fold(f64::NEG_INFINITY, f64::max),
        })
        .collect();
    let normalised = |right: bool| {
        rows.iter()
            .filter(move |r| r.1 == right && r.4 > 0.0 && r.4.is_finite())
            .map(|r| r.2 / r.4)
    };
    let right_sigmas_max = normalised(true).reduce(f64::max);
    let mut wrong_sigmas: Vec<f64> = normalised(false).collect();
    wrong_sigmas.sort_by(|a, b| b.total_cmp(a));
    Some(CheckReport {
        topic,
        tolerance_m,
        accepted: verdicts(true),
        gated: verdicts(false),
        wrong_residuals_m,
        gate_bases,
        right_sigmas_max,
        wrong_sigmas,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gprflow_msg::{Header, Point, Pose, PoseStamped, Quaternion, Time};
    use gprflow_record::{Recorder, RunMetadata};

    const S: i64 = 1_000_000_000;

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

    /// A run whose truth moves 1 m/s along x for 10 s, with `write` adding its messages.
    fn run(write: impl FnOnce(&mut Recorder)) -> (tempfile::TempDir, Recording, Trajectory) {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("r.mcap");
        let mut rec = Recorder::create(&path, &RunMetadata::this_build()).expect("create");
        let truth = rec.add_topic("truth/pose", PoseStamped::ROS_NAME).expect("topic");
        for i in 0..=10 {
            let m = PoseStamped {
                header: Header::new(i * S, "world"),
                pose: pose(i as f64),
            };
            rec.write(truth, i as u64, i * S, &msg::encode(&m)).expect("write");
        }
        write(&mut rec);
        rec.finish().expect("finish");
        let run = Recording::open(&path).expect("open");
        let t = Trajectory::from_recording(&run, "/truth/pose").expect("truth");
        (dir, run, t)
    }

    #[test]
    fn attempts_are_counted_per_outcome_and_checked_against_the_truth() {
        let (_dir, run, truth) = run(|rec| {
            let topic = rec
                .add_topic("register/attempt", RegistrationAttempt::ROS_NAME)
                .expect("topic");
            // (from s, to s, outcome, shift): the truth's offset is to - from
            let tried = [
                (1, 4, "registered", 3.01),
                (2, 5, "low_score", 3.2),
                (2, 6, "low_score", 4.0),
                (3, 9, "shape", f64::NAN),
            ];
            for (k, (from, to, outcome, shift_m)) in tried.into_iter().enumerate() {
                let a = RegistrationAttempt {
                    header: Header::new(to * S, "base_link"),
                    reference_submap: 0,
                    query_submap: 1,
                    reference_stamp: Time::from_ns(from * S),
                    query_stamp: Time::from_ns(to * S),
                    method: "engineered".into(),
                    outcome: outcome.into(),
                    shift_m,
                    score: 0.5,
                    stretch: 1.0,
                };
                rec.write(topic, k as u64, to * S, &msg::encode(&a)).expect("write");
            }
        });
        let r = attempt_report(&run, &truth, 2 * S, 0.05).expect("attempts");
        assert_eq!(r.topic, "/register/attempt");
        let row = |label: &str| r.rows.iter().find(|row| row.label == label).expect(label).clone();
        assert_eq!((row("registered").pairs, row("registered").right), (1, 1));
        // low_score: 3.2 against 3 is wrong, 4.0 against 4 right
        let low = row("low_score");
        assert_eq!((low.pairs, low.with_shift, low.right), (2, 2, 1));
        assert_eq!((row("shape").pairs, row("shape").with_shift), (1, 0));
        // every refused pair is on the path: across-track 0, heading 0
        assert_eq!(row("refused, across-track 0-0.05 m").pairs, 3);
        assert_eq!(row("refused, heading difference 0-2 deg").pairs, 3);
        assert_eq!(row("refused, across-track 0.2-inf m").pairs, 0);
    }

    #[test]
    fn checks_split_right_from_wrong_and_give_the_gate_that_keeps_the_right_ones() {
        let (_dir, run, truth) = run(|rec| {
            let topic = rec
                .add_topic("estimate/registration_check", RegistrationCheck::ROS_NAME)
                .expect("topic");
            // (from s, to s, measured, residual, accepted, predicted sigma)
            let checks = [
                (1, 3, 2.0, 0.05, true, 0.05), // right, gap 3 s from the start
                (1, 5, 4.02, 0.2, true, 0.1),  // right, gap 2 s since the query at 3 s
                (2, 6, 5.0, 0.9, false, 0.1),  // wrong (truth 4), gated
                (2, 7, 5.0, -0.1, false, 0.0), // right (truth 5), gated; no sigma
            ];
            for (k, (from, to, along_track_m, residual_m, accepted, sigma_m)) in checks.into_iter().enumerate() {
                let c = RegistrationCheck {
                    header: Header::new(to * S, "map"),
                    reference_stamp: Time::from_ns(from * S),
                    query_stamp: Time::from_ns(to * S),
                    along_track_m,
                    residual_m,
                    gate_m: 0.3,
                    sigma_m,
                    accepted,
                };
                rec.write(topic, k as u64, to * S, &msg::encode(&c)).expect("write");
            }
        });
        let r = check_report(&run, &truth, 2 * S, 0.1).expect("checks");
        assert_eq!(
            r.accepted,
            Verdicts {
                count: 2,
                right: 2,
                wrong: 0
            }
        );
        assert_eq!(
            r.gated,
            Verdicts {
                count: 2,
                right: 1,
                wrong: 1
            }
        );
        assert_eq!(r.wrong_residuals_m, vec![0.9]);
        // the right ones: |res| 0.05 (gap 3), 0.2 (gap 2), 0.1 (gap 2 since the query at 5 s)
        assert!((r.gate_bases[0].base_m - 0.2).abs() < 1e-12, "{:?}", r.gate_bases);
        let at = |rate: f64| r.gate_bases.iter().find(|g| g.growth_mps == rate).expect("rate").base_m;
        let expected = [0.05 - 0.02 * 3.0, 0.2 - 0.02 * 2.0, 0.1 - 0.02 * 2.0]
            .into_iter()
            .fold(f64::NEG_INFINITY, f64::max);
        assert!((at(0.02) - expected).abs() < 1e-12);
        // right: 0.05 / 0.05 and 0.2 / 0.1 (the third has no sigma); wrong: 0.9 / 0.1
        assert_eq!(r.right_sigmas_max, Some(2.0));
        assert_eq!(r.wrong_sigmas.len(), 1);
        assert!((r.wrong_sigmas[0] - 9.0).abs() < 1e-12, "{:?}", r.wrong_sigmas);
    }
}
