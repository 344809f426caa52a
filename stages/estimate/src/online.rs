//! Online estimation from time-stamped measurements: creates states at a fixed rate, turns
//! IMU, wheel, GPR registration, line and prior-map measurements into factors, and runs the
//! [`Smoother`] once per state. Plain code: the `estimate` stage only converts messages.

use std::collections::HashMap;
use std::time::Instant;

use nalgebra::{DMatrix, Vector2, Vector3};

use crate::factor::Factor;
use crate::factors::{
    BetweenPose, LineDistance, NonHolonomic, PosePrior, PositionAxes, PositionFix, TrackOffset, VectorPrior,
};
use crate::graph::FactorGraph;
use crate::imu::{CombinedImuFactor, ImuParams, ImuPreintegration, NavKeys};
use crate::lie::Pose3;
use crate::lines::initial_line;
use crate::noise::{NoiseModel, RobustKernel};
use crate::relative::{WholeGraphInformation, dot};
use crate::smoother::{Smoother, SmootherParams};
use crate::values::{HoughLine, ImuBias, Values, VarId, Variable};
use crate::{Error, Result};

/// Settings of the online estimator.
#[derive(Debug, Clone, PartialEq)]
pub struct OnlineParams {
    /// States per second.
    pub state_rate_hz: f64,
    /// Smoother settings.
    pub smoother: SmootherParams,
    /// IMU noise and gravity.
    pub imu: ImuParams,
    /// Sigma of the wheel along-track distance between consecutive states, m.
    pub wheel_sigma_m: f64,
    /// Sigma of a GPR along-track registration when the message carries none, m.
    pub registration_sigma_m: f64,
    /// Use a registration's full relative pose instead of its along-track distance.
    pub registration_full_pose: bool,
    /// Huber threshold on registrations (whitened); 0 for none.
    pub registration_huber_k: f64,
    /// Largest difference between a new registration's along-track distance and the current
    /// estimate's, m, right after the estimate took a registration: one further from the
    /// estimate is dropped as a wrong match (0: off). The gate widens by
    /// `registration_gate_growth_mps` for every second the query's stamp lies after the newest
    /// query the estimate has solved with (or after the first state), as the dead reckoning
    /// drifts.
    pub registration_gate_m: f64,
    /// Widening of `registration_gate_m` per second without a registration, m/s.
    pub registration_gate_growth_mps: f64,
    /// Mahalanobis gate on registrations, in standard deviations (0: off): one whose
    /// along-track residual against the current estimate is further than this many standard
    /// deviations of its prediction is dropped as a wrong match. The prediction's variance is
    /// the estimate's marginal variance of the along-track distance between the two states
    /// (from the whole graph's information, [`crate::relative`]) plus the registration's own
    /// sigma squared, so the gate is as wide as the estimate is unsure of where the query lies
    /// on the reference's pass. Applies with `registration_gate_m` when both are set.
    pub registration_gate_sigmas: f64,
    /// Sigma of the offset across the reference's track that a registration is taken to
    /// imply, m (the relative pose's y; 0 for a 1-D registration): the two submaps share
    /// features, so the passes were close. Right for a rig that drives the same line again,
    /// wrong by the wander for passes that drift apart. 0 reads only the along-track distance.
    pub registration_across_sigma_m: f64,
    /// Minimum baseline between the two observations that initialise a line, m.
    pub line_min_baseline_m: f64,
    /// Mahalanobis gate on line observations, in standard deviations (0: off): an observation
    /// of a line the graph already holds whose forward distance is further from the one the
    /// current estimate predicts than this many standard deviations of the prediction is
    /// dropped as a wrong association. The prediction's variance is the estimate's marginal
    /// variance of the forward distance from the state to the line (state and line solved
    /// together, their correlation included; [`crate::relative`]) plus the observation's
    /// sigma squared.
    pub line_gate_sigmas: f64,
    /// Prior sigma on a new line's `(rho, theta)`.
    pub line_prior_sigma: f64,
    /// Sigma of the ground-vehicle constraint on lateral and vertical body velocity, m/s (0: off).
    pub nonholonomic_sigma_mps: f64,
    /// Prior on the first state.
    pub first_state: FirstStatePrior,
    /// When no origin is given ([`OnlineEstimator::set_origin`] or
    /// [`OnlineEstimator::wait_for_origin`] before the first sample), the first state's roll
    /// and pitch come from the mean specific force over this many seconds of IMU at the start
    /// (gravity alignment; yaw 0, position 0), and the first state is made at the end of that
    /// time. Assumes the vehicle is at rest or moving steadily then. 0: no alignment, the
    /// first state level at the first sample.
    pub gravity_align_s: f64,
}

/// Prior on the first state: the origin of the estimate's frame, and what is known of the
/// IMU's biases before the run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirstStatePrior {
    /// Pose sigma (rotation rad and translation m alike).
    pub pose_sigma: f64,
    /// Velocity sigma, m/s.
    pub velocity_sigma_mps: f64,
    /// Accelerometer turn-on bias sigma, m/s^2.
    pub acc_bias_sigma_mps2: f64,
    /// Gyroscope turn-on bias sigma, rad/s. Keep it near the sensor's datasheet value: with
    /// only wheel and IMU the gyro bias is weakly observable, and a loose prior lets the yaw
    /// drift with it (0.1 rad/s turned 90-degree corners into 70-degree ones on the simulated
    /// garage run).
    pub gyro_bias_sigma_radps: f64,
}

impl Default for FirstStatePrior {
    fn default() -> Self {
        Self {
            pose_sigma: 1e-3,
            velocity_sigma_mps: 0.1,
            acc_bias_sigma_mps2: 0.05,
            gyro_bias_sigma_radps: 5e-3,
        }
    }
}

impl Default for OnlineParams {
    fn default() -> Self {
        Self {
            state_rate_hz: 10.0,
            smoother: SmootherParams::default(),
            imu: ImuParams::xsens_mti30(),
            wheel_sigma_m: 0.02,
            registration_sigma_m: 0.05,
            registration_full_pose: false,
            registration_huber_k: 1.345,
            registration_gate_m: 0.0,
            registration_gate_growth_mps: 0.0,
            registration_gate_sigmas: 0.0,
            registration_across_sigma_m: 0.0,
            line_min_baseline_m: 1.0,
            line_gate_sigmas: 0.0,
            line_prior_sigma: 1.0,
            nonholonomic_sigma_mps: 0.1,
            first_state: FirstStatePrior::default(),
            gravity_align_s: 1.0,
        }
    }
}

/// `world_from_body` rotation with yaw 0 whose body frame sees gravity along `specific_force`
/// (the accelerometer's mean at rest: `+g` along the world's up): roll `atan2(f_y, f_z)`, pitch
/// `atan2(-f_x, |f_yz|)`.
#[must_use]
pub fn level_from_specific_force(specific_force: &Vector3<f64>) -> nalgebra::Matrix3<f64> {
    let f = specific_force;
    let roll = f.y.atan2(f.z);
    let pitch = (-f.x).atan2(f.y.hypot(f.z));
    nalgebra::Rotation3::from_euler_angles(roll, pitch, 0.0).into_inner()
}

/// What became of a registration ([`OnlineEstimator::registration`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RegistrationOutcome {
    /// Added as factors; `residual_m` is the current estimate's along-track distance
    /// between the two states minus the measured one, before the factor was added (where
    /// `sigma_m` was computed, the estimate as the registrations taken since it was solved
    /// move it), `gate_m` the gate it passed (0: off) and `sigma_m` the residual's predicted
    /// standard deviation (0: not computed).
    Added {
        /// m.
        residual_m: f64,
        /// m.
        gate_m: f64,
        /// m.
        sigma_m: f64,
    },
    /// Its stamps match no two distinct states.
    NoStates,
    /// Further than the gate `gate_m` from the current estimate (the fields as for `Added`):
    /// dropped.
    Gated {
        /// m.
        residual_m: f64,
        /// m.
        gate_m: f64,
        /// m.
        sigma_m: f64,
    },
}

