//! The `register` stage: submaps in, [`Registration`]s out (seed 000 §4.3-4.5).
//!
//! The stage only moves messages: it decodes submaps and poses, hands them to the
//! [`LoopCloser`] ([`crate::closer`]: reference keeping, loop candidates, the method's
//! [`crate::closer::Matcher`], overlap stamps) and sends its matches as
//! [`Registration`]s. Every valid submap is put in ground order and kept as a reference (one
//! every `reference_spacing_m` of travel). A new submap, the query, is placed in the
//! association frame (the estimate, read as a feedback input, or the ground truth for the
//! oracle association) and registered with the references that pass the loop-candidate
//! gates ([`crate::candidates`]). The method is the engineered correlation baseline, the
//! learned model, or the oracle (the ground-truth transform; evaluation only). Submaps
//! below the saliency gate are neither references nor queries; a match below the method's
//! own gate (peak correlation, or the learned "shared features" check) is not sent.
//!
//! A query waits until the association frame reaches it: the estimate (or truth) must cover
//! its oldest trace (its anchor with the oracle), so registrations go out slightly after
//! their submap. A registration carries the two anchor stamps and the shift between them;
//! with `stamps: overlap` a shift found on the grid (every method but the oracle) goes out
//! instead as the moments the two passes were over the middle of their shared ground (the
//! submaps' column stamps, [`crate::closer::overlap_stamps`]) with an along-track offset of
//! zero, free of the wheel's scale error that the grid, laid on wheel distance, puts into a
//! shift.

mod params;

use gprflow_geometry::Planar;
use gprflow_msg::{
    Covariance6, Header, Message, Point, Pose, PoseStamped, Quaternion, Registration, RegistrationAttempt,
    StateEstimate, Submap, Time,
};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use crate::closer::{Attempt, Engineered, Keyed, Learned, LoopCloser, Match, Matcher, Oracle, SubmapIn, Zeroth};
use crate::learned::{Head, Model};
use crate::stretch;

pub use crate::closer::{Association, Method, Stamps, ground_order};
pub use params::RegisterParams;

fn planar_of(p: &Pose) -> Planar {
    let q = &p.orientation;
    Planar::from_quaternion(p.position.x, p.position.y, [q.x, q.y, q.z, q.w])
}

/// Checks the message and builds the loop closer's submap; `Err` says what is wrong with it.
fn keyed(m: &Submap<'_>) -> std::result::Result<Keyed, String> {
    Keyed::new(&SubmapIn {
        id: m.id,
        rows: m.rows as usize,
        cols: m.cols as usize,
        resolution_m: m.resolution_m,
        pixels: &m.pixels,
        column_stamps_ns: &m.column_stamps_ns,
        start_distance_m: m.start_distance_m,
        end_distance_m: m.end_distance_m,
        start_pose: planar_of(&m.start_pose),
        end_pose: planar_of(&m.end_pose),
        start_stamp_ns: m.start_stamp.to_ns(),
        end_stamp_ns: m.header.stamp.to_ns(),
    })
}

/// What happened to the submaps the loop closer never saw, and the registrations sent.
#[derive(Debug, Default)]
struct Counts {
    invalid: u64,
    not_salient: u64,
    sent: u64,
}

/// The register stage.
#[derive(Debug)]
pub struct RegisterStage {
    params: RegisterParams,
    closer: LoopCloser,
    out: Output<Registration>,
    /// The diagnostics output, when asked for.
    attempts: Option<Output<RegistrationAttempt>>,
    last_primary_ns: i64,
    counts: Counts,
    drops: Drops,
}

impl RegisterStage {
    /// Sends the matches of the queued submaps the association frame reaches (`all`: of all).
    fn process_pending(&mut self, stamp_ns: i64, out: &mut Outputs, all: bool) -> std::result::Result<(), StageError> {
        for m in self.closer.poll(all).map_err(StageError::failed)? {
            let msg = Registration {
                header: Header::new(stamp_ns, "base_link"),
                ..registration(&m)
            };
            out.send(self.out, &msg)?;
            self.counts.sent += 1;
        }
        if let Some(port) = self.attempts {
            let method = self.closer.method().name();
            for a in self.closer.take_attempts() {
                out.send(port, &attempt(stamp_ns, method, &a))?;
            }
        }
        Ok(())
    }
}

/// The diagnostics message of attempt `a`.
fn attempt(stamp_ns: i64, method: &str, a: &Attempt) -> RegistrationAttempt {
    RegistrationAttempt {
        header: Header::new(stamp_ns, "base_link"),
        reference_submap: a.reference,
        query_submap: a.query,
        reference_stamp: Time::from_ns(a.anchors_ns.0),
        query_stamp: Time::from_ns(a.anchors_ns.1),
        method: method.to_owned(),
        outcome: a.outcome.to_owned(),
        shift_m: a.shift_m,
        score: a.score,
        stretch: a.stretch,
    }
}

