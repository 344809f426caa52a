//! The gprflow simulator: subsurface worlds, trajectories and sensors, written as recordings.
//!
//! A [`Scenario`] declares a world (soil layers, texture, objects), a
//! radar (single-channel impulse GPR or the LGPR's SFCW array), the runs made in it and the
//! proprioceptive sensors. [`simulate`] writes one run to an MCAP recording with every sensor
//! topic, the ground truth and the world's truth features, deterministically per seed.
//!
//! Modules: [`scenario`] (the file format), [`world`] and [`scene`] (what the ground
//! returns), [`impulse`] and [`lgpr`] (the radars), [`motion`] (trajectories),
//! [`sensors`] (IMU, wheel, total station, GPS), [`output`] (recordings and the CMU-GPR
//! folder layout).

pub mod impulse;
pub mod lgpr;
mod load;
pub mod motion;
pub mod output;
pub mod reference;
pub mod rng;
pub mod scenario;
pub mod scene;
pub mod sensors;
pub mod world;

use std::path::PathBuf;

pub use output::{SimOptions, SimSummary, simulate};
pub use scenario::Scenario;

/// Topics a simulated recording carries (without the leading `/`).
pub mod topics {
    /// `gprflow_msgs/Trace`: raw int16 traces of the impulse GPR.
    pub const TRACE: &str = "gpr/trace";
    /// `gprflow_msgs/Sweep`: SFCW sweeps of the LGPR array (frequency domain).
    pub const SWEEP: &str = "lgpr/sweep";
    /// `gprflow_msgs/Sweep`: the array's factory calibration, once at the start.
    pub const FACTORY_CALIBRATION: &str = "lgpr/factory_calibration";
    /// `sensor_msgs/Imu`.
    pub const IMU: &str = "imu/data";
    /// `gprflow_msgs/WheelOdometry`.
    pub const WHEEL: &str = "wheel/odometry";
    /// `geometry_msgs/PoseStamped`: total-station ground truth (`world_from_body`).
    pub const TRUTH_POSE: &str = "truth/pose";
    /// `gprflow_msgs/LineMap`: the world's linear objects as Hough lines, once at the start.
    pub const TRUTH_LINES: &str = "truth/lines";
    /// `nav_msgs/Odometry`: GPS/INS fixes.
    pub const GPS: &str = "gps/odometry";
}

/// What can go wrong while simulating.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// A file cannot be read.
    #[error("{}: cannot read: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The reason.
        source: std::io::Error,
    },
    /// The scenario file is YAML but not a valid scenario.
    #[error("{at}: {message}")]
    Scenario {
        /// File, line, column and key path.
        at: Box<gprflow::graph::Location>,
        /// What is wrong.
        message: String,
    },
    /// A value is out of range.
    #[error("{at}: {message}")]
    Invalid {
        /// File, line, column and key path of the value.
        at: Box<gprflow::graph::Location>,
        /// What is wrong.
        message: String,
    },
    /// `--run` names no run of the scenario.
    #[error("no run named `{name}` (the scenario has: {})", known.join(", "))]
    UnknownRun {
        /// The name asked for.
        name: String,
        /// The runs there are.
        known: Vec<String>,
    },
    /// Writing the output failed.
    #[error("{}: cannot write: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The reason.
        source: std::io::Error,
    },
    /// The recording could not be written.
    #[error(transparent)]
    Record(#[from] gprflow::record::RecordError),
}
