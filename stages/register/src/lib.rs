//! Registration of GPR submaps (seed 000 ch. 4).
//!
//! - [`engineered`]: the engineered baseline, the along-track shift that maximises the Pearson
//!   correlation of the overlapping region of two submaps (eq. 4.2-4.3).
//!
//! The learned model (ONNX encoder, spatial correlation, linear head), loop-candidate selection
//! and the `register` stage come with issue 6.

pub mod engineered;

/// What can go wrong in this crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; `key` names it.
    #[error("{key}: {message}")]
    Param {
        /// Parameter name.
        key: &'static str,
        /// What is wrong and what was given.
        message: String,
    },
    /// Two submaps cannot be compared (different shapes, wrong pixel count).
    #[error("{0}")]
    Shape(String),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;
