//! The `lines` stage: submaps in, [`LineObservation`]s out (seed 000 §5.4).
//!
//! Every valid submap goes to an [`Observer`] ([`mod@crate::observe`]), which searches it for
//! hyperbolas ([`mod@crate::detect`]), keeps each once, and returns the observations the drive
//! has left behind: stamped with the newest submap's newest trace, with the forward distance
//! from the body there to the line and the line id from [`crate::associate`]. The `estimate`
//! feedback input (when connected) places the apexes on the ground instead of the submaps' own
//! odometry (wheel and gyro dead reckoning, which drifts over a long drive); the estimator's
//! line map (`lines`) lets an apex join the estimated line whose predicted forward distance
//! fits the measured one. Submaps that break the validity rule (turning, reversing; not sent,
//! or not searched) end the straight drive the forward distances assume: at the next searched
//! submap, whose id does not follow the last one's, the hyperbolas still waiting to be left
//! behind are dropped, counted in the stage's summary (`cut_by_turns`).

use gprflow_geometry::Planar;
use gprflow_msg::{Header, LineMap, LineObservation, Message, StateEstimate, Submap, Time};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use crate::associate::AssociationParams;
use crate::detect::{DetectParams, Image};
use crate::observe::{Observation, Observer, ObserverParams, SubmapSpan};
use gprflow_params::positive;

use crate::Error;

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
    fn check(&self) -> gprflow_params::Result {
        self.detect.check()?;
        self.association.check()?;
        positive("sigma_m", self.sigma_m)?;
        positive("soil_velocity_m_per_ns", self.soil_velocity_m_per_ns)?;
        if !self.antenna_forward_m.is_finite() {
            return Err(ParamError::new(
                "antenna_forward_m",
                format!("must be finite, got {}", self.antenna_forward_m),
            ));
        }
        Ok(())
    }
}

impl LinesParams {
    /// What the [`Observer`] needs of these parameters.
    fn observer_params(&self) -> ObserverParams {
        ObserverParams {
            detect: self.detect.clone(),
            association: self.association.clone(),
            sigma_m: self.sigma_m,
            antenna_forward_m: self.antenna_forward_m,
            soil_velocity_m_per_ns: self.soil_velocity_m_per_ns,
        }
    }
}

#[derive(Debug, Default)]
struct Counts {
    submaps: u64,
    invalid: u64,
}

/// The lines stage.
#[derive(Debug)]
pub struct LinesStage {
    include_invalid: bool,
    out: Output<LineObservation>,
    observer: Observer,
    counts: Counts,
    drops: Drops,
}

/// The planar pose of a pose message.
fn planar(p: &gprflow_msg::Pose) -> Planar {
    let q = &p.orientation;
    Planar::from_quaternion(p.position.x, p.position.y, [q.x, q.y, q.z, q.w])
}

/// Where a submap lies along the drive.
fn span(m: &Submap<'_>) -> SubmapSpan {
    SubmapSpan {
        id: m.id,
        start_ns: m.start_stamp.to_ns(),
        end_ns: m.header.stamp.to_ns(),
        start_distance_m: m.start_distance_m,
        end_distance_m: m.end_distance_m,
        start_pose: planar(&m.start_pose),
        end_pose: planar(&m.end_pose),
        cols: m.cols as usize,
    }
}

/// The message of an observation.
fn message(o: &Observation) -> LineObservation {
    LineObservation {
        header: Header::new(o.stamp_ns, "base_link"),
        line_id: o.line_id,
        forward_distance_m: o.forward_distance_m,
        sigma_m: o.sigma_m,
        apex_time_ns: o.apex_time_ns,
        depth_m: o.depth_m,
        score: o.score as f32,
        submap_id: o.submap_id,
        along_distance_m: o.along_distance_m,
        apex_stamp: Time::from_ns(o.apex_stamp_ns),
        velocity_m_per_ns: o.velocity_m_per_ns,
    }
}

/// Splits the observations released at the end into those that can still go out (stamped
/// at `watermark_ns` or later) and those that cannot.
fn in_stamp_order(observations: Vec<Observation>, watermark_ns: i64) -> (Vec<Observation>, Vec<Observation>) {
    observations.into_iter().partition(|o| o.stamp_ns >= watermark_ns)
}

