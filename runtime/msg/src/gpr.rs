//! The `gprflow_msgs` package: GPR-specific messages.
//!
//! Units and frames are in field names. Poses are `world_from_body` unless named
//! otherwise; `header.stamp` is the sensor time.

use std::borrow::Cow;

use super::{Covariance6, Header, Pose, PoseStamped, PoseWithCovariance, Time, Vector3, message, stamped};

message! {
    /// One A-scan of an impulse GPR channel. Exactly one of the sample arrays is filled:
    /// raw counts as the radar wrote them (`int16`/`int32`) or processed amplitudes
    /// (`float32`). Sample `k` is at two-way time `time_zero_ns + k * sample_interval_ns`.
    pub struct Trace<'a> = "gprflow_msgs/msg/Trace" {
        pub header: Header,
        /// Channel index within a multichannel radar (0 for single-channel).
        pub channel: u16,
        /// Sample interval, ns.
        pub sample_interval_ns: f64,
        /// Two-way time of the first sample, ns.
        pub time_zero_ns: f64,
        /// Antenna centre frequency, Hz.
        pub center_frequency_hz: f64,
        /// Along-track distance reported by the radar's own odometer, m (NaN when none).
        pub distance_m: f64,
        pub samples_i16: Cow<'a, [i16]>,
        pub samples_i32: Cow<'a, [i32]>,
        pub samples_f32: Cow<'a, [f32]>,
    }
}

/// The samples of a [`Trace`], whatever their type.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Samples<'s> {
    /// Raw 16-bit counts.
    I16(&'s [i16]),
    /// Raw 32-bit counts.
    I32(&'s [i32]),
    /// Processed amplitudes.
    F32(&'s [f32]),
}

impl Trace<'_> {
    /// The filled sample array (`F32(&[])` for an empty trace).
    pub fn samples(&self) -> Samples<'_> {
        if !self.samples_i16.is_empty() {
            Samples::I16(&self.samples_i16)
        } else if !self.samples_i32.is_empty() {
            Samples::I32(&self.samples_i32)
        } else {
            Samples::F32(&self.samples_f32)
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples_i16.len() + self.samples_i32.len() + self.samples_f32.len()
    }

    /// True when the trace has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

message! {
    /// One sweep of a multichannel stepped-frequency continuous-wave (SFCW) array.
    ///
    /// `domain` 0 (frequency): `values` holds interleaved (re, im) per channel and tone,
    /// channel-major, `bin_count` tones from `start_frequency_hz` in steps of
    /// `frequency_step_hz`; `calibration` holds the calibration channel the same way.
    /// `domain` 1 (time): `values` holds real samples per channel, `bin_count` per channel,
    /// `sample_interval_ns` apart; `calibration` is empty.
    pub struct Sweep<'a> = "gprflow_msgs/msg/Sweep" {
        pub header: Header,
        pub domain: u8,
        pub channel_count: u32,
        pub bin_count: u32,
        pub start_frequency_hz: f64,
        pub frequency_step_hz: f64,
        pub sample_interval_ns: f64,
        pub values: Cow<'a, [f32]>,
        pub calibration: Cow<'a, [f32]>,
    }
}

impl Sweep<'_> {
    /// `domain` value of a sweep of complex tones.
    pub const DOMAIN_FREQUENCY: u8 = 0;
    /// `domain` value of a sweep of real range samples.
    pub const DOMAIN_TIME: u8 = 1;
}

message! {
    /// Wheel-encoder odometry: signed distance travelled along track.
    pub struct WheelOdometry = "gprflow_msgs/msg/WheelOdometry" {
        pub header: Header,
        /// Cumulative signed distance, m.
        pub distance_m: f64,
        /// Cumulative encoder ticks.
        pub ticks: i64,
        /// Along-track speed, m/s.
        pub speed_mps: f64,
    }
}

message! {
    /// A submap: traces resampled uniformly along track, `rows` samples deep by `cols`
    /// positions long, row-major (`pixels[row * cols + col]`). `header.stamp` is the stamp
    /// of the last trace; poses are odometry poses (`world_from_body`) at its ends.
    pub struct Submap<'a> = "gprflow_msgs/msg/Submap" {
        pub header: Header,
        pub id: u32,
        pub start_stamp: Time,
        pub start_distance_m: f64,
        pub end_distance_m: f64,
        /// Along-track size of one column, m.
        pub resolution_m: f64,
        pub sample_interval_ns: f64,
        pub rows: u32,
        pub cols: u32,
        pub start_pose: Pose,
        pub end_pose: Pose,
        /// Average-pooled row-wise standard deviation.
        pub saliency: f32,
        /// The validity rule held over the whole submap.
        pub valid: bool,
        pub pixels: Cow<'a, [f32]>,
        /// When the rig was over each column's centre, ns, one per column (interpolated
        /// between the traces around it): a shift found on the grid maps to a moment of the
        /// pass without the wheel's scale.
        pub column_stamps_ns: Cow<'a, [i64]>,
    }
}

message! {
    /// A registration between two submaps: `reference_from_query` and its covariance
    /// (x, y, z, rx, ry, rz). Along-track-only models fill `along_track_m` and its variance
    /// and leave the other axes with large variance.
    pub struct Registration = "gprflow_msgs/msg/Registration" {
        pub header: Header,
        pub reference_submap: u32,
        pub query_submap: u32,
        pub reference_stamp: Time,
        pub query_stamp: Time,
        pub reference_from_query: Pose,
        pub covariance: Covariance6,
        pub along_track_m: f64,
        pub along_track_variance_m2: f64,
        /// Model confidence, or peak correlation for the engineered method.
        pub score: f32,
        /// `engineered`, `learned`, `oracle`, ...
        pub method: String,
    }
}

