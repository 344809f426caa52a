//! From hyperbolas in submaps to line observations (seed 000 §5.4), as plain code.
//!
//! [`project_apex`] places a hyperbola's apex on the drive: its wheel distance along track, its
//! stamp, and its point on the ground in the submaps' odometry frame, all interpolated across
//! the submap's span. [`forward_distance_m`] is the measurement of the line factor:
//! `s_apex + antenna_forward_m - s_end` in wheel distance `s` (negative: the line is behind).
//!
//! [`Observer`] keeps what the `lines` stage remembers between submaps. A hyperbola is taken
//! from the submaps where its apex has reached the middle (seen with as much ground on both
//! sides as the submap holds, so the edge does not pull the fit). Submaps overlap, so the same
//! hyperbola (apexes within the half aperture along track and `separation_ns` in time) comes
//! again and again: the strongest is kept, and released once the drive has left it more than
//! the half aperture behind the middle; a wavelet side lobe reaching the middle first thus
//! gives way to the hyperbola itself. One already released is not taken again while the
//! submaps still share traces. Apexes are placed on the ground by the estimate at the newest
//! trace of their submap when an estimate is fed in (they then wait for the estimate to get
//! there), else by the submaps' own odometry. With the estimator's line map, an apex whose
//! measured forward distance fits the one an estimated line predicts ([`predicted_forward_m`])
//! belongs to that line; else [`Associator`] decides.

use std::collections::VecDeque;

use gprflow_geometry::{NonFinitePose, Planar, Track, wrap_angle};

use crate::associate::{AssociationParams, Associator, GroundPoint};
use crate::detect::{DetectParams, Hyperbola, Image, detect};
use crate::{Error, Result};

/// Longest gap between two estimates that is interpolated, ns.
pub const MAX_TRACK_GAP_NS: i64 = 1_000_000_000;

/// Below this `|cos|` of the angle between heading and line normal, the robot drives along
/// the line and the forward distance to it is ill-defined.
const MIN_CROSSING_COS: f64 = 0.2;

/// Where a submap lies along the drive: its first and newest trace (stamp, wheel distance,
/// odometry pose) and its width in columns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubmapSpan {
    /// The submap's id.
    pub id: u32,
    /// Stamp of its first trace, ns.
    pub start_ns: i64,
    /// Stamp of its newest trace, ns.
    pub end_ns: i64,
    /// Wheel distance at its first trace, m.
    pub start_distance_m: f64,
    /// Wheel distance at its newest trace, m.
    pub end_distance_m: f64,
    /// Odometry pose at its first trace.
    pub start_pose: Planar,
    /// Odometry pose at its newest trace.
    pub end_pose: Planar,
    /// Columns of its image (the first at `start`, the last at `end`).
    pub cols: usize,
}

impl SubmapSpan {
    /// The last column's index as a number (at least 1, so a one-column submap divides).
    fn last_column(&self) -> f64 {
        self.cols.saturating_sub(1).max(1) as f64
    }

    /// Wheel distance at fraction `frac` of the span (0: first trace, 1: newest), m.
    pub fn along_at(&self, frac: f64) -> f64 {
        self.start_distance_m + frac * (self.end_distance_m - self.start_distance_m)
    }
}

/// A hyperbola's apex placed on the drive by [`project_apex`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ApexOnTrack {
    /// Wheel distance where the antenna passed over the apex, m.
    pub along_distance_m: f64,
    /// When it passed, ns.
    pub apex_stamp_ns: i64,
    /// The apex on the ground in the submaps' odometry frame: straight between the span's end
    /// poses, plus the antenna ahead of the body along the interpolated heading.
    pub odometry_ground: GroundPoint,
}

/// Places the apex at `apex_column` (apex time `apex_time_ns`) of a submap on the drive,
/// interpolating the span linearly by column (heading: by the wrapped difference).
pub fn project_apex(span: &SubmapSpan, apex_column: f64, apex_time_ns: f64, antenna_forward_m: f64) -> ApexOnTrack {
    let frac = apex_column / span.last_column();
    let Planar {
        x_m: x0,
        y_m: y0,
        yaw_rad: yaw0,
    } = span.start_pose;
    let Planar {
        x_m: x1,
        y_m: y1,
        yaw_rad: yaw1,
    } = span.end_pose;
    let yaw = yaw0 + frac * wrap_angle(yaw1 - yaw0);
    let a = antenna_forward_m;
    ApexOnTrack {
        along_distance_m: span.along_at(frac),
        apex_stamp_ns: span.start_ns + (frac * (span.end_ns - span.start_ns) as f64) as i64,
        odometry_ground: GroundPoint {
            x_m: x0 + frac * (x1 - x0) + a * yaw.cos(),
            y_m: y0 + frac * (y1 - y0) + a * yaw.sin(),
            apex_time_ns,
        },
    }
}

