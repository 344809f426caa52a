//! The `estimate` stage: converts messages to [`OnlineEstimator`] calls and estimates back to
//! messages. Inputs arrive merged in stamp order (the runtime's watermark merge).

use gprflow_msg::{
    Header, HoughLine as HoughLineMsg, Imu, LineMap, LineObservation, MapFix, Message, Odometry, Point, Pose,
    PoseStamped, PoseWithCovariance, Quaternion, Registration, RegistrationCheck, StateEstimate, Trajectory,
    Vector3 as Vector3Msg, WheelOdometry,
};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};
use nalgebra::{DMatrix, Vector2, Vector3};

use crate::imu::ImuParams;
use crate::incremental::IncrementalParams;
use crate::lie::Pose3;
use crate::online::{
    FirstStatePrior, OnlineEstimator, OnlineParams, RegistrationMeasurement, RegistrationOutcome, StateOutput,
};
use crate::smoother::{SmootherMethod, SmootherParams};

/// Parameters of the `estimate` stage.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct EstimateParams {
    /// States per second (default 10).
    pub state_rate_hz: f64,
    /// `fixed_lag` (default): a window of the newest states plus full re-solves when a loop
    /// closure reaches behind it. `incremental`: the whole graph kept eliminated, each update
    /// re-eliminating only what its factors touch; deterministic at any feed rate, marginal
    /// covariances; not yet the default (it diverged after 8.5 minutes of a 20.9-minute
    /// simulated IMU run).
    pub smoother: SmootherMethod,
    /// Settings of the `incremental` smoother: relinearisation thresholds
    /// (`relinearize_rotation_rad` 0.001, `relinearize_translation_m` 0.1,
    /// `relinearize_velocity_mps` 0.1, `relinearize_bias` 0.1), `max_relinearized_per_update`
    /// (32; 0: no cap), `relinearize_budget_groups` (48; 0: no budget) and
    /// `wildfire_threshold` (0.01).
    pub incremental: IncrementalParams,
    /// Window of the `fixed_lag` smoother, states (default 30).
    pub lag_states: usize,
    /// `fixed_lag` smoother: marginalise the states that leave the window into a prior on the
    /// window (Schur complement, first-estimate Jacobians) instead of holding them at their
    /// estimate, so that the window's covariance is the marginal one (default false). Loop
    /// closures to states already marginalised still hold those at their estimate.
    pub marginalise: bool,
    /// `fixed_lag` smoother: Levenberg-Marquardt iterations of the window's solve at each update
    /// at most (default 3). Each update's solve starts from where the last one ended.
    pub window_iterations: usize,
    /// `fixed_lag` smoother: Levenberg-Marquardt iterations of each whole-graph re-solve at
    /// most (default 3). Each starts from where the last one ended, so fewer iterations per
    /// re-solve still converge over the run: on the 20.9-minute basement localisation run 1
    /// took 425 s against 650 s with the same ATE (docs/known-gaps.md).
    pub resolve_iterations: usize,
    /// `fixed_lag` smoother: states between the starts of two whole-graph re-solves at least
    /// (default 1: every update that brings a loop closure starts one). Closures in between
    /// are solved with the window, against the older states as they are.
    pub resolve_spacing_states: usize,
    /// `fixed_lag` smoother: wide re-solves (of `resolve_wide_states`, by default the whole
    /// graph) at least this fraction of the states there were at the start of the last one
    /// apart (default 0: `resolve_spacing_states` alone), so that they cost a multiple of the
    /// last one in all; with `resolve_window_states` the re-solves in between solve the window.
    pub resolve_spacing_growth: f64,
    /// `fixed_lag` smoother: the newest states a wide re-solve solves (default 0: the whole
    /// graph).
    pub resolve_wide_states: usize,
    /// `fixed_lag` smoother: the newest states each re-solve solves, the older ones held at
    /// their estimate (default 0: the whole graph). Bounds a re-solve's cost on long runs; the
    /// end-of-run solve is always of the whole graph.
    pub resolve_window_states: usize,
    /// Accelerometer noise density, (m/s^2)/sqrt(Hz) (default 8.27e-3, the thesis rig's XSENS MTi-30).
    pub acc_noise_density: f64,
    /// Gyroscope noise density, (rad/s)/sqrt(Hz) (default 2.28e-3).
    pub gyro_noise_density: f64,
    /// Accelerometer bias random walk, (m/s^3)/sqrt(Hz) (default 1.33e-4).
    pub acc_bias_random_walk: f64,
    /// Gyroscope bias random walk, (rad/s^2)/sqrt(Hz) (default 5.02e-5).
    pub gyro_bias_random_walk: f64,
    /// Prior sigma of the accelerometer bias at the start, m/s^2 (default 0.05).
    pub acc_bias_prior_sigma_mps2: f64,
    /// Prior sigma of the gyroscope bias at the start, rad/s (default 5e-3). Loose values let
    /// the yaw drift with the weakly observable gyro bias.
    pub gyro_bias_prior_sigma_radps: f64,
    /// Gravity, m/s^2 (default 9.80665).
    pub gravity_mps2: f64,
    /// Wheel along-track sigma per state, m (default 0.02).
    pub wheel_sigma_m: f64,
    /// Registration along-track sigma when the message has no covariance, m (default 0.05).
    pub registration_sigma_m: f64,
    /// Use the registration's full relative pose, not only its along-track distance (default false).
    pub registration_full_pose: bool,
    /// Sigma of the offset across the reference's track that a registration is taken to imply,
    /// m: right for a rig that drives the same line again; 0 reads only the along-track
    /// distance (default 0).
    pub registration_across_sigma_m: f64,
    /// Largest difference between a new registration's along-track distance and the current
    /// estimate's, m, right after the estimate took a registration: one further from the
    /// estimate is dropped as a wrong match (default 0: off).
    pub registration_gate_m: f64,
    /// Widening of `registration_gate_m` per second that the query lies after the newest
    /// registered query the estimate has solved with, m/s (default 0).
    pub registration_gate_growth_mps: f64,
    /// Mahalanobis gate on registrations, standard deviations (default 0: off): one whose
    /// along-track residual is further than this many standard deviations of its prediction
    /// (the estimate's marginal along-track uncertainty between the two states and the
    /// registration's sigma) is dropped. Applies with `registration_gate_m` when both are set.
    pub registration_gate_sigmas: f64,
    /// Minimum baseline that initialises a line, m (default 1.0).
    pub line_min_baseline_m: f64,
    /// Mahalanobis gate on line observations, standard deviations (default 0: off): an
    /// observation of a mapped line whose forward distance is further than this many
    /// standard deviations of the estimate's prediction (the forward distance's marginal
    /// uncertainty, state and line together, and the observation's sigma) is dropped as a
    /// wrong association.
    pub line_gate_sigmas: f64,
    /// Non-holonomic constraint sigma, m/s; 0 disables it (default 0.1).
    pub nonholonomic_sigma_mps: f64,
    /// Without an `initial_pose`, `gps` or `map_fix` input, the first state's roll and pitch
    /// come from the mean specific force over this many seconds of IMU at the start (the
    /// vehicle at rest or moving steadily), and the first state is made then; yaw and position
    /// start at 0 (default 1.0; 0: a level first state at the first sample).
    pub gravity_align_s: f64,
    /// Publish Trajectory and LineMap snapshots every this many states (default 10; 0: only
    /// at the end).
    pub snapshot_every_states: u64,
    /// And only once the trajectory has grown by this fraction since the last snapshot
    /// (default 0.05; 0: every `snapshot_every_states` states however long it is). Each
    /// snapshot holds the whole trajectory, so at a fixed period their total size grows with
    /// the square of the run's length (440 MB for a 20.9-minute run at 10 states per second);
    /// growing the period with the trajectory keeps it linear (about 1 / fraction poses per
    /// state: 20 by default).
    pub snapshot_growth: f64,
    /// `fixed_lag` smoother: loop-closure full re-solves on a background thread (default
    /// true). `false` solves them in the update that needs one: slower, but the same input
    /// always gives the same output.
    pub background_solves: bool,
    /// Also publish the verdict on every registration (taken, or dropped by the gate, with
    /// its residual and predicted sigma: one whole-graph factorisation per update that brings
    /// registrations) on the `registration_check` output (`RegistrationCheck`), for
    /// `gprflow eval`, and log every line observation's residual and predicted sigma at debug
    /// level (default false).
    pub diagnostics: bool,
}