/// The registration of match `m`: the query at `m.stamps_ns.1` lies `m.along_m` along track
/// from the reference at `m.stamps_ns.0`; the other axes get a large variance (an
/// along-track-only measurement).
fn registration(m: &Match) -> Registration {
    const LOOSE: f64 = 1e4;
    let variance = m.variance_m2;
    let mut cov = [0.0; 36];
    for (i, v) in [variance, LOOSE, LOOSE, LOOSE, LOOSE, LOOSE].into_iter().enumerate() {
        cov[i * 7] = v;
    }
    Registration {
        header: Header::default(),
        reference_submap: m.reference,
        query_submap: m.query,
        reference_stamp: Time::from_ns(m.stamps_ns.0),
        query_stamp: Time::from_ns(m.stamps_ns.1),
        reference_from_query: Pose {
            position: Point {
                x: m.along_m,
                y: 0.0,
                z: 0.0,
            },
            orientation: Quaternion {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 1.0,
            },
        },
        covariance: Covariance6(cov),
        along_track_m: m.along_m,
        along_track_variance_m2: variance,
        score: m.score as f32,
        method: m.method.name().to_owned(),
    }
}

impl Stage for RegisterStage {
    type Params = RegisterParams;
    const NAME: &'static str = "register";
    const ABOUT: &'static str = "GPR submap registration (engineered correlation, learned model, or oracle) with loop candidates from the estimate";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            port("submap", Submap::TYPE_NAME, false),
            // the estimate, as a feedback input: where the submaps are (association: estimate)
            port("estimate", StateEstimate::TYPE_NAME, true),
            // ground truth: for the oracle association and the oracle method only
            port("truth", PoseStamped::TYPE_NAME, true),
        ])
    }

    fn outputs(params: &Self::Params) -> std::result::Result<Vec<PortSpec>, ParamError> {
        let mut ports = vec![PortSpec::new("registration", Registration::TYPE_NAME)];
        if params.diagnostics {
            ports.push(PortSpec::new("attempt", RegistrationAttempt::TYPE_NAME));
        }
        Ok(ports)
    }

    fn check_params(params: &Self::Params) -> std::result::Result<(), ParamError> {
        params.check()
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        let needs_truth = params.association == Association::Truth || params.method == Method::Oracle;
        if needs_truth && ports.input("truth").is_none() {
            return Err(ParamError::new(
                "method",
                "the oracle method and the truth association need the `truth` input (ground-truth poses)",
            )
            .into());
        }
        if params.association == Association::Estimate && ports.input("estimate").is_none() {
            return Err(ParamError::new(
                "association",
                "association `estimate` needs the `estimate` input (the estimator's state, as a feedback input)",
            )
            .into());
        }
        let stretches = stretch::factors(params.stretch_step, params.stretch_steps).map_err(StageError::failed)?;
        let matcher: Box<dyn Matcher> = match params.method {
            Method::Engineered => Box::new(Engineered::new(params.engineered.clone(), params.min_score)),
            Method::Learned => {
                let m = Model::load(&params.model, &params.head, params.onnxruntime.as_deref())
                    .map_err(StageError::failed)?;
                tracing::info!(
                    model = %params.model.display(),
                    head = %params.head.display(),
                    "register: learned model, {} channels, column stride {}, share threshold {}, agreement {}, sigma {} m",
                    m.head.channels,
                    m.head.column_stride,
                    m.head.share_threshold,
                    m.head.agreement.map_or("none".to_string(), |a| format!(
                        "{:.3} of the channels within {} m",
                        a.min_fraction, a.tolerance_m
                    )),
                    m.head.sigma_m
                );
                Box::new(Learned::new(m, stretches))
            }
            Method::Oracle => Box::new(Oracle),
            Method::Zeroth => Box::new(Zeroth {
                shift_m: Head::from_json(&params.head).map_err(StageError::failed)?.zeroth_m,
            }),
        };
        let closer = LoopCloser::new(params.closer(), matcher);
        let attempts = if params.diagnostics {
            Some(ports.output("attempt")?)
        } else {
            None
        };
        Ok(Self {
            closer: if attempts.is_some() {
                closer.keeping_attempts()
            } else {
                closer
            },
            attempts,
            params,
            out: ports.output("registration")?,
            last_primary_ns: i64::MIN,
            counts: Counts::default(),
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        match input.name() {
            "submap" => {
                self.last_primary_ns = self.last_primary_ns.max(input.stamp_ns());
                let m: Submap = input.decode()?;
                if !m.valid {
                    self.counts.invalid += 1;
                } else if m.saliency < self.params.min_saliency {
                    self.counts.not_salient += 1;
                } else {
                    match keyed(&m) {
                        Ok(e) => self.closer.push(e),
                        Err(why) => self.drops.record(Self::NAME, &input, &why),
                    }
                }
            }
            "truth" => {
                self.last_primary_ns = self.last_primary_ns.max(input.stamp_ns());
                let m: PoseStamped = input.decode()?;
                if let Err(e) = self.closer.add_truth(m.header.stamp.to_ns(), planar_of(&m.pose)) {
                    self.drops.record(Self::NAME, &input, &e.to_string());
                }
            }
            "estimate" => {
                let m: StateEstimate = input.decode()?;
                if let Err(e) = self
                    .closer
                    .add_estimate(m.header.stamp.to_ns(), planar_of(&m.world_from_body.pose))
                {
                    self.drops.record(Self::NAME, &input, &e.to_string());
                }
                // Registrations go out on primary inputs only: a feedback message's stamp is
                // older than the output watermark.
                return Ok(());
            }
            _ => return Ok(()),
        }
        self.process_pending(self.last_primary_ns, out, false)
    }

    fn finish(&mut self, out: &mut Outputs) -> std::result::Result<(), StageError> {
        if self.last_primary_ns > i64::MIN {
            self.process_pending(self.last_primary_ns, out, true)?;
        }
        let (c, n) = (self.closer.counts(), &self.counts);
        tracing::info!(
            sent = n.sent,
            pairs = c.pairs,
            queries = c.queries,
            rejected = c.rejected,
            references = self.closer.references(),
            invalid = n.invalid,
            not_salient = n.not_salient,
            never_placed = c.never_placed,
            stretched = c.stretched,
            encoded = c.encoded,
            "register ({}): {} registrations from {} candidate pairs ({} refused by the method's gate)",
            self.params.method.name(),
            n.sent,
            c.pairs,
            c.rejected
        );
        let (held, spilled) = self.closer.reference_bytes();
        tracing::info!(
            references = self.closer.references(),
            held_mib = format!("{:.1}", held as f64 / f64::from(1u32 << 20)),
            spilled_mib = format!("{:.1}", spilled as f64 / f64::from(1u32 << 20)),
            "register: reference store ({} m between references)",
            self.params.reference_spacing_m
        );
        self.drops.report(Self::NAME);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engineered::EngineeredParams;

    #[test]
    fn params_are_checked() {
        assert!(RegisterParams::default().check().is_ok());
        let bad = RegisterParams {
            min_score: 2.0,
            ..RegisterParams::default()
        };
        assert_eq!(bad.check().map_err(|e| e.key()), Err("min_score".into()));
        let bad = RegisterParams {
            sigma_m: Some(-1.0),
            ..RegisterParams::default()
        };
        assert_eq!(bad.check().map_err(|e| e.key()), Err("sigma_m".into()));
        for (steps, step) in [(1, f64::NAN), (1, 0.0), (10, 0.03)] {
            let bad = RegisterParams {
                stretch_steps: steps,
                stretch_step: step,
                ..RegisterParams::default()
            };
            assert_eq!(
                bad.check().map_err(|e| e.key()),
                Err("stretch_step".into()),
                "{steps} x {step}"
            );
        }
        // no search: the step is not used
        let off = RegisterParams {
            stretch_steps: 0,
            stretch_step: f64::NAN,
            ..RegisterParams::default()
        };
        assert!(off.check().is_ok());
        let bad = RegisterParams {
            engineered: EngineeredParams {
                min_overlap: 0.0,
                ..EngineeredParams::default()
            },
            ..RegisterParams::default()
        };
        assert_eq!(bad.check().map_err(|e| e.key()), Err("engineered.min_overlap".into()));
    }

    #[test]
    fn registration_carries_the_along_track_variance_in_x() {
        let m = registration(&Match {
            reference: 3,
            query: 9,
            stamps_ns: (10, 20),
            along_m: 0.25,
            variance_m2: 0.1 * 0.1,
            score: 0.8,
            method: Method::Engineered,
            stretch: 1.0,
        });
        assert_eq!((m.reference_submap, m.query_submap), (3, 9));
        assert_eq!((m.reference_stamp.to_ns(), m.query_stamp.to_ns()), (10, 20));
        assert!((m.covariance.0[0] - 0.01).abs() < 1e-15 && m.covariance.0[7] > 1.0);
        assert_eq!(m.reference_from_query.position.x, 0.25);
        assert_eq!(m.method, "engineered");
    }

    #[test]
    fn column_stamps_of_the_wrong_length_are_refused() {
        let m = Submap {
            rows: 1,
            cols: 3,
            resolution_m: 0.01,
            pixels: std::borrow::Cow::Owned(vec![0.0; 3]),
            column_stamps_ns: std::borrow::Cow::Owned(vec![0, 1]),
            ..Submap::default()
        };
        let why = keyed(&m).expect_err("two stamps for three columns");
        assert!(why.contains("column_stamps_ns: 2 values for 3 columns"), "{why}");
    }
}