/// The forward distance from the body at wheel distance `body_distance_m` to a line whose
/// apex lies at `apex_distance_m`, the antenna `antenna_forward_m` ahead of the body, m
/// (negative: the line is behind).
pub fn forward_distance_m(apex_distance_m: f64, antenna_forward_m: f64, body_distance_m: f64) -> f64 {
    apex_distance_m + antenna_forward_m - body_distance_m
}

/// The point `forward_m` ahead of `pose` along its heading, with the apex time.
pub fn ground_ahead(pose: Planar, forward_m: f64, apex_time_ns: f64) -> GroundPoint {
    GroundPoint {
        x_m: pose.x_m + forward_m * pose.yaw_rad.cos(),
        y_m: pose.y_m + forward_m * pose.yaw_rad.sin(),
        apex_time_ns,
    }
}

/// The forward distance from `pose` to the line `x cos(theta) + y sin(theta) = rho` (eq. 5.6),
/// m; `None` when the heading runs along the line.
pub fn predicted_forward_m(pose: Planar, rho_m: f64, theta_rad: f64) -> Option<f64> {
    let c = (pose.yaw_rad - theta_rad).cos();
    if c.abs() < MIN_CROSSING_COS {
        return None;
    }
    Some((rho_m - pose.x_m * theta_rad.cos() - pose.y_m * theta_rad.sin()) / c)
}

/// What [`Observer`] needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct ObserverParams {
    /// Hyperbola detection (its half aperture and separation also tell the same hyperbola).
    pub detect: DetectParams,
    /// Line association.
    pub association: AssociationParams,
    /// Sigma of the forward distance of each observation, m.
    pub sigma_m: f64,
    /// Antenna centre ahead of the body origin, m.
    pub antenna_forward_m: f64,
    /// Wave velocity in the ground that turns apex time into depth, m/ns.
    pub soil_velocity_m_per_ns: f64,
}

/// One line observation: a hyperbola's apex measured from the newest submap's end.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Observation {
    /// The newest submap's newest trace, where the forward distance is measured from, ns.
    pub stamp_ns: i64,
    /// The line the apex belongs to.
    pub line_id: u32,
    /// Forward distance from the body at `stamp_ns` to the line, m.
    pub forward_distance_m: f64,
    /// Its sigma, m.
    pub sigma_m: f64,
    /// Two-way time of the apex, ns.
    pub apex_time_ns: f64,
    /// Depth of the apex, m.
    pub depth_m: f64,
    /// Detection score.
    pub score: f64,
    /// The submap the apex was found in.
    pub submap_id: u32,
    /// Wheel distance of the apex, m.
    pub along_distance_m: f64,
    /// When the antenna passed over the apex, ns.
    pub apex_stamp_ns: i64,
    /// Fitted wave velocity of the hyperbola, m/ns.
    pub velocity_m_per_ns: f64,
}

/// A hyperbola already released: its apex and the newest trace of the submap it went out with.
#[derive(Debug, Clone, Copy)]
struct Sent {
    along_distance_m: f64,
    apex_time_ns: f64,
    submap_end_ns: i64,
}

/// A hyperbola that has reached the middle of a submap and waits for a stronger one nearby
/// or for the drive to leave it behind.
#[derive(Debug, Clone, Copy)]
struct Pending {
    along_distance_m: f64,
    apex_time_ns: f64,
    apex_stamp_ns: i64,
    velocity_m_per_ns: f64,
    score: f64,
    submap_id: u32,
    /// Newest trace of the submap it was found in: stamp, ns, and wheel distance, m.
    found_end_ns: i64,
    found_end_distance_m: f64,
    /// The apex in the submaps' odometry frame (used without an estimate).
    odometry_ground: GroundPoint,
}