/// A GPR registration between the states nearest two stamps.
#[derive(Debug, Clone, PartialEq)]
pub struct RegistrationMeasurement {
    /// Stamp of the reference submap.
    pub reference_stamp_ns: i64,
    /// Stamp of the query submap.
    pub query_stamp_ns: i64,
    /// `reference_from_query`.
    pub relative_pose: Pose3,
    /// Along-track distance, m.
    pub along_track_m: f64,
    /// Covariance `[rot x3, trans x3]` of the relative pose, if known.
    pub covariance: Option<DMatrix<f64>>,
}

/// One state's estimate, as published.
#[derive(Debug, Clone, PartialEq)]
pub struct StateOutput {
    /// Index of the state.
    pub index: u64,
    /// Stamp of the state, ns.
    pub stamp_ns: i64,
    /// Pose.
    pub pose: Pose3,
    /// Velocity in the world, m/s.
    pub velocity_mps: Vector3<f64>,
    /// IMU bias.
    pub bias: ImuBias,
    /// Pose covariance `[rot x3, trans x3]` given the older states, if computed.
    pub covariance: Option<DMatrix<f64>>,
    /// Wall time of the update, s.
    pub update_s: f64,
}

#[derive(Debug, Default)]
struct PendingLine {
    var: Option<VarId>,
    /// Observations before the line had a variable: `(state, distance, sigma)`.
    buffered: Vec<(usize, f64, f64)>,
}

/// The online estimator (see the module docs).
#[derive(Debug)]
pub struct OnlineEstimator {
    params: OnlineParams,
    graph: FactorGraph,
    values: Values,
    smoother: Smoother,
    states: Vec<NavKeys>,
    stamps_ns: Vec<i64>,
    pim: Option<ImuPreintegration>,
    last_imu: Option<(i64, Vector3<f64>, Vector3<f64>)>,
    wheel_distance_m: Option<f64>,
    wheel_at_state: Option<f64>,
    lines: HashMap<u32, PendingLine>,
    late_updates: u64,
    origin: Pose3,
    /// Drop IMU samples until [`OnlineEstimator::set_origin`] is called.
    waiting_for_origin: bool,
    dropped_before_origin: u64,
    /// An origin was set or is awaited: no gravity alignment.
    origin_given: bool,
    /// Gravity alignment: the first sample's stamp, the sum of the specific forces and their
    /// count so far.
    aligning: Option<(i64, Vector3<f64>, u64)>,
    /// The newest query stamp of the registrations added so far, and of those the estimate
    /// has solved with (the registration gate widens from it).
    registered_query_ns: Option<i64>,
    solved_query_ns: Option<i64>,
    /// Map fixes nearer the state to come than the newest one.
    waiting_fixes: Vec<WaitingFix>,
    /// Map fixes that waited for a state and found none within a period.
    unmatched_fixes: u64,
    /// The whole graph's information at the current estimate, for the Mahalanobis gate: made
    /// when a registration first needs it after an update, dropped at the next update.
    information: Option<WholeGraphInformation>,
    /// Compute every registration's predicted sigma, also where the gate needs none.
    report_sigmas: bool,
    /// Graph factors when the smoother last ran (the estimate is their solution).
    solved_factors: usize,
    /// Registrations taken since the last update, which condition the gate of later ones.
    taken: Vec<Taken>,
    /// Whole-graph factorisations made for the gate, and their wall time, s.
    gate_solves: (u64, f64),
    /// Line observations the line gate dropped.
    gated_lines: u64,
}

/// A registration taken since the last update.
#[derive(Debug)]
struct Taken {
    pi: VarId,
    pj: VarId,
    /// Against the estimate as last solved, m.
    residual_m: f64,
    /// m^2.
    measurement_var: f64,
    /// Known once the gate needed the whole-graph information.
    gain: Option<Gain>,
}

/// A taken registration's Kalman update of the estimate's Gaussian.
#[derive(Debug)]
struct Gain {
    /// Covariance (before it) times its gradient.
    u: Vec<f64>,
    /// Its predicted variance, m^2.
    variance: f64,
    /// Its residual against the estimate before it, m.
    residual_m: f64,
}

/// A map fix waiting for its state.
#[derive(Debug)]
struct WaitingFix {
    stamp_ns: i64,
    xy_m: Vector2<f64>,
    noise: NoiseModel,
}

impl OnlineEstimator {
    /// A new estimator.
    #[must_use]
    pub fn new(params: OnlineParams) -> Self {
        Self {
            smoother: Smoother::new(params.smoother),
            params,
            graph: FactorGraph::new(),
            values: Values::new(),
            states: Vec::new(),
            stamps_ns: Vec::new(),
            pim: None,
            last_imu: None,
            wheel_distance_m: None,
            wheel_at_state: None,
            lines: HashMap::new(),
            late_updates: 0,
            origin: Pose3::identity(),
            waiting_for_origin: false,
            dropped_before_origin: 0,
            origin_given: false,
            aligning: None,
            registered_query_ns: None,
            solved_query_ns: None,
            waiting_fixes: Vec::new(),
            unmatched_fixes: 0,
            information: None,
            report_sigmas: false,
            solved_factors: 0,
            taken: Vec::new(),
            gate_solves: (0, 0.0),
            gated_lines: 0,
        }
    }

    /// Computes every registration's predicted sigma ([`RegistrationOutcome`]'s `sigma_m`),
    /// also those the gate accepts on the registration's own sigma, and every line
    /// observation's (logged at debug level, "line observation against the estimate")
    /// (diagnostics; one whole-graph factorisation per update that brings registrations or
    /// line observations).
    pub fn report_gate_sigmas(&mut self, on: bool) {
        self.report_sigmas = on;
    }

    fn period_ns(&self) -> i64 {
        (1e9 / self.params.state_rate_hz.max(1e-3)).round() as i64
    }

    /// Updates that took longer than a state period (the estimator fell behind).
    #[must_use]
    pub fn late_updates(&self) -> u64 {
        self.late_updates
    }

    /// Map fixes that waited for the next state and found none within a state period (a
    /// gap in the IMU).
    #[must_use]
    pub fn unmatched_map_fixes(&self) -> u64 {
        self.unmatched_fixes
    }

    /// Whole-graph factorisations made for the registration and line gates so far, and their
    /// wall time, s.
    #[must_use]
    pub fn gate_solves(&self) -> (u64, f64) {
        self.gate_solves
    }

    /// Line observations the line gate (`line_gate_sigmas`) dropped so far.
    #[must_use]
    pub fn gated_lines(&self) -> u64 {
        self.gated_lines
    }

    /// Where the fixed-lag smoother's time went so far (`None` for the incremental one).
    #[must_use]
    pub fn solve_times(&self) -> Option<crate::smoother::SolveTimes> {
        self.smoother.solve_times()
    }

    /// Number of states.
    #[must_use]
    pub fn state_count(&self) -> usize {
        self.states.len()
    }

    /// Feeds one IMU sample; returns the state it completes, if any.
    ///
    /// # Errors
    /// A solver failure.
    pub fn imu(
        &mut self,
        stamp_ns: i64,
        acc_mps2: Vector3<f64>,
        gyro_radps: Vector3<f64>,
    ) -> Result<Option<StateOutput>> {
        if !(acc_mps2.iter().chain(gyro_radps.iter()).all(|v| v.is_finite())) {
            return Err(Error::BadMeasurement(format!(
                "IMU sample at {stamp_ns} ns is not finite (acceleration {acc_mps2:?}, angular rate {gyro_radps:?})"
            )));
        }
        let mut out = None;
        if self.waiting_for_origin {
            self.dropped_before_origin += 1;
            return Ok(None);
        }
        if self.states.is_empty() && !self.origin_given && self.params.gravity_align_s > 0.0 {
            let (t0, sum, count) = self.aligning.get_or_insert((stamp_ns, Vector3::zeros(), 0));
            *sum += acc_mps2;
            *count += 1;
            if ((stamp_ns - *t0) as f64) < self.params.gravity_align_s * 1e9 {
                return Ok(None);
            }
            let mean = *sum / *count as f64;
            self.origin = Pose3::new(level_from_specific_force(&mean), self.origin.trans_m);
            self.origin_given = true;
        }
        if self.states.is_empty() {
            out = Some(self.add_state(stamp_ns)?);
        } else if let Some((t0, a, w)) = self.last_imu {
            if stamp_ns > t0
                && let Some(pim) = &mut self.pim
            {
                pim.integrate(&a, &w, (stamp_ns - t0) as f64 * 1e-9)?;
            }
            let last = self.stamps_ns.last().copied().unwrap_or(stamp_ns);
            if stamp_ns - last >= self.period_ns() {
                out = Some(self.add_state(stamp_ns)?);
            }
        }
        self.last_imu = Some((stamp_ns, acc_mps2, gyro_radps));
        Ok(out)
    }

