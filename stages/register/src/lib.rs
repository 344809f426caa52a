//! Registration of GPR submaps (seed 000 ch. 4).
//!
//! - [`engineered`]: the engineered baseline, the along-track shift that maximises the Pearson
//!   correlation of the overlapping region of two submaps (eq. 4.2-4.3).
//!
//! - [`learned`]: the learned model (seed 000 §4.5-4.6, `tools/train/SPEC.md`): ONNX encoder,
//!   spatial correlation of the features, regression head.
//! - [`front_end`]: the encoder's weight-free front end, run before the ONNX graph.
//! - [`stretch`]: a submap's travel times stretched, for the learned method's search over the
//!   wave speed changing between passes.
//! - [`closer`]: the loop closer, in plain values: reference keeping, loop candidates, one
//!   [`closer::Matcher`] per method (engineered, learned, oracle, zeroth), overlap stamps.
//! - [`candidates`]: loop-candidate selection from the current estimate (or the ground truth,
//!   the oracle association used for evaluation).
//! - `node` (feature `node`, default): the `register` stage, which only moves messages.

pub mod candidates;
pub mod closer;
pub mod engineered;
pub mod front_end;
pub mod learned;
#[cfg(feature = "node")]
pub mod node;
pub mod stretch;

pub use gprflow_params::ParamError;

/// A submap image: `rows x cols`, row-major, columns `resolution_m` apart.
#[derive(Debug, Clone, Copy)]
pub struct SubmapView<'a> {
    /// Pixels, `pixels[row * cols + col]`.
    pub pixels: &'a [f32],
    /// Rows (samples per column).
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Along-track size of a column, m.
    pub resolution_m: f64,
}

impl SubmapView<'_> {
    pub(crate) fn check(&self, what: &str) -> Result<()> {
        if self.rows == 0 || self.cols == 0 || self.pixels.len() != self.rows * self.cols {
            return Err(Error::Shape(format!(
                "{what}: {} pixels for {} x {}",
                self.pixels.len(),
                self.rows,
                self.cols
            )));
        }
        if !(self.resolution_m.is_finite() && self.resolution_m > 0.0) {
            return Err(Error::Shape(format!("{what}: resolution {} m", self.resolution_m)));
        }
        Ok(())
    }
}

/// What can go wrong in this crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; its path names it as in the graph file.
    #[error(transparent)]
    Param(#[from] ParamError),
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
    /// The temporary file of the references' pixels (see `closer::store`).
    #[error("register: the references' spill file: {0}")]
    Spill(String),
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

/// A [`Error::Param`] at `key`.
pub(crate) fn param(key: &str, message: impl Into<String>) -> Error {
    Error::Param(ParamError::new(key, message))
}

/// `Ok` when a shift search is valid: `max_shift_m` finite and >= 0, `min_overlap` in (0, 1].
pub(crate) fn check_shift_search(max_shift_m: f64, min_overlap: f64) -> gprflow_params::Result {
    gprflow_params::non_negative("max_shift_m", max_shift_m)?;
    gprflow_params::fraction("min_overlap", min_overlap)
}
