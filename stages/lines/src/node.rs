//! The `lines` stage: submaps in, [`LineObservation`]s out (seed 000 §5.4).
//!
//! Every valid submap is searched for hyperbolas ([`mod@crate::detect`]). A hyperbola is taken
//! from the submaps where its apex has reached the middle (seen with as much ground on both
//! sides as the submap holds, so the edge does not pull the fit). Submaps overlap, so the
//! same hyperbola (apexes within the half aperture along track and `separation_ns` in time)
//! comes again and again: the strongest is kept, and sent once the drive has left it more
//! than the half aperture behind the middle; a wavelet side lobe reaching the middle first
//! thus gives way to the hyperbola itself. One already sent is not sent again while the
//! submaps still share traces. The observation is stamped with the newest submap's newest
//! trace and carries the forward distance from the body there to the line,
//! `s_apex + antenna_forward_m - s_end` in wheel distance `s` (negative: the line is
//! behind), and the line id from [`crate::associate`]. Apexes are placed on the ground by the
//! estimate at the newest trace of their submap when the `estimate` feedback input is
//! connected (it then waits for the estimate to get there), else by the submaps' own
//! odometry (wheel and gyro dead reckoning, which drifts over a long drive). With the
//! estimator's line map as a second feedback input (`lines`), an apex whose measured forward
//! distance fits the one an estimated line predicts from the estimated pose belongs to that
//! line: the two are solved together, so this holds where both have drifted from the world.

use std::collections::VecDeque;

use gprflow_geometry::{Planar, Track, wrap_angle};
use gprflow_msg::{Header, LineMap, LineObservation, Message, StateEstimate, Submap, Time};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use crate::associate::{AssociationParams, Associator, GroundPoint};
use crate::detect::{DetectParams, Image, detect};
use crate::{Error, positive};

/// Parameters of the `lines` stage.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LinesParams {
    /// Hyperbola detection.
    pub detect: DetectParams,
    /// Line association.
    pub association: AssociationParams,
    /// Sigma of the forward distance sent with each observation, m (default 0.05).
    pub sigma_m: f64,
    /// Antenna centre ahead of the body origin, m (default 0).
    pub antenna_forward_m: f64,
    /// Wave velocity in the ground that turns apex time into depth, m/ns (default 0.1).
    pub soil_velocity_m_per_ns: f64,
    /// Search submaps that broke the validity rule too (turning, reversing; default false:
    /// the forward distance assumes a straight drive across the submap).
    pub include_invalid: bool,
}

impl Default for LinesParams {
    fn default() -> Self {
        Self {
            detect: DetectParams::default(),
            association: AssociationParams::default(),
            sigma_m: 0.05,
            antenna_forward_m: 0.0,
            soil_velocity_m_per_ns: 0.1,
            include_invalid: false,
        }
    }
}

impl LinesParams {
    fn check(&self) -> crate::Result<()> {
        self.detect.check()?;
        self.association.check()?;
        positive("sigma_m", self.sigma_m)?;
        positive("soil_velocity_m_per_ns", self.soil_velocity_m_per_ns)?;
        if !self.antenna_forward_m.is_finite() {
            return Err(Error::Param {
                key: "antenna_forward_m",
                message: format!("must be finite, got {}", self.antenna_forward_m),
            });
        }
        Ok(())
    }
}

fn param_error(e: Error) -> StageError {
    match e {
        Error::Param { key, message } => StageError::Params(ParamError {
            path: key.split('.').map(str::to_owned).collect(),
            message,
        }),
        other => StageError::failed(other),
    }
}

/// A hyperbola already sent: its apex and the newest trace of the submap it went out with.
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
    /// The apex in the submaps' odometry frame (used without the `estimate` input).
    odometry_ground: GroundPoint,
}

/// The newest submap's end: where observations are measured from.
#[derive(Debug, Clone, Copy)]
struct Newest {
    end_ns: i64,
    end_distance_m: f64,
    middle_distance_m: f64,
}