impl LinesStage {
    fn send(&self, observations: &[Observation], out: &mut Outputs) -> std::result::Result<(), StageError> {
        for o in observations {
            out.send(self.out, &message(o))?;
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

    fn check_params(params: &Self::Params) -> std::result::Result<(), ParamError> {
        params.check()
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        if ports.input("lines").is_some() && ports.input("estimate").is_none() {
            return Err(ParamError::new(
                "association",
                "the `lines` input (the estimated line map) needs the `estimate` input: lines are \
                 matched by the forward distance predicted from the estimated pose",
            )
            .into());
        }
        let with_estimate = ports.input("estimate").is_some();
        Ok(Self {
            observer: Observer::new(params.observer_params(), with_estimate).map_err(StageError::failed)?,
            include_invalid: params.include_invalid,
            out: ports.output("observation")?,
            counts: Counts::default(),
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        if input.name() == "estimate" {
            let m: StateEstimate = input.decode()?;
            let pose = planar(&m.world_from_body.pose);
            if let Err(e) = self.observer.add_estimate(m.header.stamp.to_ns(), pose) {
                self.drops.record(Self::NAME, &input, &e.to_string());
            }
            // observations go out on submaps only: a feedback message's stamp is older than
            // the output watermark
            return Ok(());
        }
        if input.name() == "lines" {
            let m: LineMap = input.decode()?;
            self.observer
                .set_line_map(m.lines.iter().map(|l| (l.id, l.rho_m, l.theta_rad)));
            return Ok(());
        }
        if input.name() != "submap" {
            return Ok(());
        }
        let m: Submap = input.decode()?;
        self.counts.submaps += 1;
        if !m.valid && !self.include_invalid {
            self.counts.invalid += 1;
            return Ok(());
        }
        let image = Image {
            pixels: &m.pixels,
            rows: m.rows as usize,
            cols: m.cols as usize,
            resolution_m: m.resolution_m,
            sample_interval_ns: m.sample_interval_ns,
        };
        match self.observer.observe(&span(&m), &image) {
            Ok(observations) => self.send(&observations, out),
            Err(Error::Shape(why)) => {
                self.drops.record(Self::NAME, &input, &why);
                Ok(())
            }
            Err(e) => Err(StageError::failed(e)),
        }
    }

    fn finish(&mut self, out: &mut Outputs) -> std::result::Result<(), StageError> {
        let watermark_ns = out.watermark_ns(self.out);
        let (last, late) = in_stamp_order(self.observer.finish(), watermark_ns);
        self.send(&last, out)?;
        if let Some(first) = late.first() {
            tracing::warn!(
                observations = late.len(),
                stamp_ns = first.stamp_ns,
                watermark_ns,
                "lines: the drive ended before it left its newest hyperbolas behind; their \
                 observations, measured at the last submap's end, are older than what the \
                 submaps' stream had already promised downstream (the recording goes on after \
                 its last submap), so they are not sent"
            );
        }
        let (c, o) = (&self.counts, &self.observer);
        let sent = o.released() - late.len() as u64;
        tracing::info!(
            submaps = c.submaps,
            invalid = c.invalid,
            hyperbolas = o.hyperbolas(),
            sent,
            late = late.len(),
            cut_by_turns = o.cut_by_turns(),
            lines = o.line_count(),
            "lines: {} observations of {} lines from {} submaps",
            sent,
            o.line_count(),
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
    fn what_the_end_releases_behind_the_promised_watermark_is_held_back() {
        let at = |stamp_ns: i64, line_id: u32| Observation {
            stamp_ns,
            line_id,
            ..Observation::default()
        };
        // the last submap ended at 314.58 s; the submaps' stream had promised 317.21 s
        let (sent, late) = in_stamp_order(vec![at(314_580, 1), at(314_580, 2)], 317_210);
        assert!(sent.is_empty());
        assert_eq!(late.iter().map(|o| o.line_id).collect::<Vec<_>>(), [1, 2]);
        // where the recording ends with its last submap, they go
        let (sent, late) = in_stamp_order(vec![at(317_210, 1)], 317_210);
        assert_eq!((sent.len(), late.len()), (1, 0));
    }

    #[test]
    fn params_are_checked_with_their_keys() {
        assert!(LinesParams::default().check().is_ok());
        let bad = LinesParams {
            sigma_m: 0.0,
            ..LinesParams::default()
        };
        assert_eq!(bad.check().map_err(|e| e.key()), Err("sigma_m".into()));
        let bad = LinesParams {
            detect: DetectParams {
                velocities: 0,
                ..DetectParams::default()
            },
            ..LinesParams::default()
        };
        assert_eq!(bad.check().map_err(|e| e.key()), Err("detect.velocities".into()));
    }
}