    /// Sets the pose of the first state (its prior mean; default: the identity), for example
    /// where a run starts in a surveyed frame. Returns `false`, changing nothing, once the
    /// first state exists.
    pub fn set_origin(&mut self, world_from_body: Pose3) -> bool {
        if !self.states.is_empty() {
            return false;
        }
        self.origin = world_from_body;
        self.waiting_for_origin = false;
        self.origin_given = true;
        true
    }

    /// Holds the first state back (dropping IMU samples) until [`OnlineEstimator::set_origin`]
    /// is called: for a run whose origin arrives as a message.
    pub fn wait_for_origin(&mut self) {
        if self.states.is_empty() {
            self.waiting_for_origin = true;
            self.origin_given = true;
        }
    }

    /// IMU samples dropped while waiting for the origin.
    #[must_use]
    pub fn dropped_before_origin(&self) -> u64 {
        self.dropped_before_origin
    }

    /// Feeds a cumulative wheel distance, m.
    pub fn wheel(&mut self, distance_m: f64) {
        if distance_m.is_finite() {
            self.wheel_distance_m = Some(distance_m);
        }
    }

    fn nearest_state(&self, stamp_ns: i64) -> Option<usize> {
        let k = self.stamps_ns.partition_point(|s| *s < stamp_ns);
        let cand = [k.checked_sub(1), (k < self.stamps_ns.len()).then_some(k)];
        let best = cand
            .into_iter()
            .flatten()
            .min_by_key(|i| (self.stamps_ns[*i] - stamp_ns).abs())?;
        ((self.stamps_ns[best] - stamp_ns).abs() <= self.period_ns()).then_some(best)
    }

    /// Adds a GPR registration, unless its stamps match no states or, with a
    /// `registration_gate_m`, its along-track distance is further than that from the current
    /// estimate's.
    ///
    /// # Errors
    /// A measurement that is not finite; a bad covariance.
    pub fn registration(&mut self, r: &RegistrationMeasurement) -> Result<RegistrationOutcome> {
        let p = &r.relative_pose;
        if !(r.along_track_m.is_finite() && p.rot.iter().chain(p.trans_m.iter()).all(|v| v.is_finite())) {
            return Err(Error::BadMeasurement(format!(
                "registration {} -> {} ns is not finite (along-track {} m)",
                r.reference_stamp_ns, r.query_stamp_ns, r.along_track_m
            )));
        }
        let (Some(i), Some(j)) = (
            self.nearest_state(r.reference_stamp_ns),
            self.nearest_state(r.query_stamp_ns),
        ) else {
            return Ok(RegistrationOutcome::NoStates);
        };
        if i == j {
            return Ok(RegistrationOutcome::NoStates);
        }
        // The measurement relates the two submap stamps; the factor relates the nearest
        // states, up to half a state period away. Move each end along track by the state's
        // current forward speed times the stamp difference (at 0.5 m/s and 10 Hz states the
        // uncorrected error reaches 2.5 cm per end).
        let forward_m = |state: usize, stamp_ns: i64| -> Result<f64> {
            let keys = &self.states[state];
            let pose = self.values.pose(keys.pose)?;
            let v_body = pose.rot.transpose() * self.values.velocity(keys.velocity)?;
            Ok(v_body.x * (self.stamps_ns[state] - stamp_ns) as f64 * 1e-9)
        };
        let along_track_m = r.along_track_m + forward_m(j, r.query_stamp_ns)? - forward_m(i, r.reference_stamp_ns)?;
        let (pi, pj) = (self.states[i].pose, self.states[j].pose);
        let residual_m = self.values.pose(pi)?.between(self.values.pose(pj)?).trans_m.x - along_track_m;
        let cov = r.covariance.as_ref().filter(|c| c.nrows() == 6 && c.ncols() == 6);
        let measurement_sigma_m = cov
            .map(|c| c[(3, 3)].sqrt())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(self.params.registration_sigma_m);
        let mut gate_m = self.registration_gate_m(r.query_stamp_ns);
        let mut gated = gate_m > 0.0 && residual_m.abs() > gate_m;
        let sigmas = self.params.registration_gate_sigmas;
        let measurement_var = measurement_sigma_m.powi(2);
        // The predicted sigma is at least the measurement's, so a residual within that many of
        // them passes whatever the estimate's own uncertainty, unless registrations taken
        // since the estimate was solved have moved it: those were all as close (else their
        // gain is known and conditions this one).
        let near = |residual: f64, var: f64| residual.abs() <= sigmas * var.sqrt();
        let settled = near(residual_m, measurement_var)
            && self
                .taken
                .iter()
                .all(|t| t.gain.is_none() && near(t.residual_m, t.measurement_var));
        let gain = if self.report_sigmas || (sigmas > 0.0 && !settled) {
            Some(self.conditioned(pi, pj, residual_m, measurement_var)?)
        } else {
            None
        };
        let (tested_m, sigma_m) = gain
            .as_ref()
            .map_or((residual_m, 0.0), |g| (g.residual_m, g.variance.sqrt()));
        if sigmas > 0.0 {
            let mahalanobis_m = sigmas * sigma_m.max(measurement_sigma_m);
            gated |= tested_m.abs() > mahalanobis_m;
            gate_m = if gate_m > 0.0 {
                gate_m.min(mahalanobis_m)
            } else {
                mahalanobis_m
            };
        }
        if gated {
            return Ok(RegistrationOutcome::Gated {
                residual_m: tested_m,
                gate_m,
                sigma_m,
            });
        }
        self.taken.push(Taken {
            pi,
            pj,
            residual_m,
            measurement_var,
            gain,
        });
        self.registered_query_ns = self.registered_query_ns.max(Some(r.query_stamp_ns));
        let huber = (self.params.registration_huber_k > 0.0).then_some(RobustKernel::Huber {
            k: self.params.registration_huber_k,
        });
        let robust = |noise: NoiseModel| match huber {
            Some(k) => noise.robust(k),
            None => noise,
        };
        if self.params.registration_full_pose {
            let noise = match cov.map(NoiseModel::from_covariance) {
                Some(Ok(n)) => n,
                _ => NoiseModel::diagonal(&[0.01, 0.01, 0.01, self.params.registration_sigma_m, 0.05, 0.05])?,
            };
            self.graph
                .add(BetweenPose::new(pi, pj, r.relative_pose, robust(noise))?);
        } else {
            let noise = NoiseModel::isotropic(1, measurement_sigma_m)?;
            self.graph
                .add(TrackOffset::along(pi, pj, along_track_m, robust(noise))?);
            let across = self.params.registration_across_sigma_m;
            if across > 0.0 {
                // its own factor and robust kernel: a pass that wandered off the other's line
                // loosens the bound, not the along-track measurement
                let noise = robust(NoiseModel::isotropic(1, across)?);
                self.graph
                    .add(TrackOffset::across(pi, pj, r.relative_pose.trans_m.y, noise)?);
            }
        }
        Ok(RegistrationOutcome::Added {
            residual_m: tested_m,
            gate_m,
            sigma_m,
        })
    }

    /// The gain of a registration between poses `pi` and `pj` whose residual against the
    /// estimate as last solved is `residual_m` and whose measurement variance is
    /// `measurement_var`: its residual against that estimate moved by the registrations taken
    /// since (each a Kalman update of the estimate's Gaussian, in the order they came), its
    /// predicted variance there (the marginal along-track variance between the two states plus
    /// `measurement_var`), and the covariance times its gradient.
    fn conditioned(&mut self, pi: VarId, pj: VarId, residual_m: f64, measurement_var: f64) -> Result<Gain> {
        self.make_information()?;
        // the gains of the ones taken without one (their residuals were small), in order
        let mut taken = std::mem::take(&mut self.taken);
        let out = (|| {
            for k in 0..taken.len() {
                if taken[k].gain.is_none() {
                    let t = &taken[k];
                    let gain = self.condition_on(&taken[..k], t.pi, t.pj, t.residual_m, t.measurement_var)?;
                    taken[k].gain = Some(gain);
                }
            }
            self.condition_on(&taken, pi, pj, residual_m, measurement_var)
        })();
        self.taken = taken;
        out
    }

