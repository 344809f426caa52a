//! Errors of the messages a run recorded, against the truth: registrations (the relative
//! pose between their two stamps) and line observations (the forward distance to the nearest
//! true line). `gprflow eval` reports them.

use gprflow_msg::{self as msg, HoughLine, LineObservation, Registration};
use gprflow_record::Recording;
use serde::Serialize;

use crate::{Stats, Trajectory};

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
    /// Each matched observation's stamp (ns) and forward-distance error (m), in file order,
    /// for plots.
    #[serde(skip)]
    pub samples: Vec<(i64, f64)>,
}

/// An observation within this of a true line's forward distance is a detection of it, m.
pub const LINE_MATCH_GATE_M: f64 = 0.5;

/// The error of `run`'s line observations against the truth's poses and `true_lines`
/// (poses interpolated across gaps up to `max_gap_ns`); `None` when it has none.
pub fn line_observation_error(
    run: &Recording,
    truth: &Trajectory,
    true_lines: &[HoughLine],
    max_gap_ns: i64,
) -> Option<LineObservationError> {
    let mut topic = None;
    let (mut observations, mut errors, mut samples) = (0usize, Vec::new(), Vec::new());
    run.scan(|m| {
        if m.msg_type != LineObservation::ROS_NAME {
            return;
        }
        let Ok(o) = msg::decode::<LineObservation>(m.data) else {
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
            samples.push((o.header.stamp.to_ns(), e));
        }
    });
    Some(LineObservationError {
        topic: topic?,
        observations,
        matched: errors.len(),
        unmatched: observations - errors.len(),
        forward_distance: Stats::of(&errors),
        samples,
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
    /// Each registration's query stamp (ns) and along-track error (m), in file order, for
    /// plots.
    #[serde(skip)]
    pub samples: Vec<(i64, f64)>,
}

/// The error of `run`'s registrations against the truth's relative poses (poses interpolated
/// across gaps up to `max_gap_ns`); `None` when no registration has the truth at both stamps.
pub fn registration_error(run: &Recording, truth: &Trajectory, max_gap_ns: i64) -> Option<RegistrationError> {
    let mut topic = String::new();
    let (mut along, mut full, mut samples) = (Vec::new(), Vec::new(), Vec::new());
    run.scan(|m| {
        if m.msg_type != Registration::ROS_NAME {
            return;
        }
        let Ok(r) = msg::decode::<Registration>(m.data) else {
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
        samples.push((r.query_stamp.to_ns(), r.along_track_m - rel.translation.vector.x));
        let p = &r.reference_from_query.position;
        let t = rel.translation.vector;
        full.push(((p.x - t.x).powi(2) + (p.y - t.y).powi(2) + (p.z - t.z).powi(2)).sqrt());
    });
    Some(RegistrationError {
        topic,
        along_track: Stats::of(&along)?,
        translation: Stats::of(&full)?,
        samples,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gprflow_msg::{Header, Point, Pose, PoseStamped, Quaternion, Time};
    use gprflow_record::{Recorder, RunMetadata};

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
            rec.write(truth, i as u64, i * s, &gprflow_msg::encode(&m))
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
                covariance: gprflow_msg::Covariance6([0.0; 36]),
                along_track_m: measured,
                along_track_variance_m2: 0.01,
                score: 1.0,
                method: "test".into(),
            };
            rec.write(regs, k as u64, to * s, &gprflow_msg::encode(&r))
                .expect("write");
        }
        rec.finish().expect("finish");
        let run = Recording::open(&path).expect("open");
        let t = Trajectory::from_recording(&run, "/truth/pose").expect("truth");
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