impl Default for EstimateParams {
    fn default() -> Self {
        let o = OnlineParams::default();
        Self {
            state_rate_hz: o.state_rate_hz,
            smoother: o.smoother.method,
            incremental: o.smoother.incremental,
            lag_states: o.smoother.lag_states,
            marginalise: o.smoother.marginalise,
            window_iterations: o.smoother.iterations_per_update,
            resolve_iterations: o.smoother.full_solve.max_iterations,
            resolve_spacing_states: o.smoother.resolve_spacing_states,
            resolve_spacing_growth: o.smoother.resolve_spacing_growth,
            resolve_wide_states: o.smoother.resolve_wide_states,
            resolve_window_states: o.smoother.resolve_window_states,
            acc_noise_density: o.imu.acc_noise_density,
            gyro_noise_density: o.imu.gyro_noise_density,
            acc_bias_random_walk: o.imu.acc_bias_random_walk,
            gyro_bias_random_walk: o.imu.gyro_bias_random_walk,
            acc_bias_prior_sigma_mps2: o.first_state.acc_bias_sigma_mps2,
            gyro_bias_prior_sigma_radps: o.first_state.gyro_bias_sigma_radps,
            gravity_mps2: -o.imu.gravity_mps2.z,
            wheel_sigma_m: o.wheel_sigma_m,
            registration_sigma_m: o.registration_sigma_m,
            registration_full_pose: o.registration_full_pose,
            registration_across_sigma_m: o.registration_across_sigma_m,
            registration_gate_m: o.registration_gate_m,
            registration_gate_growth_mps: o.registration_gate_growth_mps,
            registration_gate_sigmas: o.registration_gate_sigmas,
            line_min_baseline_m: o.line_min_baseline_m,
            line_gate_sigmas: o.line_gate_sigmas,
            nonholonomic_sigma_mps: o.nonholonomic_sigma_mps,
            gravity_align_s: o.gravity_align_s,
            snapshot_every_states: 10,
            snapshot_growth: 0.05,
            background_solves: o.smoother.background,
            diagnostics: false,
        }
    }
}