    /// Makes the whole graph's information at the estimate as last solved, unless made since.
    fn make_information(&mut self) -> Result<()> {
        if self.information.is_none() {
            let start = Instant::now();
            self.information = Some(WholeGraphInformation::new(
                &self.graph,
                self.solved_factors,
                &self.values,
            )?);
            self.gate_solves.0 += 1;
            self.gate_solves.1 += start.elapsed().as_secs_f64();
        }
        Ok(())
    }

    /// The whole graph's information [`OnlineEstimator::make_information`] made.
    fn made_information(&self) -> Result<&WholeGraphInformation> {
        self.information
            .as_ref()
            .ok_or_else(|| Error::LinearSolve("no whole-graph information for the gates".into()))
    }

    /// Whether the line gate drops `factor`, an observation of a line the graph holds: its
    /// residual at the current estimate further than `line_gate_sigmas` standard deviations
    /// of its prediction (the forward distance's marginal variance plus `sigma_m` squared).
    /// One within that many of the observation's own sigma passes without the whole graph's
    /// information.
    fn line_gated(&mut self, factor: &LineDistance, line_id: u32, sigma_m: f64) -> Result<bool> {
        let sigmas = self.params.line_gate_sigmas;
        let gate = sigmas > 0.0;
        if !(gate || self.report_sigmas) {
            return Ok(false);
        }
        let residual_m = factor.evaluate(&self.values, None)?[0];
        if !self.report_sigmas && residual_m.abs() <= sigmas * sigma_m {
            return Ok(false);
        }
        self.make_information()?;
        let variance = self.made_information()?.variance(factor, &self.values)? + sigma_m * sigma_m;
        let gated = gate && residual_m.abs() > sigmas * variance.sqrt();
        tracing::debug!(
            line = line_id,
            residual_m,
            sigma_m = variance.sqrt(),
            gated,
            "line observation against the estimate"
        );
        self.gated_lines += u64::from(gated);
        Ok(gated)
    }

    /// [`OnlineEstimator::conditioned`] on the registrations `taken`, whose gains are known.
    fn condition_on(
        &self,
        taken: &[Taken],
        pi: VarId,
        pj: VarId,
        residual_m: f64,
        measurement_var: f64,
    ) -> Result<Gain> {
        let info = self.made_information()?;
        let along = TrackOffset::along(pi, pj, 0.0, NoiseModel::isotropic(1, 1.0)?)?;
        let g = info.gradient(&along, &self.values)?;
        let mut u = info.solve(&g);
        let mut residual_m = residual_m;
        for gain in taken.iter().filter_map(|t| t.gain.as_ref()) {
            // the estimate moved by -u_k nu_k / S_k, its covariance less u_k u_k^T / S_k
            let c = dot(&gain.u, &g) / gain.variance;
            for (x, uk) in u.iter_mut().zip(&gain.u) {
                *x -= c * uk;
            }
            residual_m -= c * gain.residual_m;
        }
        Ok(Gain {
            variance: dot(&g, &u).max(0.0) + measurement_var,
            u,
            residual_m,
        })
    }

    /// The registration gate for a query at `query_stamp_ns` (0: off): `registration_gate_m`
    /// widened by `registration_gate_growth_mps` per second after the newest query the
    /// estimate has solved with, or after the first state.
    fn registration_gate_m(&self, query_stamp_ns: i64) -> f64 {
        let base = self.params.registration_gate_m;
        if base <= 0.0 {
            return 0.0;
        }
        let since_ns = self
            .solved_query_ns
            .or(self.stamps_ns.first().copied())
            .unwrap_or(query_stamp_ns);
        base + self.params.registration_gate_growth_mps * ((query_stamp_ns - since_ns).max(0) as f64 * 1e-9)
    }

    /// Adds a line observation from the state nearest `stamp_ns`; `false` when none matches.
    /// The forward distance is measured from the body at `stamp_ns`: taken from the newest
    /// state, stamped up to a state period earlier, it gains the wheel distance driven since
    /// that state (without it every observation was biased by about half a period's travel,
    /// 2.5 cm at 0.5 m/s, the pipe placed that much too far back). With `line_gate_sigmas`, an
    /// observation of a line the graph holds that the estimate cannot explain is dropped
    /// ([`OnlineEstimator::gated_lines`]; `true`: it matched a state).
    ///
    /// # Errors
    /// A bad sigma.
    pub fn line(&mut self, stamp_ns: i64, line_id: u32, distance_m: f64, sigma_m: f64) -> Result<bool> {
        if !distance_m.is_finite() {
            return Err(Error::BadMeasurement(format!(
                "line {line_id} observation at {stamp_ns} ns: distance {distance_m} m"
            )));
        }
        let Some(s) = self.nearest_state(stamp_ns) else {
            return Ok(false);
        };
        let sigma = if sigma_m.is_finite() && sigma_m > 0.0 {
            sigma_m
        } else {
            0.05
        };
        // the wheel has been read up to `stamp_ns` (its messages come first at a tie)
        let driven_m = match (self.wheel_distance_m, self.wheel_at_state) {
            (Some(now), Some(at_state)) if s + 1 == self.states.len() => now - at_state,
            _ => 0.0,
        };
        let distance_m = distance_m + driven_m;
        let pose = self.states[s].pose;
        let entry = self.lines.entry(line_id).or_default();
        if let Some(var) = entry.var {
            let factor = LineDistance::new(pose, var, distance_m, NoiseModel::isotropic(1, sigma)?)?;
            if !self.line_gated(&factor, line_id, sigma)? {
                self.graph.add(factor);
            }
            return Ok(true);
        }
        entry.buffered.push((s, distance_m, sigma));
        let obs: Vec<(Pose3, f64)> = entry
            .buffered
            .iter()
            .filter_map(|(st, z, _)| self.values.pose(self.states[*st].pose).ok().map(|p| (*p, *z)))
            .collect();
        if let Some(init) = initial_line(&obs, self.params.line_min_baseline_m) {
            let var = self.values.push(Variable::Line(init));
            self.graph.add(VectorPrior::line(
                var,
                init,
                NoiseModel::isotropic(2, self.params.line_prior_sigma)?,
            )?);
            let entry = self.lines.entry(line_id).or_default();
            entry.var = Some(var);
            for (st, z, sg) in std::mem::take(&mut entry.buffered) {
                self.graph.add(LineDistance::new(
                    self.states[st].pose,
                    var,
                    z,
                    NoiseModel::isotropic(1, sg)?,
                )?);
            }
        }
        Ok(true)
    }

    /// Adds a prior-map (or GPS) position fix on the ground plane for the state nearest
    /// `stamp_ns`, through that state's velocity ([`PositionFix::moving`]: a fix 50 ms from its
    /// state at 97 km/h is 1.35 m away). A fix nearer the state still to come than the newest
    /// one waits for it: the state is then published with the fixes up to its stamp, not
    /// predicted past them from the state before.
    ///
    /// # Errors
    /// A position that is not finite; a bad sigma.
    pub fn map_fix(&mut self, stamp_ns: i64, xy_m: Vector2<f64>, sigma_xy_m: [f64; 2]) -> Result<bool> {
        if !xy_m.iter().all(|v| v.is_finite()) {
            return Err(Error::BadMeasurement(format!(
                "map fix at {stamp_ns} ns: position {xy_m:?}"
            )));
        }
        let fix = WaitingFix {
            stamp_ns,
            xy_m,
            noise: NoiseModel::diagonal(&sigma_xy_m)?,
        };
        match self.stamps_ns.last() {
            Some(newest) if stamp_ns - newest > self.period_ns() / 2 => {
                self.waiting_fixes.push(fix);
                Ok(true)
            }
            _ => self.add_map_fix(fix),
        }
    }

