//! What can go wrong in this crate.

use std::fmt;

pub use gprflow_params::ParamError;

/// Where in a sweep a bad tone sits: a measurement channel, or the calibration channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ToneIndex {
    /// Measurement channel (element pair), `None` for the calibration channel.
    pub channel: Option<usize>,
    /// Tone index within the sweep (0 = the start frequency).
    pub tone: usize,
}

impl fmt::Display for ToneIndex {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.channel {
            Some(channel) => write!(f, "channel {channel} tone {}", self.tone),
            None => write!(f, "calibration channel tone {}", self.tone),
        }
    }
}

/// What can go wrong in this crate.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; its path names it as in the graph file
    /// (`range_gain.reference_ns`).
    #[error(transparent)]
    Param(#[from] ParamError),
    /// An input has the wrong length.
    #[error("{what}: expected {expected} values, got {got}")]
    Size {
        /// Which input.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Given length.
        got: usize,
    },
    /// A tone holds NaN or an infinity.
    #[error("{what}: {at} is not finite ({re}, {im})")]
    NonFinite {
        /// Which input (`values`, `calibration`, `factory values`, ...).
        what: &'static str,
        /// The first bad tone.
        at: ToneIndex,
        /// Its real part.
        re: f64,
        /// Its imaginary part.
        im: f64,
    },
    /// A divisor (a calibration tone, or a factory calibration ratio) is zero or too small to
    /// divide by (magnitude below [`crate::sfcw::MIN_DIVISOR_MAGNITUDE`]).
    #[error("{what}: {at} has magnitude {magnitude:e}, too small to divide by")]
    ZeroDivisor {
        /// Which divisor.
        what: &'static str,
        /// The first bad tone.
        at: ToneIndex,
        /// Its magnitude.
        magnitude: f64,
    },
    /// The along-track distance since the previous sweep is negative or not finite.
    #[error("sweep {sweep}: distance since the previous sweep is {distance_m} m (must be finite and >= 0)")]
    Distance {
        /// Index of the sweep since the filter was created or reset (0 = the first).
        sweep: u64,
        /// The distance given, m.
        distance_m: f64,
    },
    /// An output sample does not fit an `f32` (the input was close to the `f32` range).
    #[error("sweep {sweep}: output channel {channel} sample {sample} overflows f32 ({value:e})")]
    Overflow {
        /// Index of the sweep since the chain was created or reset.
        sweep: u64,
        /// Channel of the sample.
        channel: usize,
        /// Range sample index.
        sample: usize,
        /// The value in `f64`.
        value: f64,
    },
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;

/// A [`Error::Param`] at `key`.
pub(crate) fn param(key: &str, message: impl Into<String>) -> Error {
    Error::Param(ParamError::new(key, message))
}
