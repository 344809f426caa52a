//! LGPR tracking accuracy as seed 001 §3 measures it (eq. 11): the tracking pass's estimate
//! relative to the mapping pass's GPS/INS track, against the same relative position from the
//! truth of both passes, so that the map's own global (GPS/INS) error does not count:
//!
//! `E(t_a) = [P_track^LGPR(t) - P_base^GPS(t_a)] - [P_track^truth(t) - P_base^truth(t_a)]`,
//!
//! `t_a` the baseline's time at the point of its true track nearest the tracking pass's true
//! position (interpolated between the two nearest samples). The error splits into along- and
//! cross-track components with the tracking pass's true heading as the along-track axis; the
//! GPS/INS error is the same with the tracking pass's GPS/INS position for the LGPR's.
//!
//! As in the paper, statistics are over distance (each sample weighs the distance driven
//! since the previous one), leave out the samples before the tracker's first lock, and keep
//! only the samples whose true lateral offset from the baseline is within `max_offset_m`
//! (1.3 m: some element over the map).

use gprflow_msg::MapFix;
use gprflow_record::Recording;
use nalgebra::Vector2;
use serde::Serialize;

use crate::trajectory::scan_topic;
use crate::{Trajectory, TrajectoryError};

/// The map fixes of a run.
#[derive(Debug, Clone, Default)]
pub struct Fixes {
    /// Stamps, ns.
    pub stamps_ns: Vec<i64>,
    /// Positions `(x, y)`, m.
    pub xy_m: Vec<[f64; 2]>,
    /// Correlation of each fix.
    pub correlation: Vec<f64>,
    /// Channels over mapped data.
    pub overlap: Vec<u32>,
    /// Lock state.
    pub locked: Vec<bool>,
}

impl Fixes {
    /// The map fixes of a run that need not hold any (a fused estimate's run): `None` when the
    /// recording has no `MapFix` topic, else as [`Fixes::from_recording`] on its only one.
    ///
    /// # Errors
    /// Several `MapFix` topics (naming them), an undecodable message (topic and seq).
    pub fn from_recording_if_any(rec: &Recording) -> Result<Option<Self>, TrajectoryError> {
        if rec.topics().iter().all(|(_, ty)| ty != MapFix::ROS_NAME) {
            return Ok(None);
        }
        Self::from_recording(rec, None).map(Some)
    }

    /// Reads the `MapFix` messages on `topic` (default: the recording's only `MapFix` topic).
    ///
    /// # Errors
    /// No or several `MapFix` topics (naming them), an undecodable message (topic and seq).
    pub fn from_recording(rec: &Recording, topic: Option<&str>) -> Result<Self, TrajectoryError> {
        let candidates: Vec<String> = rec
            .topics()
            .into_iter()
            .filter(|(_, ty)| ty == MapFix::ROS_NAME)
            .map(|(t, _)| t)
            .collect();
        let topic = match topic {
            Some(t) => format!("/{}", t.trim_start_matches('/')),
            None if candidates.len() == 1 => candidates[0].clone(),
            None => {
                return Err(TrajectoryError::NotAPoseTopic {
                    file: rec.path().to_owned(),
                    topic: "(a MapFix topic)".into(),
                    available: candidates,
                });
            }
        };
        let mut out = Self::default();
        scan_topic(rec, &topic, |data| {
            let m: MapFix = gprflow_msg::decode(data).map_err(|e| e.to_string())?;
            let p = m.world_from_body.position;
            out.stamps_ns.push(m.header.stamp.to_ns());
            out.xy_m.push([p.x, p.y]);
            out.correlation.push(f64::from(m.correlation));
            out.overlap.push(m.overlapping_channels);
            out.locked.push(m.locked);
            Ok(())
        })?;
        Ok(out)
    }
}

impl Fixes {
    /// The poses of a trajectory (a fused estimate) as fixes: every one counted as locked,
    /// correlation NaN (unknown), overlap 0.
    pub fn from_trajectory(t: &Trajectory) -> Self {
        Self {
            stamps_ns: t.stamps_ns.clone(),
            xy_m: t.poses.iter().map(|p| [p.translation.x, p.translation.y]).collect(),
            correlation: vec![f64::NAN; t.len()],
            overlap: vec![0; t.len()],
            locked: vec![true; t.len()],
        }
    }