    /// Map fixes not yet attached to a state (waiting for the next one).
    #[must_use]
    pub fn waiting_map_fixes(&self) -> usize {
        self.waiting_fixes.len()
    }

    fn add_map_fix(&mut self, fix: WaitingFix) -> Result<bool> {
        let Some(s) = self.nearest_state(fix.stamp_ns) else {
            return Ok(false);
        };
        let dt = (fix.stamp_ns - self.stamps_ns[s]) as f64 * 1e-9;
        self.graph.add(PositionFix::moving(
            self.states[s].pose,
            self.states[s].velocity,
            dt,
            Vector3::new(fix.xy_m.x, fix.xy_m.y, 0.0),
            PositionAxes::Xy,
            fix.noise,
        )?);
        Ok(true)
    }

    /// Attaches the waiting map fixes that are now nearest an existing state (all of them at
    /// the end of the run); returns how many found none.
    fn attach_waiting_fixes(&mut self, all: bool) -> Result<u64> {
        let Some(&newest) = self.stamps_ns.last() else {
            return Ok(0);
        };
        let half = self.period_ns() / 2;
        let (now, later): (Vec<_>, Vec<_>) = std::mem::take(&mut self.waiting_fixes)
            .into_iter()
            .partition(|f| all || f.stamp_ns - newest <= half);
        self.waiting_fixes = later;
        let mut unmatched = 0;
        for fix in now {
            if !self.add_map_fix(fix)? {
                unmatched += 1;
            }
        }
        Ok(unmatched)
    }

    fn add_state(&mut self, stamp_ns: i64) -> Result<StateOutput> {
        let start = Instant::now();
        // the registrations added so far are solved with in this update
        self.solved_query_ns = self.registered_query_ns;
        let i = self.states.len();
        let keys = if let Some(prev) = self.states.last().copied() {
            let bias = *self.values.bias(prev.bias)?;
            let pim = self
                .pim
                .take()
                .unwrap_or_else(|| ImuPreintegration::new(self.params.imu, bias));
            let (pose, vel) = pim.predict(
                self.values.pose(prev.pose)?,
                self.values.velocity(prev.velocity)?,
                &bias,
            );
            let keys = self.push_state(pose, vel, bias);
            if pim.delta_t_s() > 0.0 {
                self.graph.add(CombinedImuFactor::new(prev, keys, pim)?);
            } else {
                self.graph.add(crate::factors::BiasRandomWalk::new(
                    prev.bias,
                    keys.bias,
                    NoiseModel::isotropic(6, 1e-3)?,
                )?);
            }
            if let (Some(now), Some(before)) = (self.wheel_distance_m, self.wheel_at_state) {
                let noise = NoiseModel::isotropic(1, self.params.wheel_sigma_m)?;
                self.graph
                    .add(TrackOffset::along(prev.pose, keys.pose, now - before, noise)?);
            }
            keys
        } else {
            let origin = self.origin;
            let keys = self.push_state(origin, Vector3::zeros(), ImuBias::default());
            let prior = self.params.first_state;
            let (sa, sg) = (prior.acc_bias_sigma_mps2, prior.gyro_bias_sigma_radps);
            self.graph.add(PosePrior::new(
                keys.pose,
                origin,
                NoiseModel::isotropic(6, prior.pose_sigma)?,
            )?);
            self.graph.add(VectorPrior::velocity(
                keys.velocity,
                Vector3::zeros(),
                NoiseModel::isotropic(3, prior.velocity_sigma_mps)?,
            )?);
            self.graph.add(VectorPrior::bias(
                keys.bias,
                ImuBias::default(),
                NoiseModel::diagonal(&[sa, sa, sa, sg, sg, sg])?,
            )?);
            keys
        };
        if self.params.nonholonomic_sigma_mps > 0.0 {
            let noise = NoiseModel::isotropic(2, self.params.nonholonomic_sigma_mps)?;
            self.graph.add(NonHolonomic::new(keys.pose, keys.velocity, noise)?);
        }
        self.wheel_at_state = self.wheel_distance_m;
        self.stamps_ns.push(stamp_ns);
        self.unmatched_fixes += self.attach_waiting_fixes(false)?;
        let bias = *self.values.bias(keys.bias)?;
        self.pim = Some(ImuPreintegration::new(self.params.imu, bias));
        let report = self
            .smoother
            .update(&self.graph, &mut self.values, &[keys.pose, keys.velocity, keys.bias])?;
        self.information = None;
        self.taken.clear();
        self.solved_factors = self.graph.len();
        let update_s = start.elapsed().as_secs_f64();
        if update_s * self.params.state_rate_hz > 1.0 {
            self.late_updates += 1;
            let inc = report.incremental.unwrap_or_default();
            tracing::warn!(
                state = i,
                update_ms = update_s * 1e3,
                eliminated = inc.eliminated,
                relinearized = inc.relinearized,
                solved = inc.solved,
                max_separator = inc.max_separator,
                relinearize_pending = inc.relinearize_pending,
                "estimate: update slower than the state period"
            );
        }
        Ok(StateOutput {
            index: i as u64,
            stamp_ns,
            pose: *self.values.pose(keys.pose)?,
            velocity_mps: *self.values.velocity(keys.velocity)?,
            bias: *self.values.bias(keys.bias)?,
            covariance: self.smoother.newest_covariance().cloned(),
            update_s,
        })
    }

    fn push_state(&mut self, pose: Pose3, vel: Vector3<f64>, bias: ImuBias) -> NavKeys {
        let keys = NavKeys {
            pose: self.values.push(Variable::Pose(pose)),
            velocity: self.values.push(Variable::Velocity(vel)),
            bias: self.values.push(Variable::Bias(bias)),
        };
        self.states.push(keys);
        keys
    }

    /// Brings every variable's estimate up to date (the incremental smoother's updates
    /// write only what moved noticeably); call before reading a whole trajectory.
    ///
    /// # Errors
    /// Never for a consistent estimator.
    pub fn refresh(&mut self) -> Result<()> {
        self.smoother.refresh(&mut self.values)
    }

    /// Every state's `(index, stamp, pose)`.
    ///
    /// # Errors
    /// Never for a consistent estimator.
    pub fn trajectory(&self) -> Result<Vec<(u64, i64, Pose3)>> {
        self.states
            .iter()
            .zip(&self.stamps_ns)
            .enumerate()
            .map(|(i, (k, s))| Ok((i as u64, *s, *self.values.pose(k.pose)?)))
            .collect()
    }

    /// Every initialised line `(id, line)`, by id.
    #[must_use]
    pub fn line_map(&self) -> Vec<(u32, HoughLine)> {
        let mut out: Vec<(u32, HoughLine)> = self
            .lines
            .iter()
            .filter_map(|(id, l)| l.var.and_then(|v| self.values.line(v).ok()).map(|line| (*id, *line)))
            .collect();
        out.sort_by_key(|(id, _)| *id);
        out
    }

