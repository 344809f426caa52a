//! The localising GPR of MIT Lincoln Laboratory (seed 001): processing of its 11-channel
//! stepped-frequency continuous-wave (SFCW) sweeps, prior maps of them, and localisation
//! against a prior map.
//!
//! - [`sfcw`]: self and factory calibration (eq. 2-4), the 8 ns delay, the Chebyshev window,
//!   the complex-to-real inverse FFT, the distance-based IIR high-pass (eq. 5-7) and the range
//!   gain.
//! - [`mod@array`]: where each channel sits on the vehicle.
//! - [`map`]: the on-disk map store, the 50 m local grid (§2.2.1) and its double buffer.
//! - [`track`]: the correlation of eq. 8, the particle swarm of eq. 9-10 and the tracker's
//!   lock logic (§2.2.2).
//! - `node` (feature `node`, default): the `lgpr_dsp`, `lgpr_map` and `lgpr_track` stages,
//!   the only modules that touch the runtime.

pub mod array;
pub mod error;
pub mod map;
#[cfg(feature = "node")]
pub mod node;
pub mod sfcw;
pub mod track;

pub use error::{Error, Result};
