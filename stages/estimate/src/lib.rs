//! Factor-graph estimation for GPR localisation (seed 000 §2.1, §4.2.2, §4.7, §5.3-5.6),
//! on nalgebra and faer.
//!
//! - [`lie`]: SO(3)/SE(3) maps and Jacobians; [`values`]: the variables (pose, velocity, IMU
//!   bias, Hough line); [`noise`]: Gaussian noise and robust kernels (Huber, Cauchy).
//! - [`factors`] and [`imu`]: priors, relative pose (wheel, GPR, loop closure; eq. 4.12/4.14),
//!   along-track distance (the learned GPR model, wheel encoder), position fixes (GPS, prior
//!   map), the line factor of eq. 5.7, ground-vehicle constraints (non-holonomic, planar), the
//!   bias random walk (eq. 4.6-4.7) and IMU preintegration (eq. 4.4-4.5) whose factor matches
//!   GTSAM 4.3's `CombinedImuFactor` to 1e-9.
//! - [`graph`] and [`linear`]: the factor graph, its linearisation into block-sparse normal
//!   equations and faer's supernodal sparse Cholesky, whose symbolic factorisation is kept while
//!   the structure stays (every LM iteration; every window update of the same shape).
//! - [`batch`]: Levenberg-Marquardt; [`incremental`]: the incremental smoother, iSAM2-style
//!   partial re-elimination of a Bayes tree kept over the whole graph (nested-dissection
//!   ordering, fluid relinearisation, marginal covariance of the newest state);
//!   [`smoother`]: one interface over it and the older fixed-lag smoother (a window plus
//!   full re-solves).
//! - [`relative`]: the marginal variance of a scalar function of the estimate (the
//!   along-track distance between two states) from the whole graph's information, for the
//!   online estimator's Mahalanobis gate on registrations.
//! - [`lines`]: initial values of line parameters (Fig. 5.7, eq. 5.8-5.12).
//! - [`online`]: states at a fixed rate from time-stamped measurements (plain code).
//! - [`problem`] and [`bench`](mod@bench): the GTSAM peer's export format and `gprflow bench estimate`.
//! - `node` (feature `node`, default): the `estimate` stage, the only module that touches the
//!   runtime.
//!
//! Every factor's Jacobians are checked against central differences in its tests; the IMU
//! factor and whole solves are checked against GTSAM (`tools/peer/`).

pub mod batch;
pub mod bench;
mod cholesky;
pub mod factor;
pub mod factors;
pub mod graph;
pub mod imu;
pub mod incremental;
pub mod lie;
pub mod linear;
pub mod lines;
pub mod marginal;
#[cfg(feature = "node")]
pub mod node;
pub mod noise;
pub mod online;
pub mod problem;
pub mod relative;
pub mod smoother;
pub mod values;

/// Errors of the estimation library.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A factor refers to a variable that does not exist.
    #[error("unknown variable {0}")]
    UnknownVariable(usize),
    /// A factor found a variable of another kind than it needs.
    #[error("variable {id} is not a {expected}")]
    WrongKind {
        /// The variable.
        id: usize,
        /// What the factor needs.
        expected: &'static str,
    },
    /// A noise model that cannot be used.
    #[error("bad noise model: {0}")]
    BadNoise(String),
    /// A measurement that cannot be used.
    #[error("bad measurement: {0}")]
    BadMeasurement(String),
    /// The linear system could not be factorised (not positive definite even with damping).
    #[error("linear solve failed: {0}")]
    LinearSolve(String),
    /// A problem file that cannot be read.
    #[error("{path}:{line}: {message}")]
    Parse {
        /// File.
        path: String,
        /// 1-based line number (0: the file as a whole).
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// I/O on a problem file.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
}

/// Result with the library's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;
