//! The ONNX encoder (SPEC "Encoder"): a submap in ground order, standardised over the whole
//! image and put through the front end the model's metadata names ([`crate::front_end`]),
//! becomes features `K x h x w` ([`Features`]).

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::TensorRef;

use super::runtime::{onnxruntime_library, runtime};
use crate::SubmapView;
use crate::front_end::{FRONT_END_ITERATIONS_KEY, FRONT_END_KEY, FrontEnd, FrontEndScratch};
use crate::{Error, Result};

/// Added to the submap's standard deviation before dividing by it (SPEC "Input").
pub const STANDARDISE_EPSILON: f64 = 1e-6;

/// Name of the encoder's input (SPEC "Encoder").
pub const ENCODER_INPUT: &str = "submap";

/// Name of the encoder's output (SPEC "Encoder").
pub const ENCODER_OUTPUT: &str = "features";

/// Encoder features: `channels x rows x cols` f32, `data[(k * rows + row) * cols + col]`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Features {
    /// Channels, `K`.
    pub channels: usize,
    /// Rows, `h`.
    pub rows: usize,
    /// Columns, `w` (`ceil(submap cols / column_stride)`).
    pub cols: usize,
    /// Values, channel-major then row-major.
    pub data: Vec<f32>,
}

impl Features {
    /// Channel `k` (`rows x cols`, row-major); empty when `k` is out of range.
    pub fn channel(&self, k: usize) -> &[f32] {
        let n = self.rows * self.cols;
        self.data.get(k * n..(k + 1) * n).unwrap_or(&[])
    }

    pub(super) fn check(&self, what: &str) -> Result<()> {
        if self.channels == 0
            || self.rows == 0
            || self.cols == 0
            || self.data.len() != self.channels * self.rows * self.cols
        {
            return Err(Error::Shape(format!(
                "{what} features: {} values for {} x {} x {}",
                self.data.len(),
                self.channels,
                self.rows,
                self.cols
            )));
        }
        Ok(())
    }
}

/// The ONNX encoder (SPEC "Encoder"): one session, one intra-op and one inter-op thread,
/// sequential execution.
pub struct Encoder {
    session: Session,
    model_path: PathBuf,
    /// What runs before the graph, as the model's metadata names it.
    front_end: FrontEnd,
    front_end_scratch: FrontEndScratch,
    /// The standardised submap, reused from call to call.
    input: Vec<f32>,
}

impl std::fmt::Debug for Encoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Encoder")
            .field("model_path", &self.model_path)
            .field("front_end", &self.front_end)
            .finish_non_exhaustive()
    }
}

impl Encoder {
    /// Loads the encoder from `onnx_path`, loading ONNX Runtime first when this process has not
    /// (from `ort_library`, see [`onnxruntime_library`]).
    ///
    /// # Errors
    /// [`Error::OnnxRuntime`] when the library is missing or cannot be loaded; [`Error::Onnx`]
    /// when the model is missing, is no ONNX model, has not one float input `submap` and an
    /// output `features`, or names a front end this crate does not know.
    pub fn load(onnx_path: &Path, ort_library: Option<&Path>) -> Result<Encoder> {
        let env = runtime(&onnxruntime_library(ort_library))?;
        let failed = |message: String| Error::Onnx {
            model: onnx_path.to_path_buf(),
            message,
        };
        if !onnx_path.is_file() {
            return Err(failed("no such model file".into()));
        }
        let session = Session::builder(&env)
            .and_then(|b| Ok(b.with_intra_threads(1)?))
            .and_then(|b| Ok(b.with_inter_threads(1)?))
            .and_then(|b| Ok(b.with_parallel_execution(false)?))
            .and_then(|mut b| b.commit_from_file(onnx_path))
            .map_err(|e| failed(format!("ONNX Runtime: {e}")))?;
        let inputs: Vec<&str> = session.inputs().iter().map(|o| o.name()).collect();
        if inputs != [ENCODER_INPUT] {
            return Err(failed(format!(
                "inputs {inputs:?}, expected one input `{ENCODER_INPUT}` [1, 1, rows, cols]"
            )));
        }
        if !session.outputs().iter().any(|o| o.name() == ENCODER_OUTPUT) {
            let outputs: Vec<&str> = session.outputs().iter().map(|o| o.name()).collect();
            return Err(failed(format!(
                "outputs {outputs:?}, expected an output `{ENCODER_OUTPUT}` [1, K, h, w]"
            )));
        }
        let front_end = {
            let metadata = session
                .metadata()
                .map_err(|e| failed(format!("ONNX Runtime: metadata: {e}")))?;
            FrontEnd::from_metadata(
                metadata.custom(FRONT_END_KEY).as_deref(),
                metadata.custom(FRONT_END_ITERATIONS_KEY).as_deref(),
            )
            .map_err(failed)?
        };
        Ok(Encoder {
            session,
            model_path: onnx_path.to_path_buf(),
            front_end,
            front_end_scratch: FrontEndScratch::default(),
            input: Vec::new(),
        })
    }