/// The newest submap's end: where observations are measured from.
#[derive(Debug, Clone, Copy)]
struct Newest {
    id: u32,
    end_ns: i64,
    end_distance_m: f64,
    middle_distance_m: f64,
}

/// Hyperbolas in, line observations out; see the [module](self).
#[derive(Debug)]
pub struct Observer {
    params: ObserverParams,
    associator: Associator,
    pending: Vec<Pending>,
    sent: VecDeque<Sent>,
    newest: Option<Newest>,
    /// The estimate, when fed in: the association frame.
    estimate: Option<Track>,
    /// The estimator's newest line map: `(id, rho_m, theta_rad)`.
    line_map: Vec<(u32, f64, f64)>,
    hyperbolas: u64,
    released: u64,
    cut_by_turns: u64,
}

impl Observer {
    /// An observer; with `with_estimate`, apexes are placed by the estimate fed to
    /// [`Observer::add_estimate`] (and wait for it), else by the submaps' odometry.
    ///
    /// # Errors
    /// [`Error::Param`] for association parameters out of range.
    pub fn new(params: ObserverParams, with_estimate: bool) -> Result<Self> {
        Ok(Self {
            associator: Associator::new(params.association.clone())?,
            params,
            pending: Vec::new(),
            sent: VecDeque::new(),
            newest: None,
            estimate: with_estimate.then(Track::new),
            line_map: Vec::new(),
            hyperbolas: 0,
            released: 0,
            cut_by_turns: 0,
        })
    }

    /// Adds an estimated pose (ignored without `with_estimate`).
    ///
    /// # Errors
    /// A pose that is not finite (not added).
    pub fn add_estimate(&mut self, stamp_ns: i64, pose: Planar) -> std::result::Result<(), NonFinitePose> {
        match self.estimate.as_mut() {
            Some(track) => track.insert(stamp_ns, pose),
            None => Ok(()),
        }
    }

    /// Replaces the estimator's line map, `(id, rho_m, theta_rad)` each; lines that are not
    /// finite are left out.
    pub fn set_line_map(&mut self, lines: impl IntoIterator<Item = (u32, f64, f64)>) {
        self.line_map = lines
            .into_iter()
            .filter(|(_, rho_m, theta_rad)| rho_m.is_finite() && theta_rad.is_finite())
            .collect();
    }

    /// Searches a submap's image for hyperbolas and returns the observations the drive has
    /// now left behind.
    ///
    /// # Errors
    /// [`Error::Shape`] for a span whose distances are not finite or an image that cannot be
    /// searched: the submap is skipped, nothing changes.
    pub fn observe(&mut self, span: &SubmapSpan, image: &Image<'_>) -> Result<Vec<Observation>> {
        if !(span.start_distance_m.is_finite() && span.end_distance_m.is_finite()) {
            return Err(Error::Shape(format!(
                "start/end_distance_m: {} / {}",
                span.start_distance_m, span.end_distance_m
            )));
        }
        let found = detect(image, &self.params.detect)?;
        Ok(self.add_hyperbolas(span, found))
    }

    /// Takes the hyperbolas `found` in a submap (those whose apex has reached its middle) and
    /// returns the observations the drive has now left behind.
    pub fn add_hyperbolas(&mut self, span: &SubmapSpan, found: Vec<Hyperbola>) -> Vec<Observation> {
        // submaps made in between were not searched: the straight drive ended there
        if self.newest.is_some_and(|n| span.id != n.id.wrapping_add(1)) {
            self.break_drive();
        }
        self.hyperbolas += found.len() as u64;
        // forget what no longer shares traces with this submap
        while self.sent.front().is_some_and(|s| s.submap_end_ns < span.start_ns) {
            self.sent.pop_front();
        }
        let last = span.last_column();
        // an apex is taken once it reaches the middle of the submap: seen with as much ground
        // on either side as the submap holds, its fit is not pulled by the edge
        for h in found.into_iter().filter(|h| h.apex_column <= 0.5 * last) {
            let apex = project_apex(span, h.apex_column, h.apex_time_ns, self.params.antenna_forward_m);
            let along = apex.along_distance_m;
            if self
                .sent
                .iter()
                .any(|s| self.same(s.along_distance_m, s.apex_time_ns, along, h.apex_time_ns))
            {
                continue;
            }
            let candidate = Pending {
                along_distance_m: along,
                apex_time_ns: h.apex_time_ns,
                apex_stamp_ns: apex.apex_stamp_ns,
                velocity_m_per_ns: h.velocity_m_per_ns,
                score: h.score,
                submap_id: span.id,
                found_end_ns: span.end_ns,
                found_end_distance_m: span.end_distance_m,
                odometry_ground: apex.odometry_ground,
            };
            match self
                .pending
                .iter()
                .position(|p| self.same(p.along_distance_m, p.apex_time_ns, along, h.apex_time_ns))
            {
                Some(i) if self.pending[i].score < candidate.score => self.pending[i] = candidate,
                Some(_) => {}
                None => self.pending.push(candidate),
            }
        }
        self.newest = Some(Newest {
            id: span.id,
            end_ns: span.end_ns,
            end_distance_m: span.end_distance_m,
            middle_distance_m: span.along_at(0.5),
        });
        self.release(false)
    }