    /// Ends the run with a full solve of the whole graph.
    ///
    /// # Errors
    /// A solver failure.
    pub fn finish(&mut self) -> Result<()> {
        self.unmatched_fixes += self.attach_waiting_fixes(true)?;
        if !self.states.is_empty() {
            let lm = self.smoother.finish(&self.graph, &mut self.values)?;
            tracing::info!(
                states = self.states.len(),
                factors = self.graph.len(),
                seconds = lm.seconds,
                iterations = lm.iterations,
                linear_solves = lm.linear_solves,
                linearize_s = lm.linearize_s,
                solve_s = lm.solve_s,
                evaluate_s = lm.evaluate_s,
                initial_error = lm.initial_error,
                final_error = lm.final_error,
                "estimate: final solve of the whole graph"
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A robot driving a circle at 1 m/s, z up, 200 Hz IMU without noise; wheel odometry.
    #[test]
    fn tracks_a_circle_from_imu_and_wheel() {
        let mut states = 0;
        let est = drive_circle(10, 1.0, |_, _| states += 1);
        assert!(states >= 90, "{states} states");
        assert_eq!(est.late_updates(), 0);
        assert_eq!(est.trajectory().expect("trajectory").len(), states);
        let error = end_error_m(&est);
        assert!(error < 0.5, "{error} m from the truth at the end");
    }

    /// The circle the tests drive (radius 10 m, 1 m/s, starting at the origin along x) at `t_s`.
    fn circle_truth(t_s: f64) -> Pose3 {
        let (radius, omega) = (10.0, 0.1);
        let a = omega * t_s;
        let rot = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), a).into_inner();
        Pose3::new(rot, Vector3::new(radius * a.sin(), radius * (1.0 - a.cos()), 0.0))
    }

    /// Drives the circle for 10 s with a wheel that over-reads by `wheel_scale`, feeding the
    /// lines and registrations `extra` asks for after each state; returns the estimator.
    fn drive_circle(
        seconds: i64,
        wheel_scale: f64,
        extra: impl FnMut(&mut OnlineEstimator, &StateOutput),
    ) -> OnlineEstimator {
        drive_circle_with(seconds, wheel_scale, 0.0, extra)
    }

    /// [`drive_circle`] with registrations bounding the across-track offset to
    /// `registration_across_sigma_m` (0: along track only).
    fn drive_circle_with(
        seconds: i64,
        wheel_scale: f64,
        registration_across_sigma_m: f64,
        extra: impl FnMut(&mut OnlineEstimator, &StateOutput),
    ) -> OnlineEstimator {
        let params = OnlineParams {
            registration_across_sigma_m,
            ..OnlineParams::default()
        };
        drive_circle_params(seconds, wheel_scale, params, extra)
    }

    /// [`drive_circle`] with `params`, in line re-solves and a weak velocity prior.
    fn drive_circle_params(
        seconds: i64,
        wheel_scale: f64,
        params: OnlineParams,
        mut extra: impl FnMut(&mut OnlineEstimator, &StateOutput),
    ) -> OnlineEstimator {
        drive_circle_samples(seconds, wheel_scale, params, |est, _, state| {
            if let Some(s) = state {
                extra(est, s);
            }
        })
    }

    /// [`drive_circle_params`] calling `each` after every IMU sample, with its stamp and the
    /// state it made.
    fn drive_circle_samples(
        seconds: i64,
        wheel_scale: f64,
        params: OnlineParams,
        mut each: impl FnMut(&mut OnlineEstimator, i64, Option<&StateOutput>),
    ) -> OnlineEstimator {
        let params = OnlineParams {
            smoother: SmootherParams {
                background: false,
                ..SmootherParams::default()
            },
            first_state: FirstStatePrior {
                velocity_sigma_mps: 10.0,
                ..FirstStatePrior::default()
            },
            // the circle starts moving: no gravity alignment, the first state at t = 0
            gravity_align_s: 0.0,
            ..params
        };
        let mut est = OnlineEstimator::new(params);
        // Body x along the velocity, centripetal acceleration along body y; at rest the
        // accelerometer reads +g up. The run starts moving: a weak velocity prior, the wheel
        // fixes the speed.
        let (speed, omega) = (1.0, 0.1);
        let dt_ns = 5_000_000i64;
        for k in 0..=seconds * 200 {
            let t = k as f64 * dt_ns as f64 * 1e-9;
            est.wheel(wheel_scale * speed * t);
            let s = est
                .imu(
                    k * dt_ns,
                    Vector3::new(0.0, speed * omega, 9.80665),
                    Vector3::new(0.0, 0.0, omega),
                )
                .expect("imu");
            each(&mut est, k * dt_ns, s.as_ref());
        }
        est.finish().expect("finish");
        est
    }

    fn end_error_m(est: &OnlineEstimator) -> f64 {
        let traj = est.trajectory().expect("trajectory");
        let (_, stamp_ns, last) = traj[traj.len() - 1];
        (last.trans_m - circle_truth(stamp_ns as f64 * 1e-9).trans_m).norm()
    }

    #[test]
    fn registrations_correct_a_wrong_wheel_scale() {
        let without = end_error_m(&drive_circle(10, 1.1, |_, _| {}));
        // Every 10 states, the true along-track distance to the state 1 s before.
        let with = end_error_m(&drive_circle(10, 1.1, |est, s| {
            if s.index >= 10 && s.index % 10 == 0 {
                let (t_j, t_i) = (s.stamp_ns, s.stamp_ns - 1_000_000_000);
                let rel = circle_truth(t_i as f64 * 1e-9).between(&circle_truth(t_j as f64 * 1e-9));
                let r = RegistrationMeasurement {
                    reference_stamp_ns: t_i,
                    query_stamp_ns: t_j,
                    relative_pose: rel,
                    along_track_m: rel.trans_m.x,
                    covariance: None,
                };
                let added = est.registration(&r).expect("registration");
                assert!(matches!(added, RegistrationOutcome::Added { .. }), "{added:?}");
            }
        }));
        assert!(without > 0.3, "a 10 % wheel error should show: {without} m");
        assert!(with < 0.5 * without, "with registrations {with} m, without {without} m");
    }

    /// Every 10 states, the truth's relative pose to the state 1 s before as a registration
    /// (`along_track_m` its x), its across offset (y) moved by `across_error_m`.
    fn register_one_second_back(across_error_m: f64) -> impl FnMut(&mut OnlineEstimator, &StateOutput) {
        move |est, s| {
            if s.index >= 10 && s.index % 10 == 0 {
                let (t_j, t_i) = (s.stamp_ns, s.stamp_ns - 1_000_000_000);
                let mut rel = circle_truth(t_i as f64 * 1e-9).between(&circle_truth(t_j as f64 * 1e-9));
                let along_track_m = rel.trans_m.x;
                rel.trans_m.y += across_error_m;
                let r = RegistrationMeasurement {
                    reference_stamp_ns: t_i,
                    query_stamp_ns: t_j,
                    relative_pose: rel,
                    along_track_m,
                    covariance: None,
                };
                let added = est.registration(&r).expect("registration");
                assert!(matches!(added, RegistrationOutcome::Added { .. }), "{added:?}");
            }
        }
    }

    /// The truth's relative pose from `t_i` to `t_j` on the circle as a registration, its
    /// along-track distance `offset_m` off.
    fn truth_registration(t_i: i64, t_j: i64, offset_m: f64) -> RegistrationMeasurement {
        let rel = circle_truth(t_i as f64 * 1e-9).between(&circle_truth(t_j as f64 * 1e-9));
        RegistrationMeasurement {
            reference_stamp_ns: t_i,
            query_stamp_ns: t_j,
            relative_pose: rel,
            along_track_m: rel.trans_m.x + offset_m,
            covariance: None,
        }
    }

    #[test]
    fn a_registration_far_from_the_estimate_is_gated() {
        // Every 10 states the true along-track distance to the state 1 s before, on a wheel
        // 10 % long; at 5 s one 1.5 m wrong (a match on a repeated structure), or none.
        let run = |registration_gate_m: f64, wrong: Option<f64>| {
            let mut outcomes = Vec::new();
            let params = OnlineParams {
                registration_gate_m,
                registration_gate_growth_mps: 0.1,
                ..OnlineParams::default()
            };
            let est = drive_circle_params(10, 1.1, params, |est, s| {
                if s.index >= 10 && s.index % 10 == 0 {
                    let wrong_m = match (s.index, wrong) {
                        (50, Some(m)) => m,
                        (50, None) => return,
                        _ => 0.0,
                    };
                    let r = truth_registration(s.stamp_ns - 1_000_000_000, s.stamp_ns, wrong_m);
                    outcomes.push((wrong_m, est.registration(&r).expect("registration")));
                }
            });
            (end_error_m(&est), outcomes)
        };
        let (ungated, outcomes) = run(0.0, Some(1.5));
        assert!(
            outcomes
                .iter()
                .all(|(_, o)| matches!(o, RegistrationOutcome::Added { .. }))
        );
        let (gated, outcomes) = run(0.5, Some(1.5));
        for (wrong_m, outcome) in &outcomes {
            match outcome {
                // the estimate is within a few cm where the registrations keep it: the wrong
                // one is 1.5 m from it, the right ones stay well inside the gate
                RegistrationOutcome::Gated { residual_m, gate_m, .. } if *wrong_m > 0.0 => {
                    assert!((residual_m + 1.5).abs() < 0.1, "{residual_m}");
                    // a second after the last registration
                    assert!((gate_m - 0.6).abs() < 1e-9, "{gate_m}");
                }
                RegistrationOutcome::Added { residual_m, gate_m, .. } if *wrong_m == 0.0 => {
                    assert!(residual_m.abs() < 0.2, "{residual_m}");
                    assert!(*gate_m >= 0.5, "{gate_m}");
                }
                other => panic!("{wrong_m} m wrong: {other:?}"),
            }
        }
        // gated, the wrong one changes nothing; taken, it pulls the estimate off (the Huber
        // kernel bounds its pull, not its harm)
        let (without, _) = run(0.5, None);
        assert_eq!(gated, without);
        assert!(
            ungated > without + 0.03,
            "with the wrong one {ungated} m, without {without} m"
        );
    }

    #[test]
    fn the_mahalanobis_gate_is_as_wide_as_the_estimate_is_unsure() {
        // On a wheel 10 % long, every 10 states the truth's along-track distance to the state
        // `back_s` before; at 5 s one 1.5 m wrong. Gated at 3 sigma of the prediction.
        let run = |back_s: i64, sigmas: f64| {
            let mut outcomes = Vec::new();
            let params = OnlineParams {
                registration_gate_sigmas: sigmas,
                ..OnlineParams::default()
            };
            let est = drive_circle_params(10, 1.1, params, |est, s| {
                est.report_gate_sigmas(true);
                if s.index >= 10 * back_s as u64 && s.index % 10 == 0 {
                    let wrong_m = if s.index == 50 { 1.5 } else { 0.0 };
                    let r = truth_registration(s.stamp_ns - back_s * 1_000_000_000, s.stamp_ns, wrong_m);
                    outcomes.push((s.index, wrong_m, est.registration(&r).expect("registration")));
                }
            });
            (end_error_m(&est), outcomes)
        };
        let sigma_of = |o: &RegistrationOutcome| match o {
            RegistrationOutcome::Added { sigma_m, .. } | RegistrationOutcome::Gated { sigma_m, .. } => *sigma_m,
            RegistrationOutcome::NoStates => f64::NAN,
        };
        let (_, one) = run(1, 3.0);
        let (_, four) = run(4, 3.0);
        for outcomes in [&one, &four] {
            for (index, wrong_m, outcome) in outcomes {
                let sigma = sigma_of(outcome);
                // at least the registration's own sigma, and the gate three of them
                assert!(sigma >= 0.05 && sigma.is_finite(), "state {index}: {outcome:?}");
                match outcome {
                    RegistrationOutcome::Gated { residual_m, gate_m, .. } if *wrong_m > 0.0 => {
                        assert!((residual_m + 1.5).abs() < 0.2, "{residual_m}");
                        assert!((gate_m - 3.0 * sigma).abs() < 1e-12, "{gate_m}");
                    }
                    RegistrationOutcome::Added { residual_m, .. } if *wrong_m == 0.0 => {
                        assert!(residual_m.abs() < 3.0 * sigma, "{residual_m}");
                    }
                    other => panic!("state {index}, {wrong_m} m wrong: {other:?}"),
                }
            }
        }
        // The first registration of each: four seconds of dead reckoning between the two
        // states are less certain than one.
        let first = |o: &[(u64, f64, RegistrationOutcome)]| sigma_of(&o[0].2);
        assert!(
            first(&four) > 1.5 * first(&one),
            "4 s back {} m, 1 s back {} m",
            first(&four),
            first(&one)
        );
        // The gate off takes the wrong one; on, the estimate ends as without it.
        let (ungated, _) = run(1, 0.0);
        let (gated, _) = run(1, 3.0);
        assert!(ungated > gated + 0.03, "taken {ungated} m, gated {gated} m");
    }

    #[test]
    fn a_registration_that_contradicts_one_taken_in_the_same_update_is_gated() {
        // After 8 s of dead reckoning on a true wheel (no registration yet), registrations of
        // the query at 8 s against the state at 0.5 s: the true distance, then one `wrong_m`
        // off it.
        let run = |first: bool, wrong_m: f64, report: bool| {
            let mut outcomes = Vec::new();
            let params = OnlineParams {
                registration_gate_sigmas: 3.0,
                ..OnlineParams::default()
            };
            drive_circle_params(10, 1.0, params, |est, s| {
                est.report_gate_sigmas(report);
                if s.index == 80 {
                    let offsets = if first { vec![0.0, wrong_m] } else { vec![wrong_m] };
                    for offset in offsets {
                        let r = truth_registration(500_000_000 + est.stamps_ns[0], s.stamp_ns, offset);
                        outcomes.push(est.registration(&r).expect("registration"));
                    }
                }
            });
            outcomes
        };
        // alone, the estimate is unsure enough to take it
        let alone = run(false, 0.3, false);
        assert!(matches!(alone[..], [RegistrationOutcome::Added { .. }]), "{alone:?}");
        // after the right one, it is 0.3 m from where that one moved the estimate, whose
        // uncertainty it also took away
        let after = run(true, 0.3, false);
        match after[..] {
            [
                RegistrationOutcome::Added { sigma_m: first, .. },
                RegistrationOutcome::Gated {
                    residual_m, sigma_m, ..
                },
            ] => {
                // within three of its own sigmas of the estimate: taken without the solve,
                // whose gain the second one's test then computes
                assert_eq!(first, 0.0);
                assert!(sigma_m < 0.08, "{sigma_m}");
                assert!((residual_m + 0.3).abs() < 0.05, "{residual_m}");
            }
            _ => panic!("{after:?}"),
        }
        // the same verdicts with every sigma computed as it comes (diagnostics)
        let reported = run(true, 0.3, true);
        match reported[..] {
            [
                RegistrationOutcome::Added { sigma_m: first, .. },
                RegistrationOutcome::Gated { sigma_m, .. },
            ] => assert!(first > 0.1 && sigma_m < 0.08, "{reported:?}"),
            _ => panic!("{reported:?}"),
        }
    }

    #[test]
    fn registrations_bound_the_across_offset_only_when_asked_to() {
        // Along track only, a registration's across offset is not read.
        let along = end_error_m(&drive_circle_with(10, 1.1, 0.0, register_one_second_back(0.0)));
        let along_shifted = end_error_m(&drive_circle_with(10, 1.1, 0.0, register_one_second_back(0.3)));
        assert_eq!(along, along_shifted);
        // Bounded to 5 cm, the true offset keeps the estimate where it was, a 30 cm error in
        // it pulls the estimate off.
        let bounded = end_error_m(&drive_circle_with(10, 1.1, 0.05, register_one_second_back(0.0)));
        let bounded_shifted = end_error_m(&drive_circle_with(10, 1.1, 0.05, register_one_second_back(0.3)));
        assert!(
            (bounded - along).abs() < 0.01,
            "bounded {bounded} m, along track only {along} m"
        );
        assert!(
            bounded_shifted > along + 0.1,
            "bounded, offset wrong by 0.3 m: {bounded_shifted} m, along track only {along} m"
        );
    }

    #[test]
    fn a_crossed_line_is_initialised_and_estimated() {
        let truth = HoughLine {
            rho_m: 6.0,
            theta_rad: 0.2,
        };
        // Crossed twice, 16 m apart (one crossing alone has no baseline: every observed point
        // is the same point of the line).
        let est = drive_circle(30, 1.0, |est, s| {
            let (h, _, _) = crate::factors::forward_distance_to_line(&circle_truth(s.stamp_ns as f64 * 1e-9), &truth);
            if (0.5..4.0).contains(&h) {
                assert!(est.line(s.stamp_ns, 7, h, 0.05).expect("line"));
            }
        });
        let lines = est.line_map();
        assert_eq!(lines.len(), 1, "{lines:?}");
        let (id, line) = lines[0];
        assert_eq!(id, 7);
        assert!(
            (line.rho_m - truth.rho_m).abs() < 0.1 && (line.theta_rad - truth.theta_rad).abs() < 0.02,
            "{line:?} against {truth:?}"
        );
    }

    #[test]
    fn a_line_observation_between_states_is_measured_from_its_own_stamp() {
        // The line of the test above, observed half a state period (50 ms, 5 cm at 1 m/s)
        // after each state, by the forward distance from the body then. Taken as if from the
        // state before it, every observation is 5 cm short and the line comes out 5 cm off.
        let truth = HoughLine {
            rho_m: 6.0,
            theta_rad: 0.2,
        };
        let mut observed = 0;
        let est = drive_circle_samples(30, 1.0, OnlineParams::default(), |est, stamp_ns, _| {
            if stamp_ns % 100_000_000 == 50_000_000 {
                let (h, _, _) = crate::factors::forward_distance_to_line(&circle_truth(stamp_ns as f64 * 1e-9), &truth);
                if (0.5..4.0).contains(&h) {
                    assert!(est.line(stamp_ns, 7, h, 0.05).expect("line"));
                    observed += 1;
                }
            }
        });
        assert!(observed > 40, "{observed}");
        let line = est.line_map()[0].1;
        assert!(
            (line.rho_m - truth.rho_m).abs() < 0.005 && (line.theta_rad - truth.theta_rad).abs() < 0.001,
            "{line:?} against {truth:?}"
        );
    }

    #[test]
    fn the_line_gate_drops_an_observation_the_estimate_cannot_explain() {
        // The line of the test above, on a 70 s drive: observed from every state 0.5-4 m
        // before it, in three crossings (the first has no baseline: the line is made at the
        // second, the 37th observation; the third, from the 67th, comes 38 s of dead reckoning
        // later). Observation `wrong_at` is `wrong_m` long (`None`: not made). Gated at
        // `sigmas`; returns whether that one was gated, how many were, and the line's error.
        let truth = HoughLine {
            rho_m: 6.0,
            theta_rad: 0.2,
        };
        let run = |wrong_at: usize, wrong_m: Option<f64>, sigmas: f64| {
            let params = OnlineParams {
                line_gate_sigmas: sigmas,
                ..OnlineParams::default()
            };
            let (mut observed, mut wrong_gated) = (0, false);
            let est = drive_circle_params(70, 1.0, params, |est, s| {
                let (h, _, _) =
                    crate::factors::forward_distance_to_line(&circle_truth(s.stamp_ns as f64 * 1e-9), &truth);
                if (0.5..4.0).contains(&h) {
                    observed += 1;
                    let before = est.gated_lines();
                    let z = if observed == wrong_at {
                        wrong_m.map(|w| h + w)
                    } else {
                        Some(h)
                    };
                    if let Some(z) = z {
                        assert!(est.line(s.stamp_ns, 7, z, 0.05).expect("line"));
                    }
                    wrong_gated |= observed == wrong_at && est.gated_lines() > before;
                }
            });
            let line = est.line_map()[0].1;
            let error = (line.rho_m - truth.rho_m).hypot(line.theta_rad - truth.theta_rad);
            (wrong_gated, est.gated_lines(), error)
        };
        // in the second crossing the estimate knows where the line is to a few cm: 0.5 m off
        // is dropped, and only it
        let (wrong_gated, gated, error) = run(50, Some(0.5), 3.0);
        assert!(wrong_gated);
        assert_eq!(gated, 1);
        // dropped, it changes nothing; taken, it pulls the line off
        let (_, none_gated, without) = run(50, None, 3.0);
        assert_eq!(none_gated, 0);
        assert!((error - without).abs() < 1e-9, "{error} against {without}");
        let (_, _, pulled) = run(50, Some(0.5), 0.0);
        assert!(pulled > without + 0.001, "taken {pulled}, without {without}");
        // after 38 s of dead reckoning the estimate cannot tell 0.5 m: the same miss passes
        let (wrong_gated, _, _) = run(67, Some(0.5), 3.0);
        assert!(!wrong_gated);
    }

    #[test]
    fn a_tilted_start_is_levelled_from_the_first_second_of_imu() {
        // At rest on a slope (roll 0.1, pitch -0.05 rad, yaw 0), 5 s, wheel reading 0.
        let tilt = nalgebra::Rotation3::from_euler_angles(0.1, -0.05, 0.0);
        let specific_force = tilt.inverse() * Vector3::new(0.0, 0.0, 9.80665);
        let run = |gravity_align_s: f64| {
            let mut est = OnlineEstimator::new(OnlineParams {
                gravity_align_s,
                ..OnlineParams::default()
            });
            let mut first = None;
            for k in 0..1000i64 {
                est.wheel(0.0);
                if let Some(s) = est.imu(k * 5_000_000, specific_force, Vector3::zeros()).expect("imu") {
                    first.get_or_insert(s);
                }
            }
            let first = first.expect("a state");
            let traj = est.trajectory().expect("trajectory");
            (first, traj[traj.len() - 1].2)
        };
        let tilted = Pose3::new(tilt.into_inner(), Vector3::zeros());
        let angle = |p: &Pose3| {
            let level = Pose3::new(p.rot, Vector3::zeros());
            tilted.between(&level).log().fixed_rows::<3>(0).norm()
        };
        let (first, last) = run(1.0);
        // made at the end of the first second, already tilted as the platform is
        assert_eq!(first.stamp_ns, 1_000_000_000);
        assert!(angle(&first.pose) < 1e-6, "first state {} rad off", angle(&first.pose));
        assert!(angle(&last) < 2e-3, "last state {} rad off", angle(&last));
        // without alignment the first state is level, 0.11 rad off
        let (first, _) = run(0.0);
        assert_eq!(first.stamp_ns, 0);
        assert!(angle(&first.pose) > 0.1, "{}", angle(&first.pose));
    }

    /// Map fixes at 100 Hz between the states: those nearer the next state wait for it, and
    /// each is compared with its state moved by the state's velocity (10-90 ms at 1 m/s is 1-9
    /// cm: a fix taken as its state's position, or moved the wrong way, shows).
    #[test]
    fn map_fixes_wait_for_the_state_they_are_nearest() {
        let mut published = Vec::new();
        let est = drive_circle(6, 1.0, |est, s| {
            published.push((s.stamp_ns, s.pose.trans_m));
            for k in 1..10 {
                let stamp = s.stamp_ns + k * 10_000_000;
                let at = circle_truth(stamp as f64 * 1e-9).trans_m;
                assert!(est.map_fix(stamp, at.xy(), [0.02, 0.02]).expect("fix"));
            }
            // 60 to 90 ms after the state: nearer the next one
            assert_eq!(est.waiting_map_fixes(), 4);
        });
        assert_eq!((est.waiting_map_fixes(), est.unmatched_map_fixes()), (0, 0));
        for (stamp, p) in &published {
            let off = (p - circle_truth(*stamp as f64 * 1e-9).trans_m).xy().norm();
            assert!(off < 0.002, "state at {stamp} ns published {off} m from the truth");
        }
    }

    #[test]
    fn non_finite_measurements_are_refused_and_change_nothing() {
        let mut est = OnlineEstimator::new(OnlineParams {
            gravity_align_s: 0.0,
            ..OnlineParams::default()
        });
        let g = Vector3::new(0.0, 0.0, 9.80665);
        assert!(est.imu(0, g, Vector3::zeros()).expect("first sample").is_some());
        let bad = est.imu(5_000_000, Vector3::new(f64::NAN, 0.0, 9.8), Vector3::zeros());
        assert!(
            matches!(bad, Err(Error::BadMeasurement(ref m)) if m.contains("5000000 ns")),
            "{bad:?}"
        );
        assert!(matches!(
            est.line(0, 1, f64::INFINITY, 0.05),
            Err(Error::BadMeasurement(_))
        ));
        assert!(matches!(
            est.map_fix(0, Vector2::new(f64::NAN, 0.0), [0.5, 0.5]),
            Err(Error::BadMeasurement(_))
        ));
        // The run goes on: the next state comes 100 ms later as usual.
        let mut states = 1;
        for k in 2..=40i64 {
            if est.imu(k * 5_000_000, g, Vector3::zeros()).expect("sample").is_some() {
                states += 1;
            }
        }
        assert_eq!(states, 3);
        assert_eq!(est.state_count(), 3);
    }
}