    /// The model file.
    pub fn model_path(&self) -> &Path {
        &self.model_path
    }

    /// What runs before the graph.
    pub fn front_end(&self) -> FrontEnd {
        self.front_end
    }

    /// The features of `submap` (in ground order, not standardised).
    ///
    /// # Errors
    /// See [`Encoder::encode_into`].
    pub fn encode(&mut self, submap: &SubmapView<'_>) -> Result<Features> {
        let mut features = Features::default();
        self.encode_into(submap, &mut features)?;
        Ok(features)
    }

    /// The features of `submap` (in ground order, not standardised) into `features`, whose
    /// buffer is reused.
    ///
    /// # Errors
    /// A submap of inconsistent shape, a pixel that is NaN or infinite ([`Error::Pixels`]), an
    /// ONNX Runtime failure or an output that is not `[1, K, h, w]` ([`Error::Onnx`]).
    pub fn encode_into(&mut self, submap: &SubmapView<'_>, features: &mut Features) -> Result<()> {
        submap.check("submap")?;
        standardise(submap, &mut self.input)?;
        self.front_end_scratch
            .apply(self.front_end, &mut self.input, submap.rows, submap.cols)?;
        let failed = |message: String| Error::Onnx {
            model: self.model_path.clone(),
            message,
        };
        let input = TensorRef::from_array_view(([1, 1, submap.rows, submap.cols], &self.input[..]))
            .map_err(|e| failed(format!("ONNX Runtime: input tensor: {e}")))?;
        let outputs = self
            .session
            .run(ort::inputs![input])
            .map_err(|e| failed(format!("ONNX Runtime: {e}")))?;
        let Some(output) = outputs.get(ENCODER_OUTPUT) else {
            return Err(failed(format!("no output `{ENCODER_OUTPUT}`")));
        };
        let (shape, data) = output
            .try_extract_tensor::<f32>()
            .map_err(|e| failed(format!("output `{ENCODER_OUTPUT}`: {e}")))?;
        let dims: &[i64] = shape;
        let [1, k, h, w] = *dims else {
            return Err(failed(format!(
                "output `{ENCODER_OUTPUT}` has shape {dims:?}, expected [1, K, h, w]"
            )));
        };
        let (Ok(k), Ok(h), Ok(w)) = (usize::try_from(k), usize::try_from(h), usize::try_from(w)) else {
            return Err(failed(format!("output `{ENCODER_OUTPUT}` has shape {dims:?}")));
        };
        if k * h * w != data.len() || data.is_empty() {
            return Err(failed(format!(
                "output `{ENCODER_OUTPUT}` has shape {dims:?} and {} values",
                data.len()
            )));
        }
        features.channels = k;
        features.rows = h;
        features.cols = w;
        features.data.clear();
        features.data.extend_from_slice(data);
        Ok(())
    }
}

/// `x = (S - mean(S)) / (std(S) + 1e-6)` over the whole image (population std, f64), as f32,
/// into `out`.
fn standardise(submap: &SubmapView<'_>, out: &mut Vec<f32>) -> Result<()> {
    let pixels = submap.pixels;
    let sum = lane_sum(pixels, |p| p);
    // a NaN or infinite pixel makes the f64 sum so (finite f32 pixels cannot overflow it)
    if !sum.is_finite() {
        let i = pixels.iter().position(|p| !p.is_finite()).unwrap_or(0);
        return Err(Error::Pixels {
            index: i,
            row: i / submap.cols,
            col: i % submap.cols,
            value: pixels[i],
        });
    }
    let n = pixels.len() as f64;
    let mean = sum / n;
    let var = lane_sum(pixels, |p| (p - mean) * (p - mean)) / n;
    let scale = var.sqrt() + STANDARDISE_EPSILON;
    out.clear();
    out.extend(pixels.iter().map(|&p| ((f64::from(p) - mean) / scale) as f32));
    Ok(())
}

/// `Σ f(x)` over `values` in f64, in [`SUM_LANES`] interleaved partial sums (which vectorise).
#[inline(always)]
fn lane_sum(values: &[f32], f: impl Fn(f64) -> f64) -> f64 {
    let mut acc = [0.0f64; SUM_LANES];
    let chunks = values.chunks_exact(SUM_LANES);
    let rest = chunks.remainder();
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a += f(f64::from(v));
        }
    }
    for (a, &v) in acc.iter_mut().zip(rest) {
        *a += f(f64::from(v));
    }
    acc.iter().sum()
}

/// Partial sums of [`lane_sum`].
const SUM_LANES: usize = 8;