impl EstimateParams {
    fn online(&self) -> OnlineParams {
        OnlineParams {
            state_rate_hz: self.state_rate_hz,
            smoother: SmootherParams {
                method: self.smoother,
                incremental: self.incremental,
                lag_states: self.lag_states,
                background: self.background_solves,
                marginalise: self.marginalise,
                resolve_spacing_states: self.resolve_spacing_states,
                resolve_spacing_growth: self.resolve_spacing_growth,
                resolve_wide_states: self.resolve_wide_states,
                resolve_window_states: self.resolve_window_states,
                iterations_per_update: self.window_iterations,
                full_solve: crate::batch::LmParams {
                    max_iterations: self.resolve_iterations,
                    ..SmootherParams::default().full_solve
                },
                ..SmootherParams::default()
            },
            imu: ImuParams {
                gravity_mps2: Vector3::new(0.0, 0.0, -self.gravity_mps2),
                acc_noise_density: self.acc_noise_density,
                gyro_noise_density: self.gyro_noise_density,
                acc_bias_random_walk: self.acc_bias_random_walk,
                gyro_bias_random_walk: self.gyro_bias_random_walk,
                ..ImuParams::xsens_mti30()
            },
            wheel_sigma_m: self.wheel_sigma_m,
            registration_sigma_m: self.registration_sigma_m,
            registration_full_pose: self.registration_full_pose,
            registration_across_sigma_m: self.registration_across_sigma_m,
            registration_gate_m: self.registration_gate_m,
            registration_gate_growth_mps: self.registration_gate_growth_mps,
            registration_gate_sigmas: self.registration_gate_sigmas,
            line_min_baseline_m: self.line_min_baseline_m,
            line_gate_sigmas: self.line_gate_sigmas,
            nonholonomic_sigma_mps: self.nonholonomic_sigma_mps,
            gravity_align_s: self.gravity_align_s,
            first_state: FirstStatePrior {
                acc_bias_sigma_mps2: self.acc_bias_prior_sigma_mps2,
                gyro_bias_sigma_radps: self.gyro_bias_prior_sigma_radps,
                ..FirstStatePrior::default()
            },
            ..OnlineParams::default()
        }
    }

