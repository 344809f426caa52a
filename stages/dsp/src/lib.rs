//! Signal processing of impulse GPR traces and submaps (seed 000 §3.2.2, Table 3.1). The
//! LGPR's stepped-frequency chain is in `gprflow-lgpr`.
//!
//! Plain functions over sample slices and images; no bus, files or clocks.
//! - [`trace`]: trace-level filters of an impulse radar: dewow, zero-time correction, FIR
//!   band-pass (triangular window, zero phase), SEC gain (eq. 3.1), stacking.
//! - [`window`]: window-level background subtraction (mean trace over all prior submaps, as the
//!   thesis prescribes, or the plain per-window mean).
//! - [`image`]: image-level wavelet denoising (BayesShrink, soft threshold) and gaussian
//!   smoothing along track.
//! - [`chain`]: the configurable trace chain the `dsp` stage runs.
//! - [`bench`](mod@bench): the trace-chain benchmark behind `gprflow bench dsp`.
//! - `node` (feature `node`, default): the stages, the only module that touches the runtime.
//!
//! Each filter is compared with a reference implementation (scipy.signal, scipy.ndimage,
//! PyWavelets, scikit-image) in the tests; `tools/peer/dsp_check.sh` regenerates the fixtures.

pub mod bench;
pub mod chain;
pub mod image;
#[cfg(feature = "node")]
pub mod node;
pub mod trace;
pub mod window;

pub use gprflow_params::ParamError;

/// What can go wrong in this crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; its path names it as in the graph file
    /// (`bandpass.taps`).
    #[error(transparent)]
    Param(#[from] ParamError),
    /// An input has the wrong length.
    #[error("{what}: expected {expected} values, got {got}")]
    Size {
        /// Which input.
        what: String,
        /// Expected length.
        expected: usize,
        /// Given length.
        got: usize,
    },
    /// An input holds NaN or an infinity.
    #[error("{what}: value {index} is not finite ({value})")]
    NonFinite {
        /// Which input.
        what: String,
        /// Index of the first bad value.
        index: usize,
        /// The value.
        value: f64,
    },
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;