    /// Releases every hyperbola still pending (at the end of the drive).
    pub fn finish(&mut self) -> Vec<Observation> {
        self.release(true)
    }

    /// The drive stopped being straight: submaps the submap stage made were not searched here
    /// (turning or reversing ones, not sent or not valid), so this submap's id does not follow
    /// the newest's. The hyperbolas still pending are dropped ([`Observer::cut_by_turns`]) and
    /// this submap starts afresh. Their forward distance would be measured from a submap
    /// after the turn: the wheel distance along the turn's path, taken along the new heading
    /// (metres off: one such observation of a row's end turned a 21-minute lawnmower's whole
    /// map by 0.8 rad). It cannot be measured from the last straight submap either: an
    /// observation is stamped no earlier than the submap that releases it.
    fn break_drive(&mut self) {
        if !self.pending.is_empty() {
            tracing::debug!(
                hyperbolas = self.pending.len(),
                "lines: the drive turned before it left these hyperbolas behind; dropped"
            );
        }
        self.cut_by_turns += self.pending.len() as u64;
        self.pending.clear();
        self.newest = None;
    }

    /// Hyperbolas dropped so far because the drive turned before it left them behind: the
    /// next submap searched did not follow the one before (its id skips those made between).
    pub fn cut_by_turns(&self) -> u64 {
        self.cut_by_turns
    }

    /// Hyperbolas detected so far.
    pub fn hyperbolas(&self) -> u64 {
        self.hyperbolas
    }

    /// Observations released so far.
    pub fn released(&self) -> u64 {
        self.released
    }

    /// Lines the associator knows.
    pub fn line_count(&self) -> usize {
        self.associator.line_count()
    }

    /// Same hyperbola: apexes within the half aperture along track and `separation_ns`.
    fn same(&self, along_a: f64, time_a: f64, along_b: f64, time_b: f64) -> bool {
        let det = &self.params.detect;
        (along_a - along_b).abs() < det.half_aperture_m && (time_a - time_b).abs() < det.separation_ns
    }

    /// Where an apex lies in the association frame: the estimate at the newest trace of the
    /// submap it was found in, moved back along the heading by the wheel distance from the
    /// apex (the nearest pose when the estimate does not reach it: at the end of a run); or
    /// the submaps' odometry without an estimate.
    fn ground(&self, p: &Pending) -> GroundPoint {
        let Some(track) = &self.estimate else {
            return p.odometry_ground;
        };
        let pose = track
            .at(p.found_end_ns, MAX_TRACK_GAP_NS)
            .or_else(|| track.last_stamp_ns().and_then(|last| track.at(last, 0)));
        match pose {
            Some(pose) => {
                let forward_m = forward_distance_m(
                    p.along_distance_m,
                    self.params.antenna_forward_m,
                    p.found_end_distance_m,
                );
                ground_ahead(pose, forward_m, p.apex_time_ns)
            }
            None => p.odometry_ground,
        }
    }