#[derive(Debug, Default)]
struct Counts {
    submaps: u64,
    invalid: u64,
    hyperbolas: u64,
    sent: u64,
}

/// The lines stage.
#[derive(Debug)]
pub struct LinesStage {
    params: LinesParams,
    out: Output<LineObservation>,
    associator: Associator,
    pending: Vec<Pending>,
    sent: VecDeque<Sent>,
    newest: Option<Newest>,
    /// The estimate (feedback input), when connected: the association frame.
    estimate: Option<Track>,
    /// The estimator's newest line map (feedback input): `(id, rho_m, theta_rad)`.
    line_map: Vec<(u32, f64, f64)>,
    counts: Counts,
    drops: Drops,
}

/// Longest gap between two estimates that is interpolated, ns.
const MAX_TRACK_GAP_NS: i64 = 1_000_000_000;

/// The planar pose of a pose message.
fn planar(p: &gprflow_msg::Pose) -> Planar {
    let q = &p.orientation;
    Planar::from_quaternion(p.position.x, p.position.y, [q.x, q.y, q.z, q.w])
}

impl LinesStage {
    /// Same hyperbola: apexes within the half aperture along track and `separation_ns`.
    fn same(&self, along_a: f64, time_a: f64, along_b: f64, time_b: f64) -> bool {
        let det = &self.params.detect;
        (along_a - along_b).abs() < det.half_aperture_m && (time_a - time_b).abs() < det.separation_ns
    }

    fn on_submap(&mut self, m: &Submap<'_>, out: &mut Outputs) -> std::result::Result<Option<String>, StageError> {
        let (rows, cols) = (m.rows as usize, m.cols as usize);
        if !(m.start_distance_m.is_finite() && m.end_distance_m.is_finite()) {
            return Ok(Some(format!(
                "start/end_distance_m: {} / {}",
                m.start_distance_m, m.end_distance_m
            )));
        }
        let image = Image {
            pixels: &m.pixels,
            rows,
            cols,
            resolution_m: m.resolution_m,
            sample_interval_ns: m.sample_interval_ns,
        };
        let found = match detect(&image, &self.params.detect) {
            Ok(found) => found,
            Err(Error::Shape(why)) => return Ok(Some(why)),
            Err(e) => return Err(StageError::failed(e)),
        };
        self.counts.hyperbolas += found.len() as u64;
        let end_ns = m.header.stamp.to_ns();
        let start_ns = m.start_stamp.to_ns();
        // forget what no longer shares traces with this submap
        while self.sent.front().is_some_and(|s| s.submap_end_ns < start_ns) {
            self.sent.pop_front();
        }
        let last = cols.saturating_sub(1).max(1) as f64;
        let Planar {
            x_m: x0,
            y_m: y0,
            yaw_rad: yaw0,
        } = planar(&m.start_pose);
        let Planar {
            x_m: x1,
            y_m: y1,
            yaw_rad: yaw1,
        } = planar(&m.end_pose);
        let along_at = |frac: f64| m.start_distance_m + frac * (m.end_distance_m - m.start_distance_m);
        // an apex is taken once it reaches the middle of the submap: seen with as much ground
        // on either side as the submap holds, its fit is not pulled by the edge
        for h in found.into_iter().filter(|h| h.apex_column <= 0.5 * last) {
            let frac = h.apex_column / last;
            let along = along_at(frac);
            if self
                .sent
                .iter()
                .any(|s| self.same(s.along_distance_m, s.apex_time_ns, along, h.apex_time_ns))
            {
                continue;
            }
            // the apex on the ground: straight between the submap's end poses, plus the antenna
            let yaw = yaw0 + frac * wrap_angle(yaw1 - yaw0);
            let a = self.params.antenna_forward_m;
            let candidate = Pending {
                along_distance_m: along,
                apex_time_ns: h.apex_time_ns,
                apex_stamp_ns: start_ns + (frac * (end_ns - start_ns) as f64) as i64,
                velocity_m_per_ns: h.velocity_m_per_ns,
                score: h.score,
                submap_id: m.id,
                found_end_ns: end_ns,
                found_end_distance_m: m.end_distance_m,
                odometry_ground: GroundPoint {
                    x_m: x0 + frac * (x1 - x0) + a * yaw.cos(),
                    y_m: y0 + frac * (y1 - y0) + a * yaw.sin(),
                    apex_time_ns: h.apex_time_ns,
                },
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
            end_ns,
            end_distance_m: m.end_distance_m,
            middle_distance_m: along_at(0.5),
        });
        self.release(out, false)?;
        Ok(None)
    }

