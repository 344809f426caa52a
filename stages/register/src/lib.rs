//! Registration of GPR submaps (seed 000 ch. 4).
//!
//! - [`engineered`]: the engineered baseline, the along-track shift that maximises the Pearson
//!   correlation of the overlapping region of two submaps (eq. 4.2-4.3).
//!
//! - [`learned`]: the learned model (seed 000 §4.5-4.6, `tools/train/SPEC.md`): ONNX encoder,
//!   spatial correlation of the features, regression head.
//! - [`candidates`]: loop-candidate selection from the current estimate (or the ground truth,
//!   the oracle association used for evaluation).
//! - `node` (feature `node`, default): the `register` stage.

pub mod candidates;
pub mod engineered;
pub mod learned;
#[cfg(feature = "node")]
pub mod node;

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
    /// A submap pixel is NaN or infinite.
    #[error("submap pixels[{index}] (row {row}, col {col}) is {value}")]
    Pixels {
        /// Index into the pixels.
        index: usize,
        /// Its row.
        row: usize,
        /// Its column.
        col: usize,
        /// The value.
        value: f32,
    },
    /// The ONNX Runtime library is missing or cannot be loaded.
    #[error(
        "ONNX Runtime library {}: {message}; run tools/scripts/ensure-onnxruntime.sh, or give the library's path (parameter or GPRFLOW_ONNXRUNTIME)",
        path.display()
    )]
    OnnxRuntime {
        /// The library file tried.
        path: std::path::PathBuf,
        /// What went wrong.
        message: String,
    },
    /// An ONNX model is missing, malformed, fails to run or gives an unexpected output.
    #[error("{}: {message}", model.display())]
    Onnx {
        /// The model file.
        model: std::path::PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A head file is malformed; `field` names the part (`layers[0].weights`).
    #[error("{}: {field}: {message}", file.display())]
    Head {
        /// The head file.
        file: std::path::PathBuf,
        /// The field, as a path into the JSON.
        field: String,
        /// What is wrong and what was given.
        message: String,
    },
    /// A file cannot be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;