message! {
    /// One candidate pair the register stage tried, registered or refused, and why: a
    /// diagnostic (the stage's `attempt` output, with its `diagnostics` parameter on) that
    /// `gprflow eval` checks against the truth.
    pub struct RegistrationAttempt = "gprflow_msgs/msg/RegistrationAttempt" {
        /// Stamped with the query's anchor.
        pub header: Header,
        pub reference_submap: u32,
        pub query_submap: u32,
        /// The two anchors (not the overlap stamps a registration may carry).
        pub reference_stamp: Time,
        pub query_stamp: Time,
        /// `engineered`, `learned`, `oracle`, ...
        pub method: String,
        /// `registered`, or the reason of the refusal (`low_score`, `shape`, `share`, ...).
        pub outcome: String,
        /// The along-track shift the method found, m (NaN when it found none).
        pub shift_m: f64,
        /// The method's score (NaN when none).
        pub score: f64,
        /// The travel-time stretch of the query that was judged (1 without the search).
        pub stretch: f64,
    }
}

message! {
    /// The estimator's verdict on one registration: taken into the graph, or dropped by
    /// the gate. A diagnostic (the estimate stage's `registration_check` output, with its
    /// `diagnostics` parameter on) that `gprflow eval` checks against the truth.
    pub struct RegistrationCheck = "gprflow_msgs/msg/RegistrationCheck" {
        /// Stamped when the registration arrived (its query stamp).
        pub header: Header,
        pub reference_stamp: Time,
        pub query_stamp: Time,
        /// The measured along-track distance between the two stamps, m.
        pub along_track_m: f64,
        /// The estimate's along-track distance minus the measured one, m (with `sigma_m`,
        /// the estimate as the registrations taken since it was last solved move it).
        pub residual_m: f64,
        /// The gate at that moment, m (0: off).
        pub gate_m: f64,
        /// The residual's predicted standard deviation, m: the estimate's marginal
        /// along-track uncertainty between the two states and the registration's sigma
        /// (0: not computed).
        pub sigma_m: f64,
        /// Taken into the graph (false: dropped by the gate).
        pub accepted: bool,
    }
}

message! {
    /// A detected subsurface line crossing (hyperbola apex) seen from the body.
    pub struct LineObservation = "gprflow_msgs/msg/LineObservation" {
        pub header: Header,
        /// Associated line id; `u32::MAX` when not (yet) associated.
        pub line_id: u32,
        /// Forward distance from the body to the line along track, m.
        pub forward_distance_m: f64,
        pub sigma_m: f64,
        /// Two-way time of the hyperbola apex, ns.
        pub apex_time_ns: f64,
        pub depth_m: f64,
        pub score: f32,
        /// The submap the hyperbola was found in.
        pub submap_id: u32,
        /// Wheel distance of the apex (the submaps' along-track coordinate), m.
        pub along_distance_m: f64,
        /// When the antenna passed over the apex (interpolated in the submap).
        pub apex_stamp: Time,
        /// Velocity of the fitted hyperbola, m/ns (the soil's over sin of the crossing angle).
        pub velocity_m_per_ns: f64,
    }
}

message! {
    /// A 2-D line in Hough form: points p with p . (cos theta, sin theta) = rho.
    pub struct HoughLine = "gprflow_msgs/msg/HoughLine" {
        pub id: u32,
        pub rho_m: f64,
        pub theta_rad: f64,
        /// Covariance of (rho, theta), row-major.
        pub covariance: [f64; 4],
    }
}

message! {
    /// The current estimate of every mapped line.
    pub struct LineMap = "gprflow_msgs/msg/LineMap" {
        pub header: Header,
        pub lines: Vec<HoughLine>,
    }
}

message! {
    /// The estimate of one state of the factor graph.
    pub struct StateEstimate = "gprflow_msgs/msg/StateEstimate" {
        pub header: Header,
        pub state_index: u64,
        pub world_from_body: PoseWithCovariance,
        pub velocity_in_world_mps: Vector3,
        pub accel_bias: Vector3,
        pub gyro_bias: Vector3,
    }
}

message! {
    /// A snapshot of the whole estimated trajectory.
    pub struct Trajectory = "gprflow_msgs/msg/Trajectory" {
        pub header: Header,
        pub state_indices: Vec<u64>,
        pub poses: Vec<PoseStamped>,
    }
}

message! {
    /// A prior-map registration result (LGPR, 5-DOF: x, y, yaw, roll, height).
    pub struct MapFix = "gprflow_msgs/msg/MapFix" {
        pub header: Header,
        pub world_from_body: Pose,
        pub covariance: Covariance6,
        pub correlation: f32,
        pub overlapping_channels: u32,
        /// The lock criteria held (correlation, overlap, velocity consistency).
        pub locked: bool,
    }
}

stamped!(
    Trace<'a>,
    Sweep<'a>,
    WheelOdometry,
    Submap<'a>,
    Registration,
    RegistrationAttempt,
    RegistrationCheck,
    LineObservation,
    LineMap,
    StateEstimate,
    Trajectory,
    MapFix,
);