    /// # Errors
    /// A parameter out of its range, named.
    fn check(&self) -> gprflow_params::Result {
        gprflow_params::positive("state_rate_hz", self.state_rate_hz)?;
        gprflow_params::at_least("lag_states", self.lag_states, 1)?;
        gprflow_params::at_least("window_iterations", self.window_iterations, 1)?;
        gprflow_params::at_least("resolve_iterations", self.resolve_iterations, 1)?;
        gprflow_params::at_least("resolve_spacing_states", self.resolve_spacing_states, 1)?;
        gprflow_params::non_negative("resolve_spacing_growth", self.resolve_spacing_growth)?;
        let inc = &self.incremental;
        for (key, value) in [
            ("incremental.relinearize_rotation_rad", inc.relinearize_rotation_rad),
            ("incremental.relinearize_translation_m", inc.relinearize_translation_m),
            ("incremental.relinearize_velocity_mps", inc.relinearize_velocity_mps),
            ("incremental.relinearize_bias", inc.relinearize_bias),
        ] {
            gprflow_params::positive(key, value)?;
        }
        gprflow_params::non_negative("incremental.wildfire_threshold", inc.wildfire_threshold)?;
        let positive = [
            ("acc_noise_density", self.acc_noise_density),
            ("gyro_noise_density", self.gyro_noise_density),
            ("acc_bias_random_walk", self.acc_bias_random_walk),
            ("gyro_bias_random_walk", self.gyro_bias_random_walk),
            ("acc_bias_prior_sigma_mps2", self.acc_bias_prior_sigma_mps2),
            ("gyro_bias_prior_sigma_radps", self.gyro_bias_prior_sigma_radps),
            ("gravity_mps2", self.gravity_mps2),
            ("wheel_sigma_m", self.wheel_sigma_m),
            ("registration_sigma_m", self.registration_sigma_m),
        ];
        for (key, value) in positive {
            gprflow_params::positive(key, value)?;
        }
        let off_or_positive = [
            ("nonholonomic_sigma_mps", self.nonholonomic_sigma_mps),
            ("gravity_align_s", self.gravity_align_s),
            ("registration_across_sigma_m", self.registration_across_sigma_m),
            ("registration_gate_m", self.registration_gate_m),
            ("registration_gate_growth_mps", self.registration_gate_growth_mps),
            ("registration_gate_sigmas", self.registration_gate_sigmas),
            ("line_gate_sigmas", self.line_gate_sigmas),
            ("snapshot_growth", self.snapshot_growth),
        ];
        for (key, value) in off_or_positive {
            gprflow_params::non_negative(key, value)?;
        }
        Ok(())
    }
}

/// The factor-graph estimator stage.
#[derive(Debug)]
pub struct EstimateStage {
    params: EstimateParams,
    est: OnlineEstimator,
    state_out: Output<StateEstimate>,
    trajectory_out: Output<Trajectory>,
    line_map_out: Output<LineMap>,
    /// The diagnostics output, when asked for.
    check_out: Option<Output<RegistrationCheck>>,
    last_stamp_ns: i64,
    /// The first `initial_pose` message was seen (later ones are ignored).
    origin_seen: bool,
    /// No `initial_pose` input but a `gps` one: the first GPS/INS message anchors the estimate
    /// (its position on the ground plane and its orientation are the first state's).
    anchor_on_gps: bool,
    /// No `initial_pose` or `gps` input but a `map_fix` one: the first locked map fix anchors
    /// the estimate (its position and orientation are the first state's).
    anchor_on_map_fix: bool,
    /// Map fixes not used because the tracker was not locked (dead-reckoned, not measured).
    unlocked_map_fixes: u64,
    /// Messages dropped as unusable (non-finite values).
    drops: Drops,
    /// Registrations dropped by `registration_gate_m`.
    gated_registrations: u64,
    /// States in the trajectory at the last snapshot.
    snapshot_states: u64,
}