    /// The estimated line whose predicted forward distance (eq. 5.6, from the estimate at
    /// the newest trace of the apex's submap) is within `max_forward_m` of the measured one,
    /// the nearest, at a similar apex time. The estimate and its lines are solved together,
    /// so this holds where the estimate has drifted from the world.
    fn mapped_line(&self, p: &Pending) -> Option<u32> {
        let pose = self.estimate.as_ref()?.at(p.found_end_ns, MAX_TRACK_GAP_NS)?;
        let measured_m = forward_distance_m(
            p.along_distance_m,
            self.params.antenna_forward_m,
            p.found_end_distance_m,
        );
        let gate = self.params.association.max_forward_m;
        self.line_map
            .iter()
            .filter(|(id, _, _)| self.associator.same_depth(*id, p.apex_time_ns))
            .filter_map(|&(id, rho_m, theta_rad)| {
                let predicted_m = predicted_forward_m(pose, rho_m, theta_rad)?;
                let miss = (predicted_m - measured_m).abs();
                tracing::debug!(
                    line = id,
                    predicted_m,
                    measured_m,
                    "forward distance against the line map"
                );
                (miss <= gate).then_some((miss, id))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, id)| id)
    }

    /// Releases the pending hyperbolas the drive has left behind (all of them with `all`),
    /// measured from the newest submap's end.
    fn release(&mut self, all: bool) -> Vec<Observation> {
        let Some(newest) = self.newest else {
            return Vec::new();
        };
        let half = self.params.detect.half_aperture_m;
        // with the estimate as the association frame, an apex also waits for it to arrive
        let placed = |p: &Pending| match &self.estimate {
            Some(t) => t.last_stamp_ns().is_some_and(|last| last >= p.found_end_ns),
            None => true,
        };
        let (ready, waiting): (Vec<Pending>, Vec<Pending>) = std::mem::take(&mut self.pending)
            .into_iter()
            .partition(|p| all || ((p.along_distance_m - newest.middle_distance_m).abs() > half && placed(p)));
        self.pending = waiting;
        let mut observations = Vec::with_capacity(ready.len());
        for p in ready {
            let ground = self.ground(&p);
            let line_id = match self.mapped_line(&p) {
                Some(id) => {
                    self.associator.add(id, ground);
                    id
                }
                None => self.associator.associate(ground),
            };
            let o = Observation {
                stamp_ns: newest.end_ns,
                line_id,
                forward_distance_m: forward_distance_m(
                    p.along_distance_m,
                    self.params.antenna_forward_m,
                    newest.end_distance_m,
                ),
                sigma_m: self.params.sigma_m,
                apex_time_ns: p.apex_time_ns,
                depth_m: 0.5 * self.params.soil_velocity_m_per_ns * p.apex_time_ns,
                score: p.score,
                submap_id: p.submap_id,
                along_distance_m: p.along_distance_m,
                apex_stamp_ns: p.apex_stamp_ns,
                velocity_m_per_ns: p.velocity_m_per_ns,
            };
            tracing::debug!(
                submap = p.submap_id,
                line = line_id,
                ground_x_m = ground.x_m,
                ground_y_m = ground.y_m,
                forward_m = o.forward_distance_m,
                apex_ns = p.apex_time_ns,
                velocity = p.velocity_m_per_ns,
                score = p.score,
                "line observation"
            );
            observations.push(o);
            self.released += 1;
            self.sent.push_back(Sent {
                along_distance_m: p.along_distance_m,
                apex_time_ns: p.apex_time_ns,
                submap_end_ns: newest.end_ns,
            });
        }
        observations
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Tolerance of the interpolations, which are exact up to rounding.
    const TOL: f64 = 1e-12;

    fn pose(x_m: f64, y_m: f64, yaw_rad: f64) -> Planar {
        Planar { x_m, y_m, yaw_rad }
    }

    /// A 2 m submap from wheel distance `start_m`, driving along x at 1 m/s, 1 cm per column.
    fn span(id: u32, start_m: f64) -> SubmapSpan {
        let end_m = start_m + 2.0;
        SubmapSpan {
            id,
            start_ns: (start_m * 1e9) as i64,
            end_ns: (end_m * 1e9) as i64,
            start_distance_m: start_m,
            end_distance_m: end_m,
            start_pose: pose(start_m, 0.0, 0.0),
            end_pose: pose(end_m, 0.0, 0.0),
            cols: 201,
        }
    }

    fn hyperbola(apex_column: f64, apex_time_ns: f64, score: f64) -> Hyperbola {
        Hyperbola {
            apex_column,
            apex_time_ns,
            velocity_m_per_ns: 0.1,
            score,
        }
    }

    fn observer(with_estimate: bool) -> Observer {
        let params = ObserverParams {
            detect: DetectParams::default(),
            association: AssociationParams::default(),
            sigma_m: 0.05,
            antenna_forward_m: 0.25,
            soil_velocity_m_per_ns: 0.1,
        };
        Observer::new(params, with_estimate).expect("valid parameters")
    }

    #[test]
    fn an_apex_is_placed_by_its_column_across_the_span() {
        let s = SubmapSpan {
            start_pose: pose(1.0, 2.0, 0.0),
            end_pose: pose(3.0, 2.0, 0.0),
            ..span(7, 10.0)
        };
        let a = project_apex(&s, 50.0, 30.0, 0.5);
        assert!((a.along_distance_m - 10.5).abs() < TOL, "{a:?}");
        assert_eq!(a.apex_stamp_ns, 10_500_000_000);
        assert!((a.odometry_ground.x_m - 2.0).abs() < TOL && (a.odometry_ground.y_m - 2.0).abs() < TOL);
        assert_eq!(a.odometry_ground.apex_time_ns, 30.0);
    }

    #[test]
    fn the_heading_is_interpolated_across_the_wrap() {
        use std::f64::consts::PI;
        let s = SubmapSpan {
            start_pose: pose(0.0, 0.0, PI - 0.1),
            end_pose: pose(0.0, 0.0, -PI + 0.1),
            ..span(0, 0.0)
        };
        // halfway the heading is pi (not 0): the antenna 1 m ahead lies at x = -1
        let a = project_apex(&s, 100.0, 0.0, 1.0);
        assert!((a.odometry_ground.x_m + 1.0).abs() < 1e-9, "{a:?}");
        assert!(a.odometry_ground.y_m.abs() < 1e-9, "{a:?}");
    }

    #[test]
    fn the_forward_distance_is_negative_behind_and_the_prediction_needs_a_crossing() {
        assert!((forward_distance_m(11.0, 0.5, 12.0) + 0.5).abs() < TOL);
        assert!((forward_distance_m(11.0, 0.5, 10.0) - 1.5).abs() < TOL);
        // the line x = 3 seen from (1, 5) heading along +x (and along -x)
        let ahead = predicted_forward_m(pose(1.0, 5.0, 0.0), 3.0, 0.0).expect("crossing");
        assert!((ahead - 2.0).abs() < TOL);
        let behind = predicted_forward_m(pose(1.0, 5.0, std::f64::consts::PI), 3.0, 0.0).expect("crossing");
        assert!((behind + 2.0).abs() < TOL);
        assert_eq!(
            predicted_forward_m(pose(1.0, 5.0, 1.5), 3.0, 0.0),
            None,
            "driving along the line"
        );
        let ground = ground_ahead(pose(1.0, 5.0, std::f64::consts::FRAC_PI_2), 2.0, 9.0);
        assert!((ground.x_m - 1.0).abs() < TOL && (ground.y_m - 7.0).abs() < TOL);
    }

    #[test]
    fn a_hyperbola_seen_in_overlapping_submaps_goes_out_once_the_strongest() {
        let mut o = observer(false);
        // at 0.9 m, near the middle of the first submap (1.0 m): waits
        assert!(
            o.add_hyperbolas(&span(1, 0.0), vec![hyperbola(90.0, 20.0, 5.0)])
                .is_empty()
        );
        // again, stronger, in the next submap, whose middle (1.5 m) has left it behind;
        // one past the middle (column 150) is not taken
        let sent = o.add_hyperbolas(
            &span(2, 0.5),
            vec![hyperbola(40.0, 20.5, 8.0), hyperbola(150.0, 40.0, 99.0)],
        );
        assert_eq!(sent.len(), 1, "{sent:?}");
        let s = sent[0];
        assert_eq!((s.submap_id, s.score, s.stamp_ns), (2, 8.0, 2_500_000_000));
        assert!((s.along_distance_m - 0.9).abs() < TOL);
        assert!((s.forward_distance_m - (0.9 + 0.25 - 2.5)).abs() < TOL);
        assert!((s.depth_m - 1.025).abs() < TOL);
        assert_eq!(s.apex_stamp_ns, 900_000_000);
        // while the submaps share traces, the same apex is not taken again; another one waits
        // for the end
        assert!(
            o.add_hyperbolas(
                &span(3, 0.6),
                vec![hyperbola(35.0, 20.0, 9.0), hyperbola(90.0, 40.0, 3.0)]
            )
            .is_empty()
        );
        let last = o.finish();
        assert_eq!(last.len(), 1, "{last:?}");
        assert!((last[0].along_distance_m - 1.5).abs() < TOL);
        assert_ne!(last[0].line_id, s.line_id, "another depth, another line");
        assert_eq!((o.hyperbolas(), o.released(), o.line_count()), (5, 2, 2));
    }

    #[test]
    fn a_turn_drops_what_it_would_measure_across() {
        let mut o = observer(false);
        // at 0.9 m, near the middle of the first submap: waits for the drive to leave it
        assert!(
            o.add_hyperbolas(&span(1, 0.0), vec![hyperbola(90.0, 20.0, 5.0)])
                .is_empty()
        );
        // the drive turns (submap 2, turning, is not searched); the straight submap after the
        // turn would have released it, measured along the turn
        assert!(o.add_hyperbolas(&span(3, 4.0), Vec::new()).is_empty());
        assert!(o.finish().is_empty());
        assert_eq!((o.hyperbolas(), o.released(), o.cut_by_turns()), (1, 0, 1));
        // a hyperbola found after the turn goes out as before, measured from after it
        o.add_hyperbolas(&span(4, 4.1), vec![hyperbola(90.0, 20.0, 5.0)]);
        let sent = o.add_hyperbolas(&span(5, 4.6), Vec::new());
        assert_eq!(sent.len(), 1, "{sent:?}");
        assert!((sent[0].forward_distance_m - (5.0 + 0.25 - 6.6)).abs() < TOL);
        assert_eq!((o.released(), o.cut_by_turns()), (1, 1));
        // three turning submaps (ids 7-9) in between
        assert!(
            o.add_hyperbolas(&span(6, 4.7), vec![hyperbola(90.0, 30.0, 5.0)])
                .is_empty()
        );
        assert!(o.add_hyperbolas(&span(10, 9.0), Vec::new()).is_empty());
        assert_eq!((o.released(), o.cut_by_turns()), (1, 2));
    }

    #[test]
    fn with_an_estimate_an_apex_waits_for_it_and_is_placed_by_it() {
        let mut o = observer(true);
        o.add_hyperbolas(&span(1, 0.0), vec![hyperbola(90.0, 20.0, 5.0)]);
        assert!(
            o.add_hyperbolas(&span(2, 0.5), Vec::new()).is_empty(),
            "no estimate at 2 s yet"
        );
        assert!(o.add_estimate(0, pose(f64::NAN, 0.0, 0.0)).is_err());
        o.add_estimate(2_000_000_000, pose(100.0, 50.0, 0.0)).expect("finite");
        let sent = o.add_hyperbolas(&span(3, 0.6), Vec::new());
        assert_eq!(sent.len(), 1, "{sent:?}");
        // the forward distance is measured from the newest submap's end (2.6 m)
        assert!((sent[0].forward_distance_m - (0.9 + 0.25 - 2.6)).abs() < TOL);
        assert_eq!(sent[0].stamp_ns, 2_600_000_000);
    }

    #[test]
    fn a_span_without_distances_is_refused_and_changes_nothing() {
        let mut o = observer(false);
        let pixels = vec![0.0_f32; 4];
        let image = Image {
            pixels: &pixels,
            rows: 2,
            cols: 2,
            resolution_m: 0.01,
            sample_interval_ns: 0.1,
        };
        let bad = SubmapSpan {
            end_distance_m: f64::NAN,
            ..span(1, 0.0)
        };
        let e = o.observe(&bad, &image).expect_err("refused");
        assert!(
            matches!(&e, Error::Shape(why) if why.starts_with("start/end_distance_m: 0 / NaN")),
            "{e:?}"
        );
        assert_eq!(o.hyperbolas(), 0);
    }

    #[test]
    fn the_line_map_keeps_finite_lines_only() {
        let mut o = observer(true);
        o.set_line_map([(1, 3.0, 0.0), (2, f64::NAN, 0.0), (3, 1.0, f64::INFINITY)]);
        assert_eq!(o.line_map, vec![(1, 3.0, 0.0)]);
    }
}
