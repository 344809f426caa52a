//! Trajectories: read from a recording's pose topics or from TUM files, written as TUM.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion as NaQuaternion, Translation3, UnitQuaternion};

use gprflow_msg::{self as msg, Odometry, Pose, PoseStamped, StateEstimate, Trajectory as TrajectoryMsg};
use gprflow_record::{RecordError, Recording};

/// A trajectory: stamped `world_from_body` poses, stamps increasing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// Stamps, ns.
    pub stamps_ns: Vec<i64>,
    /// Poses.
    pub poses: Vec<Isometry3<f64>>,
}

/// Problems reading a trajectory.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TrajectoryError {
    /// The recording cannot be read.
    #[error(transparent)]
    Record(#[from] RecordError),
    /// The recording has no topic carrying poses.
    #[error("{}: no pose topic (PoseStamped, Odometry, StateEstimate or Trajectory); topics: {}", file.display(), available.join(", "))]
    NoPoseTopic {
        /// The recording.
        file: PathBuf,
        /// Its topics.
        available: Vec<String>,
    },
    /// The named topic is not in the recording or carries no poses.
    #[error("{}: topic `{topic}` carries no poses; pose topics: {}", file.display(), available.join(", "))]
    NotAPoseTopic {
        /// The recording.
        file: PathBuf,
        /// The topic asked for.
        topic: String,
        /// Pose topics there are.
        available: Vec<String>,
    },
    /// No wheel odometry topic, or not the one asked for.
    #[error("{}: no wheel topic{} ({}); topics: {}", file.display(), topic.as_ref().map(|t| format!(" `{t}`")).unwrap_or_default(), <gprflow_msg::WheelOdometry as gprflow_msg::Message>::TYPE_NAME, available.join(", "))]
    NoWheelTopic {
        /// The recording.
        file: PathBuf,
        /// The topic asked for, if one was.
        topic: Option<String>,
        /// Its topics, with their types.
        available: Vec<String>,
    },
    /// A message cannot be decoded (or holds a value that cannot be used).
    #[error("{}: {topic} seq {seq}: {reason}", file.display())]
    Decode {
        /// The recording.
        file: PathBuf,
        /// Topic.
        topic: String,
        /// Sequence number.
        seq: u32,
        /// Why.
        reason: String,
    },
    /// A TUM file line is malformed.
    #[error("{}:{line}: {reason}", file.display())]
    Tum {
        /// The file.
        file: PathBuf,
        /// Line, from 1.
        line: usize,
        /// Why.
        reason: String,
    },
    /// A file cannot be read or written.
    #[error("{}: {source}", file.display())]
    Io {
        /// The file.
        file: PathBuf,
        /// The reason.
        source: std::io::Error,
    },
}

/// What a pose topic carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseTopicKind {
    /// `geometry_msgs/PoseStamped` (ground truth, poses).
    PoseStamped,
    /// `nav_msgs/Odometry`.
    Odometry,
    /// `gprflow_msgs/StateEstimate`, one per state.
    StateEstimate,
    /// `gprflow_msgs/Trajectory` snapshots: the last one is the trajectory.
    Snapshot,
}

impl PoseTopicKind {
    fn of(msg_type: &str) -> Option<Self> {
        match msg_type {
            t if t == PoseStamped::ROS_NAME => Some(Self::PoseStamped),
            t if t == Odometry::ROS_NAME => Some(Self::Odometry),
            t if t == StateEstimate::ROS_NAME => Some(Self::StateEstimate),
            t if t == TrajectoryMsg::ROS_NAME => Some(Self::Snapshot),
            _ => None,
        }
    }
}

/// The recording's topics that carry poses, with their kinds, in topic order.
pub fn pose_topics(rec: &Recording) -> Vec<(String, PoseTopicKind)> {
    rec.topics()
        .into_iter()
        .filter_map(|(topic, ty)| PoseTopicKind::of(&ty).map(|k| (topic, k)))
        .collect()
}

fn isometry(p: &Pose) -> Isometry3<f64> {
    let q = &p.orientation;
    Isometry3::from_parts(
        Translation3::new(p.position.x, p.position.y, p.position.z),
        UnitQuaternion::from_quaternion(NaQuaternion::new(q.w, q.x, q.y, q.z)),
    )
}

impl Trajectory {
    /// Reads the poses on `topic` of a recording (with or without the leading `/`).
    ///
    /// # Errors
    /// Unreadable recording, a topic without poses (naming the pose topics there are),
    /// undecodable messages (topic and seq).
    pub fn from_recording(rec: &Recording, topic: &str) -> Result<Self, TrajectoryError> {
        let file = rec.path().to_owned();
        let topics = pose_topics(rec);
        let wanted = format!("/{}", topic.trim_start_matches('/'));
        let Some((_, kind)) = topics.iter().find(|(t, _)| *t == wanted) else {
            return Err(TrajectoryError::NotAPoseTopic {
                file,
                topic: topic.to_owned(),
                available: topics.into_iter().map(|(t, _)| t).collect(),
            });
        };
        let kind = *kind;
        let mut out = Self::default();
        scan_topic(rec, &wanted, |data| {
            let poses = match kind {
                PoseTopicKind::PoseStamped => {
                    msg::decode::<PoseStamped>(data).map(|p| vec![(p.header.stamp.to_ns(), isometry(&p.pose))])
                }
                PoseTopicKind::Odometry => {
                    msg::decode::<Odometry>(data).map(|o| vec![(o.header.stamp.to_ns(), isometry(&o.pose.pose))])
                }
                PoseTopicKind::StateEstimate => msg::decode::<StateEstimate>(data)
                    .map(|s| vec![(s.header.stamp.to_ns(), isometry(&s.world_from_body.pose))]),
                PoseTopicKind::Snapshot => msg::decode::<TrajectoryMsg>(data).map(|t| {
                    out = Self::default(); // only the last snapshot counts
                    t.poses
                        .iter()
                        .map(|p| (p.header.stamp.to_ns(), isometry(&p.pose)))
                        .collect()
                }),
            }
            .map_err(|e| e.to_string())?;
            for (stamp, pose) in poses {
                out.stamps_ns.push(stamp);
                out.poses.push(pose);
            }
            Ok(())
        })?;
        out.sort();
        Ok(out)
    }