    /// The stamp of the first locked fix, if any.
    #[must_use]
    pub fn first_lock_ns(&self) -> Option<i64> {
        self.locked.iter().position(|&l| l).map(|i| self.stamps_ns[i])
    }

    /// Marks the poses before `stamp_ns` as not locked, so [`evaluate`] starts there: a fused
    /// estimate is measured over the span its tracker's fixes are (from their first lock),
    /// not over the drive to the first lock, where it is the GPS/INS's.
    #[must_use]
    pub fn from_lock(mut self, stamp_ns: i64) -> Self {
        for (locked, t) in self.locked.iter_mut().zip(&self.stamps_ns) {
            *locked = *t >= stamp_ns;
        }
        self
    }
}

/// The four tracks eq. 11 needs besides the fixes.
#[derive(Debug, Clone, Copy)]
pub struct Tracks<'a> {
    /// Truth of the tracking pass.
    pub track_truth: &'a Trajectory,
    /// GPS/INS of the tracking pass.
    pub track_gps: &'a Trajectory,
    /// Truth of the mapping pass.
    pub base_truth: &'a Trajectory,
    /// GPS/INS of the mapping pass.
    pub base_gps: &'a Trajectory,
}

/// One evaluated fix.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Sample {
    /// Stamp, ns.
    pub stamp_ns: i64,
    /// Distance driven since the previous fix (its weight), m.
    pub weight_m: f64,
    /// True speed, m/s.
    pub speed_mps: f64,
    /// True lateral offset from the baseline, left positive, m.
    pub offset_m: f64,
    /// LGPR error (along, cross), m.
    pub lgpr: [f64; 2],
    /// GPS/INS error (along, cross), m.
    pub gps: [f64; 2],
    /// Correlation of the fix.
    pub correlation: f64,
    /// Lock state.
    pub locked: bool,
}

/// RMS errors over distance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Rms {
    /// Cross-track, m.
    pub cross_m: f64,
    /// Along-track, m.
    pub along_m: f64,
    /// Total, m.
    pub total_m: f64,
}

/// A run's (or several runs') summary.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Summary {
    /// LGPR RMS errors.
    pub lgpr: Rms,
    /// GPS/INS RMS errors.
    pub gps: Rms,
    /// Share of the distance with the tracker locked, percent.
    pub locked_pct: f64,
    /// Distance evaluated, m.
    pub distance_m: f64,
    /// Fixes evaluated.
    pub fixes: usize,
    /// Mean true speed over the distance, m/s.
    pub mean_speed_mps: f64,
    /// Cross-track error below which 68.3 % / 95.5 % of the distance lies, m (Fig. 17).
    pub cross_p68_m: f64,
    /// As `cross_p68_m`, 95.5 %.
    pub cross_p95_m: f64,
}

/// Options of [`evaluate`].
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Largest true lateral offset from the baseline kept, m (seed 001: 1.3).
    pub max_offset_m: f64,
    /// Largest gap interpolated over in the truth and GPS/INS tracks, ns.
    pub max_gap_ns: i64,
    /// Farthest the baseline may be from the tracking pass's true position, m (beyond: not
    /// the mapped road).
    pub max_baseline_distance_m: f64,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            max_offset_m: 1.3,
            max_gap_ns: 500_000_000,
            max_baseline_distance_m: 5.0,
        }
    }
}

/// The baseline's truth as a polyline, with a cursor for the nearest-point search.
struct Baseline<'a> {
    truth: &'a Trajectory,
    xy: Vec<Vector2<f64>>,
    cursor: Option<usize>,
}

impl<'a> Baseline<'a> {
    fn new(truth: &'a Trajectory) -> Self {
        let xy = truth
            .poses
            .iter()
            .map(|p| Vector2::new(p.translation.x, p.translation.y))
            .collect();
        Self {
            truth,
            xy,
            cursor: None,
        }
    }