    /// Where an apex lies in the association frame: the estimate at the newest trace of the
    /// submap it was found in, moved back along the heading by the wheel distance from the
    /// apex (the nearest pose when the estimate does not reach it: at the end of a run); or
    /// the submaps' odometry without the `estimate` input.
    fn ground(&self, p: &Pending) -> GroundPoint {
        let Some(track) = &self.estimate else {
            return p.odometry_ground;
        };
        let pose = track
            .at(p.found_end_ns, MAX_TRACK_GAP_NS)
            .or_else(|| track.last_stamp_ns().and_then(|last| track.at(last, 0)));
        match pose {
            Some(Planar { x_m, y_m, yaw_rad }) => {
                let forward_m = p.along_distance_m + self.params.antenna_forward_m - p.found_end_distance_m;
                GroundPoint {
                    x_m: x_m + forward_m * yaw_rad.cos(),
                    y_m: y_m + forward_m * yaw_rad.sin(),
                    apex_time_ns: p.apex_time_ns,
                }
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
        let measured_m = p.along_distance_m + self.params.antenna_forward_m - p.found_end_distance_m;
        let gate = self.params.association.max_forward_m;
        self.line_map
            .iter()
            .filter(|(id, _, _)| self.associator.same_depth(*id, p.apex_time_ns))
            .filter_map(|&(id, rho_m, theta_rad)| {
                let c = (pose.yaw_rad - theta_rad).cos();
                // driving along the line: the forward distance is ill-defined
                if c.abs() < 0.2 {
                    return None;
                }
                let predicted_m = (rho_m - pose.x_m * theta_rad.cos() - pose.y_m * theta_rad.sin()) / c;
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

    /// Sends the pending hyperbolas the drive has left behind (all of them at the end),
    /// measured from the newest submap's end.
    fn release(&mut self, out: &mut Outputs, all: bool) -> std::result::Result<(), StageError> {
        let Some(newest) = self.newest else {
            return Ok(());
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
        for p in ready {
            let ground = self.ground(&p);
            let line_id = match self.mapped_line(&p) {
                Some(id) => {
                    self.associator.add(id, ground);
                    id
                }
                None => self.associator.associate(ground),
            };
            let msg = LineObservation {
                header: Header::new(newest.end_ns, "base_link"),
                line_id,
                forward_distance_m: p.along_distance_m + self.params.antenna_forward_m - newest.end_distance_m,
                sigma_m: self.params.sigma_m,
                apex_time_ns: p.apex_time_ns,
                depth_m: 0.5 * self.params.soil_velocity_m_per_ns * p.apex_time_ns,
                score: p.score as f32,
                submap_id: p.submap_id,
                along_distance_m: p.along_distance_m,
                apex_stamp: Time::from_ns(p.apex_stamp_ns),
                velocity_m_per_ns: p.velocity_m_per_ns,
            };
            tracing::debug!(
                submap = p.submap_id,
                line = line_id,
                ground_x_m = ground.x_m,
                ground_y_m = ground.y_m,
                forward_m = msg.forward_distance_m,
                apex_ns = p.apex_time_ns,
                velocity = p.velocity_m_per_ns,
                score = p.score,
                "line observation"
            );
            out.send(self.out, &msg)?;
            self.counts.sent += 1;
            self.sent.push_back(Sent {
                along_distance_m: p.along_distance_m,
                apex_time_ns: p.apex_time_ns,
                submap_end_ns: newest.end_ns,
            });
        }
        Ok(())
    }
}

impl Stage for LinesStage {
    type Params = LinesParams;
    const NAME: &'static str = "lines";
    const ABOUT: &'static str =
        "subsurface line features: hyperbola detection in submaps, forward-distance observations, line association";

    fn inputs() -> InputPorts {
        InputPorts::Fixed(vec![
            InputSpec {
                port: PortSpec::new("submap", Submap::TYPE_NAME),
                optional: false,
            },
            // the estimate, as a feedback input: where the apexes are for the association
            // (without it, the submaps' own odometry)
            InputSpec {
                port: PortSpec::new("estimate", StateEstimate::TYPE_NAME),
                optional: true,
            },
            // the estimator's lines, as a feedback input: an apex whose forward distance
            // fits one of them belongs to it (needs `estimate`)
            InputSpec {
                port: PortSpec::new("lines", LineMap::TYPE_NAME),
                optional: true,
            },
        ])
    }

    fn outputs(_: &Self::Params) -> std::result::Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("observation", LineObservation::TYPE_NAME)])
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        params.check().map_err(param_error)?;
        if ports.input("lines").is_some() && ports.input("estimate").is_none() {
            return Err(StageError::Params(ParamError {
                path: vec!["association".into()],
                message: "the `lines` input (the estimated line map) needs the `estimate` input: lines are \
                          matched by the forward distance predicted from the estimated pose"
                    .into(),
            }));
        }
        Ok(Self {
            associator: Associator::new(params.association.clone()).map_err(param_error)?,
            params,
            out: ports.output("observation")?,
            pending: Vec::new(),
            sent: VecDeque::new(),
            newest: None,
            estimate: ports.input("estimate").map(|_| Track::new()),
            line_map: Vec::new(),
            counts: Counts::default(),
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        if input.name() == "estimate" {
            let m: StateEstimate = input.decode()?;
            let pose = planar(&m.world_from_body.pose);
            if let Some(track) = self.estimate.as_mut()
                && let Err(e) = track.insert(m.header.stamp.to_ns(), pose)
            {
                self.drops.record(Self::NAME, &input, &e.to_string());
            }
            // observations go out on submaps only: a feedback message's stamp is older than
            // the output watermark
            return Ok(());
        }
        if input.name() == "lines" {
            let m: LineMap = input.decode()?;
            self.line_map = m
                .lines
                .iter()
                .filter(|l| l.rho_m.is_finite() && l.theta_rad.is_finite())
                .map(|l| (l.id, l.rho_m, l.theta_rad))
                .collect();
            return Ok(());
        }
        if input.name() != "submap" {
            return Ok(());
        }
        let m: Submap = input.decode()?;
        self.counts.submaps += 1;
        if !m.valid && !self.params.include_invalid {
            self.counts.invalid += 1;
            return Ok(());
        }
        if let Some(why) = self.on_submap(&m, out)? {
            self.drops.record(Self::NAME, &input, &why);
        }
        Ok(())
    }

    fn finish(&mut self, out: &mut Outputs) -> std::result::Result<(), StageError> {
        self.release(out, true)?;
        let c = &self.counts;
        tracing::info!(
            submaps = c.submaps,
            invalid = c.invalid,
            hyperbolas = c.hyperbolas,
            sent = c.sent,
            lines = self.associator.line_count(),
            "lines: {} observations of {} lines from {} submaps",
            c.sent,
            self.associator.line_count(),
            c.submaps
        );
        self.drops.report(Self::NAME);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_are_checked_with_their_keys() {
        assert!(LinesParams::default().check().is_ok());
        let bad = LinesParams {
            sigma_m: 0.0,
            ..LinesParams::default()
        };
        assert!(matches!(bad.check(), Err(Error::Param { key: "sigma_m", .. })));
        let bad = LinesParams {
            detect: DetectParams {
                velocities: 0,
                ..DetectParams::default()
            },
            ..LinesParams::default()
        };
        assert!(matches!(
            bad.check(),
            Err(Error::Param {
                key: "detect.velocities",
                ..
            })
        ));
    }

    #[test]
    fn wrap_keeps_angles_in_range() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-12);
    }
}