/// A trajectory of `states` states is due a snapshot when the last one had `last` states.
fn snapshot_due(states: u64, last: u64, params: &EstimateParams) -> bool {
    params.snapshot_every_states > 0
        && states.is_multiple_of(params.snapshot_every_states)
        && states as f64 >= last as f64 * (1.0 + params.snapshot_growth)
}

fn pose_msg(p: &Pose3) -> Pose {
    let q = p.quaternion();
    Pose {
        position: Point {
            x: p.trans_m.x,
            y: p.trans_m.y,
            z: p.trans_m.z,
        },
        orientation: Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

fn pose_from_msg(p: &Pose) -> Pose3 {
    let o = &p.orientation;
    Pose3::from_quaternion(
        [o.x, o.y, o.z, o.w],
        Vector3::new(p.position.x, p.position.y, p.position.z),
    )
}

/// ROS covariance `[x y z rx ry rz]` <-> ours `[rx ry rz x y z]`: the same permutation both ways.
fn swap_rot_trans(c: &[f64; 36]) -> [f64; 36] {
    let perm = [3, 4, 5, 0, 1, 2];
    let mut out = [0.0; 36];
    for r in 0..6 {
        for k in 0..6 {
            out[r * 6 + k] = c[perm[r] * 6 + perm[k]];
        }
    }
    out
}

fn vec_msg(v: &Vector3<f64>) -> Vector3Msg {
    Vector3Msg { x: v.x, y: v.y, z: v.z }
}

impl EstimateStage {
    /// A measurement the estimator refused (non-finite values) is counted, logged with its
    /// input and seq, and dropped; any other error fails the stage.
    fn accept<T>(&mut self, input: &Input<'_>, result: crate::Result<T>) -> Result<Option<T>, StageError> {
        match result {
            Ok(v) => Ok(Some(v)),
            Err(crate::Error::BadMeasurement(why)) => {
                self.drops.record(Self::NAME, input, &why);
                Ok(None)
            }
            Err(e) => Err(StageError::failed(e)),
        }
    }

    /// A ground-plane position measurement (a locked map fix, a GPS/INS position) with its
    /// 6x6 covariance: the estimate's anchor when `anchor` and none is set yet, else a
    /// position factor.
    fn position_fix(
        &mut self,
        input: &Input<'_>,
        pose: &Pose,
        covariance: &[f64; 36],
        anchor: bool,
        what: &str,
    ) -> Result<(), StageError> {
        if anchor && !self.origin_seen {
            let mut origin = *pose;
            origin.position.z = 0.0;
            self.origin_seen = self.est.set_origin(pose_from_msg(&origin));
            tracing::info!(seq = input.seq(), "estimate: {what} anchors the estimate");
            return Ok(());
        }
        let sig = |v: f64| if v.is_finite() && v > 0.0 { v.sqrt() } else { 0.5 };
        let p = &pose.position;
        let added = self.est.map_fix(
            input.stamp_ns(),
            Vector2::new(p.x, p.y),
            [sig(covariance[0]), sig(covariance[7])],
        );
        self.accept(input, added)?;
        Ok(())
    }

    fn publish_state(&mut self, s: &StateOutput, out: &mut Outputs) -> Result<(), StageError> {
        let mut cov = [0.0; 36];
        if let Some(c) = &s.covariance
            && c.nrows() == 6
            && c.ncols() == 6
        {
            for r in 0..6 {
                for k in 0..6 {
                    cov[r * 6 + k] = c[(r, k)];
                }
            }
            cov = swap_rot_trans(&cov);
        }
        let msg = StateEstimate {
            header: Header::new(s.stamp_ns, "world"),
            state_index: s.index,
            world_from_body: PoseWithCovariance {
                pose: pose_msg(&s.pose),
                covariance: gprflow_msg::Covariance6(cov),
            },
            velocity_in_world_mps: vec_msg(&s.velocity_mps),
            accel_bias: vec_msg(&s.bias.acc_mps2),
            gyro_bias: vec_msg(&s.bias.gyro_radps),
        };
        out.send(self.state_out, &msg)?;
        let states = s.index + 1;
        if snapshot_due(states, self.snapshot_states, &self.params) {
            self.snapshot_states = states;
            self.publish_snapshots(s.stamp_ns, out)?;
        }
        Ok(())
    }

    /// The whole trajectory as the estimate holds it. Mid-run it is the incremental
    /// smoother's wildfire estimate (states far from the newest may lag by up to its
    /// threshold); at the end, after the final solve, the best one.
    fn publish_snapshots(&mut self, stamp_ns: i64, out: &mut Outputs) -> Result<(), StageError> {
        let traj = self.est.trajectory().map_err(StageError::failed)?;
        let msg = Trajectory {
            header: Header::new(stamp_ns, "world"),
            state_indices: traj.iter().map(|(i, _, _)| *i).collect(),
            poses: traj
                .iter()
                .map(|(_, s, p)| PoseStamped {
                    header: Header::new(*s, "world"),
                    pose: pose_msg(p),
                })
                .collect(),
        };
        out.send(self.trajectory_out, &msg)?;
        let lines = LineMap {
            header: Header::new(stamp_ns, "world"),
            lines: self
                .est
                .line_map()
                .into_iter()
                .map(|(id, l)| HoughLineMsg {
                    id,
                    rho_m: l.rho_m,
                    theta_rad: l.theta_rad,
                    ..HoughLineMsg::default()
                })
                .collect(),
        };
        out.send(self.line_map_out, &lines)
    }
}

impl Stage for EstimateStage {
    type Params = EstimateParams;
    const NAME: &'static str = "estimate";
    const ABOUT: &'static str =
        "factor-graph estimation (IMU preintegration, wheel, GPR registration, lines, map fixes; fixed-lag smoother)";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            // When connected, the first state waits for its first message.
            port("initial_pose", PoseStamped::TYPE_NAME, true),
            port("imu", Imu::TYPE_NAME, false),
            port("wheel", WheelOdometry::TYPE_NAME, true),
            port("registration", Registration::TYPE_NAME, true),
            port("line", LineObservation::TYPE_NAME, true),
            port("map_fix", MapFix::TYPE_NAME, true),
            // GPS/INS positions as ground-plane position factors, with their own covariance
            port("gps", Odometry::TYPE_NAME, true),
        ])
    }

    fn outputs(params: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        let mut ports = vec![
            PortSpec::new("state", StateEstimate::TYPE_NAME),
            PortSpec::new("trajectory", Trajectory::TYPE_NAME),
            PortSpec::new("line_map", LineMap::TYPE_NAME),
        ];
        if params.diagnostics {
            ports.push(PortSpec::new("registration_check", RegistrationCheck::TYPE_NAME));
        }
        Ok(ports)
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        params.check()
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let mut est = OnlineEstimator::new(params.online());
        est.report_gate_sigmas(params.diagnostics);
        let no_initial_pose = ports.input("initial_pose").is_none();
        let anchor_on_gps = no_initial_pose && ports.input("gps").is_some();
        let anchor_on_map_fix = no_initial_pose && !anchor_on_gps && ports.input("map_fix").is_some();
        if !no_initial_pose || anchor_on_gps || anchor_on_map_fix {
            est.wait_for_origin();
        }
        Ok(Self {
            est,
            state_out: ports.output("state")?,
            trajectory_out: ports.output("trajectory")?,
            line_map_out: ports.output("line_map")?,
            check_out: if params.diagnostics {
                Some(ports.output("registration_check")?)
            } else {
                None
            },
            params,
            last_stamp_ns: 0,
            origin_seen: false,
            anchor_on_gps,
            anchor_on_map_fix,
            unlocked_map_fixes: 0,
            drops: Drops::new(),
            gated_registrations: 0,
            snapshot_states: 0,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        self.last_stamp_ns = self.last_stamp_ns.max(input.stamp_ns());
        match input.name() {
            "initial_pose" if !self.origin_seen => {
                let m: PoseStamped = input.decode()?;
                self.origin_seen = true;
                if !self.est.set_origin(pose_from_msg(&m.pose)) {
                    tracing::warn!(
                        seq = input.seq(),
                        "initial_pose arrived after the first state; the estimate keeps its own origin"
                    );
                }
            }
            "imu" => {
                let m: Imu = input.decode()?;
                let a = &m.linear_acceleration;
                let w = &m.angular_velocity;
                let state = self.est.imu(
                    input.stamp_ns(),
                    Vector3::new(a.x, a.y, a.z),
                    Vector3::new(w.x, w.y, w.z),
                );
                if let Some(Some(s)) = self.accept(&input, state)? {
                    self.publish_state(&s, out)?;
                }
            }
            "wheel" => {
                let m: WheelOdometry = input.decode()?;
                self.est.wheel(m.distance_m);
            }
            "registration" => {
                let m: Registration = input.decode()?;
                let c = swap_rot_trans(&m.covariance.0);
                let covariance = (c.iter().any(|v| *v != 0.0)).then(|| DMatrix::from_row_slice(6, 6, &c));
                let r = RegistrationMeasurement {
                    reference_stamp_ns: m.reference_stamp.to_ns(),
                    query_stamp_ns: m.query_stamp.to_ns(),
                    relative_pose: pose_from_msg(&m.reference_from_query),
                    along_track_m: m.along_track_m,
                    covariance,
                };
                let outcome = self.est.registration(&r);
                match self.accept(&input, outcome)? {
                    Some(RegistrationOutcome::NoStates) => {
                        tracing::debug!(seq = input.seq(), "registration matches no states; dropped");
                    }
                    Some(
                        o @ (RegistrationOutcome::Added {
                            residual_m,
                            gate_m,
                            sigma_m,
                        }
                        | RegistrationOutcome::Gated {
                            residual_m,
                            gate_m,
                            sigma_m,
                        }),
                    ) => {
                        let gated = matches!(o, RegistrationOutcome::Gated { .. });
                        self.gated_registrations += u64::from(gated);
                        tracing::trace!(seq = input.seq(), residual_m, gate_m, sigma_m, gated, "registration");
                        if let Some(port) = self.check_out {
                            let check = RegistrationCheck {
                                header: Header::new(input.stamp_ns(), "map"),
                                reference_stamp: m.reference_stamp,
                                query_stamp: m.query_stamp,
                                along_track_m: r.along_track_m,
                                residual_m,
                                gate_m,
                                sigma_m,
                                accepted: !gated,
                            };
                            out.send(port, &check)?;
                        }
                    }
                    None => {}
                }
            }
            "line" => {
                let m: LineObservation = input.decode()?;
                let added = self
                    .est
                    .line(input.stamp_ns(), m.line_id, m.forward_distance_m, m.sigma_m);
                self.accept(&input, added)?;
            }
            "map_fix" => {
                let m: MapFix = input.decode()?;
                if !m.locked {
                    self.unlocked_map_fixes += 1;
                    return Ok(());
                }
                let anchor = self.anchor_on_map_fix;
                self.position_fix(
                    &input,
                    &m.world_from_body,
                    &m.covariance.0,
                    anchor,
                    "the first locked map fix",
                )?;
            }
            "gps" => {
                let m: Odometry = input.decode()?;
                let anchor = self.anchor_on_gps;
                self.position_fix(
                    &input,
                    &m.pose.pose,
                    &m.pose.covariance.0,
                    anchor,
                    "the first GPS/INS message",
                )?;
            }
            _ => {}
        }
        Ok(())
    }

    fn finish(&mut self, out: &mut Outputs) -> Result<(), StageError> {
        self.est.finish().map_err(StageError::failed)?;
        self.drops.report(Self::NAME);
        if self.est.unmatched_map_fixes() > 0 {
            tracing::warn!(
                map_fixes = self.est.unmatched_map_fixes(),
                "estimate: map fixes with no state within a state period (a gap in the IMU), not used"
            );
        }
        if self.unlocked_map_fixes > 0 {
            tracing::info!(
                map_fixes = self.unlocked_map_fixes,
                "estimate: map fixes without a lock, not used"
            );
        }
        if self.est.dropped_before_origin() > 0 {
            tracing::info!(
                imu_samples = self.est.dropped_before_origin(),
                "estimate: IMU samples before the first initial_pose, not used"
            );
        }
        if self.gated_registrations > 0 {
            tracing::info!(
                gated = self.gated_registrations,
                "estimate: registrations further than the registration gate from the estimate, dropped"
            );
        }
        if self.est.gated_lines() > 0 {
            tracing::info!(
                gated = self.est.gated_lines(),
                "estimate: line observations further than the line gate from the estimate, dropped"
            );
        }
        let (solves, solve_s) = self.est.gate_solves();
        if solves > 0 {
            tracing::info!(
                solves,
                solve_s,
                "estimate: whole-graph factorisations for the registration and line gates"
            );
        }
        if let Some(t) = self.est.solve_times() {
            tracing::info!(
                window_solves = t.window.0,
                window_s = t.window.1,
                window_iterations = t.window_iterations.0,
                window_linear_solves = t.window_iterations.1,
                narrow_resolves = t.narrow.0,
                narrow_s = t.narrow.1,
                wide_resolves = t.wide.0,
                wide_s = t.wide.1,
                "estimate: time in the smoother"
            );
        }
        if self.est.late_updates() > 0 {
            tracing::warn!(
                late = self.est.late_updates(),
                "estimate: updates that fell behind the state rate"
            );
        }
        self.publish_snapshots(self.last_stamp_ns, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector6;

    /// The snapshots published over a run of `n` states: how many, and their poses in all.
    fn snapshots(n: u64, params: &EstimateParams) -> (u64, u64) {
        let (mut last, mut count, mut poses) = (0, 0, 0);
        for states in 1..=n {
            if snapshot_due(states, last, params) {
                (last, count, poses) = (states, count + 1, poses + states);
            }
        }
        (count, poses)
    }

    #[test]
    fn snapshots_grow_linearly_with_the_run() {
        let mut params = EstimateParams::default();
        // Every 10 states while short: the sample runs' first 200 states as before.
        assert_eq!(snapshots(200, &params).0, 20);
        for n in [12_500, 37_500] {
            let (count, poses) = snapshots(n, &params);
            assert!(poses <= 22 * n, "{n} states: {count} snapshots of {poses} poses");
            assert!((20..200).contains(&count), "{n} states: {count} snapshots");
        }
        // Without the growth: every 10 states, the square of the run.
        params.snapshot_growth = 0.0;
        let (count, poses) = snapshots(12_500, &params);
        assert_eq!(count, 1250);
        assert!(poses > 7_000_000, "{poses}");
        // Off.
        params.snapshot_every_states = 0;
        assert_eq!(snapshots(1000, &params), (0, 0));
    }

    #[test]
    fn covariance_reordering_is_its_own_inverse() {
        let c: [f64; 36] = std::array::from_fn(|k| k as f64);
        assert_eq!(swap_rot_trans(&swap_rot_trans(&c)), c);
        // Our rotation variance (index 0) lands on ROS's roll variance (row 3, column 3).
        assert_eq!(swap_rot_trans(&c)[3 * 6 + 3], c[0]);
    }

    #[test]
    fn pose_messages_round_trip() {
        let p = Pose3::exp(&Vector6::new(0.3, -0.2, 2.5, 1.0, -4.0, 0.5));
        let back = pose_from_msg(&pose_msg(&p));
        assert!(p.between(&back).log().norm() < 1e-12);
    }

    #[test]
    fn params_out_of_range_are_named() {
        assert!(EstimateParams::default().check().is_ok());
        let gated = EstimateParams {
            registration_gate_m: 1.0,
            registration_gate_growth_mps: 0.02,
            ..EstimateParams::default()
        };
        assert!(gated.check().is_ok());
        for (params, key) in [
            (
                EstimateParams {
                    registration_gate_m: -1.0,
                    ..EstimateParams::default()
                },
                "registration_gate_m",
            ),
            (
                EstimateParams {
                    registration_gate_growth_mps: f64::NAN,
                    ..EstimateParams::default()
                },
                "registration_gate_growth_mps",
            ),
            (
                EstimateParams {
                    wheel_sigma_m: 0.0,
                    ..EstimateParams::default()
                },
                "wheel_sigma_m",
            ),
        ] {
            match params.check() {
                Err(e) => assert_eq!(e.path, vec![key.to_owned()], "{}", e.message),
                other => panic!("{key}: {other:?}"),
            }
        }
    }

    #[test]
    fn default_params_map_onto_the_online_defaults() {
        let o = EstimateParams::default().online();
        assert_eq!(o, OnlineParams::default());
    }
}