    /// Sorts by stamp, keeping the last of equal stamps.
    fn sort(&mut self) {
        let mut pairs: Vec<(i64, Isometry3<f64>)> =
            self.stamps_ns.iter().copied().zip(self.poses.iter().copied()).collect();
        pairs.sort_by_key(|p| p.0);
        pairs.dedup_by(|later, earlier| {
            if later.0 == earlier.0 {
                earlier.1 = later.1;
                true
            } else {
                false
            }
        });
        self.stamps_ns = pairs.iter().map(|p| p.0).collect();
        self.poses = pairs.into_iter().map(|p| p.1).collect();
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// True when there are no poses.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The pose at `stamp_ns`, interpolated between the samples around it when they are at
    /// most `max_gap_ns` apart (exact stamps always match).
    pub fn interpolate(&self, stamp_ns: i64, max_gap_ns: i64) -> Option<Isometry3<f64>> {
        let i = self.stamps_ns.partition_point(|&s| s < stamp_ns);
        if self.stamps_ns.get(i) == Some(&stamp_ns) {
            return Some(self.poses[i]);
        }
        if i == 0 || i >= self.stamps_ns.len() {
            return None;
        }
        let (s0, s1) = (self.stamps_ns[i - 1], self.stamps_ns[i]);
        if s1 - s0 > max_gap_ns {
            return None;
        }
        let f = (stamp_ns - s0) as f64 / (s1 - s0) as f64;
        let (p0, p1) = (&self.poses[i - 1], &self.poses[i]);
        let t = p0.translation.vector.lerp(&p1.translation.vector, f);
        let r = p0.rotation.slerp(&p1.rotation, f);
        Some(Isometry3::from_parts(Translation3::from(t), r))
    }
}

/// Visits the payload of every message on `topic` (in log order) until `visit` refuses one;
/// its reason comes back as [`TrajectoryError::Decode`] with the topic and seq. A read that
/// stops early keeps what came before it, with a warning.
pub(super) fn scan_topic(
    rec: &Recording,
    topic: &str,
    mut visit: impl FnMut(&[u8]) -> Result<(), String>,
) -> Result<(), TrajectoryError> {
    let mut failure = None;
    let (_, stopped) = rec.scan(|m| {
        if m.topic != topic || failure.is_some() {
            return;
        }
        if let Err(reason) = visit(m.data) {
            failure = Some(TrajectoryError::Decode {
                file: rec.path().to_owned(),
                topic: topic.to_owned(),
                seq: m.sequence,
                reason,
            });
        }
    });
    if let Some(e) = failure {
        return Err(e);
    }
    if let Some(reason) = stopped {
        tracing::warn!("{}: read stopped early: {reason}", rec.path().display());
    }
    Ok(())
}

/// Writes a trajectory as TUM text: `stamp_s x y z qx qy qz qw` per line.
pub fn write_tum(t: &Trajectory) -> String {
    let mut out = String::with_capacity(t.len() * 96);
    for (stamp, p) in t.stamps_ns.iter().zip(&t.poses) {
        let (v, q) = (p.translation.vector, p.rotation);
        let _ = writeln!(
            out,
            "{}.{:09} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
            stamp.div_euclid(1_000_000_000),
            stamp.rem_euclid(1_000_000_000),
            v.x,
            v.y,
            v.z,
            q.i,
            q.j,
            q.k,
            q.w
        );
    }
    out
}

/// Reads a TUM trajectory file (`#` comments and blank lines allowed).
///
/// # Errors
/// Unreadable file, or the first malformed line with its number.
pub fn read_tum(path: &Path) -> Result<Trajectory, TrajectoryError> {
    let text = std::fs::read_to_string(path).map_err(|source| TrajectoryError::Io {
        file: path.to_owned(),
        source,
    })?;
    let mut out = Trajectory::default();
    let mut line_numbers = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |reason: String| TrajectoryError::Tum {
            file: path.to_owned(),
            line: n + 1,
            reason,
        };
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != 8 {
            return Err(bad(format!(
                "expected 8 fields (t x y z qx qy qz qw), found {}",
                fields.len()
            )));
        }
        let mut v = [0.0; 8];
        for (i, (slot, f)) in v.iter_mut().zip(&fields).enumerate() {
            *slot = f
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(format!("field {} `{f}` is not a finite number", i + 1)))?;
        }
        let q = NaQuaternion::new(v[7], v[4], v[5], v[6]);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(bad(format!("quaternion norm {} is not 1", q.norm())));
        }
        line_numbers.push(n + 1);
        out.stamps_ns.push((v[0] * 1e9).round() as i64);
        out.poses.push(Isometry3::from_parts(
            Translation3::new(v[1], v[2], v[3]),
            UnitQuaternion::from_quaternion(q),
        ));
    }
    if let Some(i) = out.stamps_ns.windows(2).position(|w| w[1] <= w[0]) {
        return Err(TrajectoryError::Tum {
            file: path.to_owned(),
            line: line_numbers[i + 1],
            reason: "stamps must increase".into(),
        });
    }
    Ok(out)
}