    /// Nearest point of segment `i` (`i`, `i + 1`) to `p`: (distance, fraction).
    fn on_segment(&self, i: usize, p: &Vector2<f64>) -> (f64, f64) {
        let (a, b) = (self.xy[i], self.xy[i + 1]);
        let d = b - a;
        let len2 = d.norm_squared();
        let f = if len2 > 0.0 {
            ((p - a).dot(&d) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        ((a + d * f - p).norm(), f)
    }

    /// `(t_a, truth position, heading of the baseline there, distance)` of the baseline point
    /// nearest `p`: near the last match first, everywhere when that is far.
    fn nearest(&mut self, p: &Vector2<f64>, max_distance_m: f64) -> Option<(i64, Vector2<f64>, Vector2<f64>)> {
        if self.xy.len() < 2 {
            return None;
        }
        let segments = self.xy.len() - 1;
        let best_in = |s: &Self, range: std::ops::Range<usize>| {
            range
                .map(|i| {
                    let (d, f) = s.on_segment(i, p);
                    (d, i, f)
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
        };
        let mut best = self
            .cursor
            .and_then(|c| best_in(self, c.saturating_sub(400)..(c + 400).min(segments)));
        if best.is_none_or(|b| b.0 > max_distance_m) {
            best = best_in(self, 0..segments);
        }
        let (d, i, f) = best?;
        if d > max_distance_m {
            return None;
        }
        self.cursor = Some(i);
        let (s0, s1) = (self.truth.stamps_ns[i], self.truth.stamps_ns[i + 1]);
        let t_a = s0 + ((s1 - s0) as f64 * f).round() as i64;
        let at = self.xy[i] + (self.xy[i + 1] - self.xy[i]) * f;
        let dir = (self.xy[i + 1] - self.xy[i]).try_normalize(1e-9)?;
        Some((t_a, at, dir))
    }
}

fn xy(p: &nalgebra::Isometry3<f64>) -> Vector2<f64> {
    Vector2::new(p.translation.x, p.translation.y)
}

/// Evaluates `fixes` by eq. 11 (samples in fix order).
pub fn evaluate(fixes: &Fixes, tracks: Tracks<'_>, opts: Options) -> Vec<Sample> {
    let mut base = Baseline::new(tracks.base_truth);
    let mut out = Vec::new();
    let mut prev_truth: Option<(i64, Vector2<f64>)> = None;
    let first_lock = fixes.locked.iter().position(|&l| l);
    for i in 0..fixes.stamps_ns.len() {
        let t = fixes.stamps_ns[i];
        let Some(truth) = tracks.track_truth.interpolate(t, opts.max_gap_ns) else {
            continue;
        };
        let p_true = xy(&truth);
        let (weight, speed) = match prev_truth {
            Some((t0, p0)) => {
                let d = (p_true - p0).norm();
                let dt = (t - t0) as f64 * 1e-9;
                (d, if dt > 0.0 { d / dt } else { 0.0 })
            }
            None => (0.0, 0.0),
        };
        prev_truth = Some((t, p_true));
        if first_lock.is_none_or(|f| i < f) {
            continue;
        }
        let Some((t_a, base_true, base_dir)) = base.nearest(&p_true, opts.max_baseline_distance_m) else {
            continue;
        };
        let base_left = Vector2::new(-base_dir.y, base_dir.x);
        let offset = (p_true - base_true).dot(&base_left);
        if offset.abs() > opts.max_offset_m {
            continue;
        }
        let (Some(base_gps), Some(track_gps)) = (
            tracks.base_gps.interpolate(t_a, opts.max_gap_ns),
            tracks.track_gps.interpolate(t, opts.max_gap_ns),
        ) else {
            continue;
        };
        let truth_rel = p_true - base_true;
        let fix = Vector2::new(fixes.xy_m[i][0], fixes.xy_m[i][1]);
        let e_lgpr = (fix - xy(&base_gps)) - truth_rel;
        let e_gps = (xy(&track_gps) - xy(&base_gps)) - truth_rel;
        // along-track: the tracking pass's true heading
        let fwd = truth.rotation * nalgebra::Vector3::x();
        let along = Vector2::new(fwd.x, fwd.y).try_normalize(1e-9).unwrap_or(base_dir);
        let left = Vector2::new(-along.y, along.x);
        out.push(Sample {
            stamp_ns: t,
            weight_m: weight,
            speed_mps: speed,
            offset_m: offset,
            lgpr: [e_lgpr.dot(&along), e_lgpr.dot(&left)],
            gps: [e_gps.dot(&along), e_gps.dot(&left)],
            correlation: fixes.correlation[i],
            locked: fixes.locked[i],
        });
    }
    out
}

/// The distance-weighted `q` quantile of `|values|`.
fn weighted_quantile(values: &[(f64, f64)], q: f64) -> f64 {
    let mut v: Vec<(f64, f64)> = values.iter().map(|(x, w)| (x.abs(), *w)).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = v.iter().map(|x| x.1).sum();
    let mut acc = 0.0;
    for (x, w) in &v {
        acc += w;
        if acc >= q * total {
            return *x;
        }
    }
    v.last().map_or(0.0, |x| x.0)
}

/// Distance-weighted summary of `samples` (`None` without distance).
pub fn summarise(samples: &[Sample]) -> Option<Summary> {
    let total: f64 = samples.iter().map(|s| s.weight_m).sum();
    if total <= 0.0 {
        return None;
    }
    let rms =
        |f: &dyn Fn(&Sample) -> f64| (samples.iter().map(|s| s.weight_m * f(s).powi(2)).sum::<f64>() / total).sqrt();
    let of = |pick: fn(&Sample) -> [f64; 2]| Rms {
        along_m: rms(&|s| pick(s)[0]),
        cross_m: rms(&|s| pick(s)[1]),
        total_m: rms(&|s| pick(s)[0].hypot(pick(s)[1])),
    };
    let cross: Vec<(f64, f64)> = samples.iter().map(|s| (s.lgpr[1], s.weight_m)).collect();
    Some(Summary {
        lgpr: of(|s| s.lgpr),
        gps: of(|s| s.gps),
        locked_pct: 100.0 * samples.iter().filter(|s| s.locked).map(|s| s.weight_m).sum::<f64>() / total,
        distance_m: total,
        fixes: samples.len(),
        mean_speed_mps: samples.iter().map(|s| s.weight_m * s.speed_mps).sum::<f64>() / total,
        cross_p68_m: weighted_quantile(&cross, 0.683),
        cross_p95_m: weighted_quantile(&cross, 0.955),
    })
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    use super::*;

    fn line(y: f64, dt_ns: i64, n: usize, speed: f64, bias: [f64; 2]) -> Trajectory {
        let mut t = Trajectory::default();
        for i in 0..n {
            let x = i as f64 * speed * dt_ns as f64 * 1e-9;
            t.stamps_ns.push(i as i64 * dt_ns);
            t.poses.push(Isometry3::from_parts(
                Translation3::new(x + bias[0], y + bias[1], 0.0),
                UnitQuaternion::identity(),
            ));
        }
        t
    }

    #[test]
    fn eq_11_cancels_the_maps_gps_error_and_splits_along_and_cross() {
        // baseline along y = 0 at 4 m/s, its GPS 0.3 m off in x and -0.2 in y; the tracking
        // pass 0.5 m to the left at 10 m/s
        let base_truth = line(0.0, 50_000_000, 2000, 4.0, [0.0, 0.0]);
        let base_gps = line(0.0, 50_000_000, 2000, 4.0, [0.3, -0.2]);
        let track_truth = line(0.5, 50_000_000, 600, 10.0, [0.0, 0.0]);
        let track_gps = line(0.5, 50_000_000, 600, 10.0, [-0.4, 0.1]);
        // an LGPR that reports the map frame (the baseline GPS's) plus 3 cm along, -2 cm cross
        let mut fixes = Fixes::default();
        for (s, p) in track_truth.stamps_ns.iter().zip(&track_truth.poses).skip(10).take(500) {
            fixes.stamps_ns.push(*s);
            fixes
                .xy_m
                .push([p.translation.x + 0.3 + 0.03, p.translation.y - 0.2 - 0.02]);
            fixes.correlation.push(0.95);
            fixes.overlap.push(11);
            fixes.locked.push(true);
        }
        let tracks = Tracks {
            track_truth: &track_truth,
            track_gps: &track_gps,
            base_truth: &base_truth,
            base_gps: &base_gps,
        };
        let samples = evaluate(&fixes, tracks, Options::default());
        assert_eq!(samples.len(), 500);
        for s in &samples[1..] {
            assert!(
                (s.lgpr[0] - 0.03).abs() < 1e-9 && (s.lgpr[1] + 0.02).abs() < 1e-9,
                "{s:?}"
            );
            assert!((s.gps[0] + 0.7).abs() < 1e-9 && (s.gps[1] - 0.3).abs() < 1e-9, "{s:?}");
            assert!((s.offset_m - 0.5).abs() < 1e-9 && (s.speed_mps - 10.0).abs() < 1e-6);
        }
        let sum = summarise(&samples).expect("distance");
        assert!((sum.lgpr.cross_m - 0.02).abs() < 1e-9 && (sum.lgpr.along_m - 0.03).abs() < 1e-9);
        assert!((sum.lgpr.total_m - 0.03_f64.hypot(0.02)).abs() < 1e-9);
        assert!((sum.locked_pct - 100.0).abs() < 1e-9);
        // beyond the offset limit nothing is kept
        let far = Options {
            max_offset_m: 0.4,
            ..Options::default()
        };
        assert!(evaluate(&fixes, tracks, far).is_empty());
    }

    #[test]
    fn fixes_before_the_first_lock_are_left_out() {
        let base = line(0.0, 50_000_000, 400, 4.0, [0.0, 0.0]);
        let mut fixes = Fixes::default();
        for i in 0..100 {
            fixes.stamps_ns.push(i * 50_000_000);
            fixes.xy_m.push([i as f64 * 0.2, 0.0]);
            fixes.correlation.push(0.5);
            fixes.overlap.push(11);
            fixes.locked.push(i >= 30 && i % 2 == 0);
        }
        let tracks = Tracks {
            track_truth: &base,
            track_gps: &base,
            base_truth: &base,
            base_gps: &base,
        };
        let s = evaluate(&fixes, tracks, Options::default());
        assert_eq!(s.len(), 70);
        let sum = summarise(&s).expect("distance");
        assert!((sum.locked_pct - 50.0).abs() < 1.5, "{}", sum.locked_pct);
    }

    #[test]
    fn a_fused_estimate_is_measured_from_its_trackers_first_lock() {
        let base = line(0.0, 50_000_000, 400, 4.0, [0.0, 0.0]);
        let mut fixes = Fixes::default();
        for i in 0..100 {
            fixes.stamps_ns.push(i * 50_000_000);
            fixes.xy_m.push([i as f64 * 0.2, 0.0]);
            fixes.correlation.push(0.95);
            fixes.overlap.push(11);
            fixes.locked.push(i >= 30);
        }
        assert_eq!(fixes.first_lock_ns(), Some(1_500_000_000));
        // 10 Hz poses, 1 m off before the first lock and on the truth after it
        let mut fused = line(0.0, 100_000_000, 50, 4.0, [0.0, 0.0]);
        for (t, p) in fused.stamps_ns.iter().zip(fused.poses.iter_mut()) {
            if *t < 1_500_000_000 {
                p.translation.y += 1.0;
            }
        }
        let tracks = Tracks {
            track_truth: &base,
            track_gps: &base,
            base_truth: &base,
            base_gps: &base,
        };
        let all = evaluate(&Fixes::from_trajectory(&fused), tracks, Options::default());
        let from_lock = evaluate(
            &Fixes::from_trajectory(&fused).from_lock(1_500_000_000),
            tracks,
            Options::default(),
        );
        assert_eq!((all.len(), from_lock.len()), (50, 35));
        assert!(summarise(&all).expect("distance").lgpr.cross_m > 0.5);
        assert!(summarise(&from_lock).expect("distance").lgpr.cross_m < 1e-9);
    }

    #[test]
    fn a_run_without_map_fixes_has_none_and_a_bad_one_is_an_error() {
        use gprflow_record::{Recorder, RunMetadata};
        let dir = tempfile::tempdir().expect("tempdir");
        let write = |name: &str, fix_topics: &[&str]| {
            let path = dir.path().join(name);
            let mut rec = Recorder::create(&path, &RunMetadata::this_build()).expect("create");
            rec.add_topic("estimate/state", "gprflow_msgs/msg/StateEstimate")
                .expect("topic");
            for t in fix_topics {
                let id = rec.add_topic(t, MapFix::ROS_NAME).expect("topic");
                // not a MapFix
                rec.write(id, 0, 0, &[1, 2, 3]).expect("write");
            }
            rec.finish().expect("finish");
            Recording::open(&path).expect("open")
        };
        let none = write("none.mcap", &[]);
        assert!(Fixes::from_recording_if_any(&none).expect("no fixes").is_none());
        let bad = write("bad.mcap", &["track/map_fix"]);
        let e = Fixes::from_recording_if_any(&bad).expect_err("undecodable").to_string();
        assert!(e.contains("bad.mcap") && e.contains("/track/map_fix seq 0"), "{e}");
        let two = write("two.mcap", &["a/map_fix", "b/map_fix"]);
        let e = Fixes::from_recording_if_any(&two).expect_err("ambiguous").to_string();
        assert!(e.contains("a/map_fix") && e.contains("b/map_fix"), "{e}");
    }
}
