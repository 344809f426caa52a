//! The localising GPR of MIT Lincoln Laboratory (seed 001): processing of its 11-channel
//! stepped-frequency continuous-wave (SFCW) sweeps.
//!
//! - [`sfcw`]: self and factory calibration (eq. 2-4), the 8 ns delay, the Chebyshev window,
//!   the complex-to-real inverse FFT, the distance-based IIR high-pass (eq. 5-7) and the range
//!   gain.
//! - `node` (feature `node`, default): the `lgpr_dsp` stage, the only module that touches the
//!   runtime.

pub mod error;
#[cfg(feature = "node")]
pub mod node;
pub mod sfcw;

pub use error::{Error, Result};
