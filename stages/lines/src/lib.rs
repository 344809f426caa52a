//! Subsurface line features (seed 000 ch. 5): a pipe crossed by the robot is a hyperbola in
//! the GPR submap; its apex is where the antenna passed over the line, and the along-track
//! distance from the apex to the newest trace is the robot's *forward distance* to the line
//! (§5.4, Fig. 5.5), the measurement of the line factor (eq. 5.7).
//!
//! - [`mod@detect`]: automatic hyperbola detection (§5.2.3; the thesis picked them by hand). A
//!   diffraction stack: for every apex (column, time) and every trial velocity the image is
//!   summed along the hyperbola `t(x) = sqrt(t0^2 + (2 (x - x0) / v)^2)` and normalised by the
//!   image's robust noise level; local maxima above `min_score` whose whole aperture lies in
//!   the submap are hyperbolas. An oblique crossing (angle `phi` between track and line)
//!   flattens the hyperbola to the velocity `v / sin(phi)`, so the trial velocities run from
//!   the soil's up to several times it.
//! - [`associate`]: which line an apex belongs to. Apexes are placed on the ground (by the
//!   estimate fed back to the stage, or the submaps' own odometry); an apex joins the line
//!   whose fitted ground line passes within `max_cross_m` of it at a similar apex time, else
//!   starts a new line. The stage first tries the estimator's own lines: the one whose
//!   predicted forward distance fits the measured one.
//! - [`observe`]: from hyperbolas to observations. Each apex is projected on the drive (wheel
//!   distance, stamp, odometry ground point), kept once across overlapping submaps (the
//!   strongest), and released with its forward distance once the drive has left it behind.
//!
//! `node` (feature `node`, default): the `lines` stage, which moves messages to and from an
//! [`Observer`].

#[cfg(feature = "node")]
pub mod node;

pub mod associate;
pub mod detect;
pub mod observe;

pub use associate::{AssociationParams, Associator, GroundPoint};
pub use detect::{DetectParams, Hyperbola, Image, detect};
pub use observe::{Observation, Observer, ObserverParams, SubmapSpan};

pub use gprflow_params::ParamError;

/// What can go wrong in this crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; its path names it as in the graph file.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// A submap that cannot be searched: its image's size or values, or its span's distances.
    #[error("{0}")]
    Shape(String),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;
