//! The learned registration model (seed 000 §4.5-4.6, "Ground Encoding"), inference side: the
//! contract is `tools/train/SPEC.md`, which training (PyTorch) and this module compute alike.
//!
//! - [`Encoder`]: the ONNX encoder (ONNX Runtime through `ort`, one thread) turns a submap in
//!   ground order into features `K x h x w` ([`Features`]); the submap is standardised over the
//!   whole image first (f64 mean and population std, stored as f32), then goes through the
//!   front end the model's metadata names ([`crate::front_end`]).
//! - [`correlate`] / [`Correlator`]: the spatial correlation (§4.5.3) of reference and query
//!   features, per channel the Pearson correlation of the shared block for every integer column
//!   shift, its argmax refined by a parabola: the vector `v = [tau_1 .. tau_K, m_1 .. m_K]`.
//! - [`Head`]: the linear or nonlinear regression head (JSON) mapping `v` to the shift, m.
//! - [`Model`]: the three together; [`Model::register`] answers "do these two share features"
//!   (`mean m_k >= share_threshold`, §4.5.2) and, when they do, the shift and its variance.
//!
//! Putting a submap in ground order (columns reversed when it was driven backwards) is the
//! caller's job.
//!
//! ONNX Runtime is loaded once per process from a library file ([`onnxruntime_library`] says
//! which), `libonnxruntime.so.1.31.1` as `tools/scripts/ensure-onnxruntime.sh` installs it.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

use ort::session::Session;
use ort::value::TensorRef;
use serde_json::{Map, Value};

use crate::engineered::SubmapView;
use crate::front_end::{FRONT_END_ITERATIONS_KEY, FRONT_END_KEY, FrontEnd, FrontEndScratch};
use crate::{Error, Result};

/// The ONNX Runtime library file this crate is built for.
pub const ONNXRUNTIME_LIBRARY: &str = "libonnxruntime.so.1.31.1";

/// Environment variable naming the ONNX Runtime library when no path is given.
pub const ONNXRUNTIME_ENV: &str = "GPRFLOW_ONNXRUNTIME";

/// Added to the submap's standard deviation before dividing by it (SPEC "Input").
pub const STANDARDISE_EPSILON: f64 = 1e-6;

/// Name of the encoder's input (SPEC "Encoder").
pub const ENCODER_INPUT: &str = "submap";

/// Name of the encoder's output (SPEC "Encoder").
pub const ENCODER_OUTPUT: &str = "features";

/// A block whose variance is at most this fraction of its sum of squares counts as flat (its
/// norm as 0): the one-pass sums leave rounding noise where a constant block has none.
const FLAT_VARIANCE_FRACTION: f64 = 1e-12;

/// The `format` of a head file.
pub const HEAD_FORMAT: &str = "gprflow-register-head";

/// The `version` of a head file this module reads.
pub const HEAD_VERSION: u64 = 1;

// ---------------------------------------------------------------------------------------------
// ONNX Runtime

/// The ONNX Runtime library to load, and where its path came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OnnxRuntimeLibrary {
    /// The library file (absolute).
    pub path: PathBuf,
    /// Where the path came from: `parameter`, `GPRFLOW_ONNXRUNTIME` or `default`.
    pub source: &'static str,
}

/// The ONNX Runtime library to load: `explicit` when given, else the file named by
/// `GPRFLOW_ONNXRUNTIME` when set, else `.onnxruntime/libonnxruntime.so.1.31.1` under the current
/// directory (where `tools/scripts/ensure-onnxruntime.sh` puts it in a checkout).
pub fn onnxruntime_library(explicit: Option<&Path>) -> OnnxRuntimeLibrary {
    let (path, source) = match explicit {
        Some(p) => (p.to_path_buf(), "parameter"),
        None => match std::env::var_os(ONNXRUNTIME_ENV) {
            Some(p) if !p.is_empty() => (PathBuf::from(p), ONNXRUNTIME_ENV),
            _ => (Path::new(".onnxruntime").join(ONNXRUNTIME_LIBRARY), "default"),
        },
    };
    let path = std::path::absolute(&path).unwrap_or(path);
    OnnxRuntimeLibrary { path, source }
}

/// The process's ONNX Runtime environment and the library it was loaded from.
static RUNTIME: Mutex<Option<(PathBuf, ort::environment::Environment)>> = Mutex::new(None);

/// Loads ONNX Runtime (once per process) and returns its environment.
fn runtime(library: &OnnxRuntimeLibrary) -> Result<ort::environment::Environment> {
    let mut loaded = RUNTIME.lock().unwrap_or_else(PoisonError::into_inner);
    // the same file under another name is the same library
    let canonical = std::fs::canonicalize(&library.path).unwrap_or_else(|_| library.path.clone());
    if let Some((path, env)) = loaded.as_ref() {
        if *path != canonical {
            return Err(Error::OnnxRuntime {
                path: library.path.clone(),
                message: format!(
                    "ONNX Runtime is already loaded in this process from {}; one library per process",
                    path.display()
                ),
            });
        }
        return Ok(env.clone());
    }
    if !library.path.is_file() {
        return Err(Error::OnnxRuntime {
            path: library.path.clone(),
            message: format!("no such file (path from {})", library.source),
        });
    }
    let failed = |message: String| Error::OnnxRuntime {
        path: library.path.clone(),
        message,
    };
    let env = ort::init_from(&library.path)
        .map_err(|e| failed(e.to_string()))?
        .with_name("gprflow-register")
        .with_telemetry(false)
        .build()
        .map_err(|e| failed(e.to_string()))?;
    *loaded = Some((canonical, env.clone()));
    Ok(env)
}

// ---------------------------------------------------------------------------------------------
// Features and the encoder

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

    fn check(&self, what: &str) -> Result<()> {
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

// ---------------------------------------------------------------------------------------------
// Spatial correlation

/// Parameters of the spatial correlation (SPEC "Spatial correlation").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrelationParams {
    /// Along-track size of a feature column, m (`resolution_m * column_stride`).
    pub column_m: f64,
    /// Largest shift tried either way, m.
    pub max_shift_m: f64,
    /// Smallest shared region, as a fraction of the feature columns, in (0, 1].
    pub min_overlap: f64,
}

impl CorrelationParams {
    fn check(&self) -> Result<()> {
        if !(self.column_m.is_finite() && self.column_m > 0.0) {
            return Err(Error::Param {
                key: "column_m",
                message: format!("must be finite and > 0, got {}", self.column_m),
            });
        }
        crate::check_shift_search(self.max_shift_m, self.min_overlap)
    }

    /// The largest shift tried, in columns, for `cols` feature columns: `floor(max_shift_m /
    /// column_m)`, and no more than leaves `ceil(min_overlap * cols)` columns shared.
    pub fn max_shift_cols(&self, cols: usize) -> usize {
        let min_shared = ((self.min_overlap * cols as f64).ceil() as usize).clamp(1, cols.max(1));
        let by_distance = (self.max_shift_m / self.column_m).floor();
        // `as` saturates: a huge ratio is bounded by the overlap below
        (by_distance as usize).min(cols.saturating_sub(min_shared))
    }
}

/// The correlation vector `v = [tau_1 .. tau_K, m_1 .. m_K]` (SPEC "corr-feat").
#[derive(Debug, Clone, PartialEq)]
pub struct CorrVector {
    /// `2K` values: the per-channel shifts `tau_k` (m), then the peak correlations `m_k`.
    pub values: Vec<f64>,
    /// Largest shift tried either way, columns (the shifts tried are `-T..=T`).
    pub max_shift_cols: usize,
}

impl CorrVector {
    /// Channels, `K`.
    pub fn channels(&self) -> usize {
        self.values.len() / 2
    }

    /// `tau_k`, m: where channel `k` correlates best.
    pub fn tau_m(&self) -> &[f64] {
        &self.values[..self.channels()]
    }

    /// `m_k`: the best correlation of channel `k`.
    pub fn peaks(&self) -> &[f64] {
        &self.values[self.channels()..]
    }

    /// `mean_k m_k`: "do these two share features" (§4.5.2).
    pub fn share_score(&self) -> f64 {
        let peaks = self.peaks();
        if peaks.is_empty() {
            return 0.0;
        }
        peaks.iter().sum::<f64>() / peaks.len() as f64
    }
}

/// The spatial correlation with its work buffers, reused from call to call.
///
/// Per channel, with `R` and `Q` the reference's and the query's `h x w` images, the shared
/// block of a shift `T` is the reference's columns `c + T` and the query's columns `c` for `c`
/// in `[max(0, -T), min(w, w - T))`. Its Pearson correlation needs `Σ AB`, `Σ A`, `Σ A²`,
/// `Σ B`, `Σ B²` over the block. The four single sums are differences of column prefix sums.
/// `Σ AB` is the `T`-th diagonal sum of the column cross-product matrix
/// `D[i][j] = Σ_rows R[row][i] Q[row][j]` (`i - j = T`), computed in `4 x 8` tiles (only those
/// that touch a shift tried) and added into the diagonals tile by tile, never stored whole. Then
/// `r = (Σ AB - Σ A Σ B / N) / sqrt((Σ A² - (Σ A)² / N) (Σ B² - (Σ B)² / N))`, in f64 (f32
/// products are exact in f64; the sums round as in any f64 order).
#[derive(Debug, Clone, Default)]
pub struct Correlator {
    /// One channel of the reference as f64 in panels of [`TILE_I`] columns (see
    /// [`prepare_channel`]).
    reference: Vec<f64>,
    /// One channel of the query as f64 in panels of [`TILE_J`] columns.
    query: Vec<f64>,
    /// Column prefix sums of one channel: reference `Σ`, reference `Σ x²`, query `Σ`, query
    /// `Σ x²`, `w + 1` each.
    prefix: Vec<f64>,
    /// `Σ AB` of one channel per shift tried, in increasing shift.
    products: Vec<f64>,
    /// `r(T)` of one channel for the shifts tried, in increasing shift.
    curve: Vec<f64>,
}

/// [`Correlator::correlate`] with fresh buffers.
///
/// # Errors
/// See [`Correlator::correlate`].
pub fn correlate(reference: &Features, query: &Features, params: &CorrelationParams) -> Result<CorrVector> {
    Correlator::default().correlate(reference, query, params)
}

impl Correlator {
    /// The correlation vector of `query` over `reference` (SPEC "Spatial correlation").
    ///
    /// # Errors
    /// Parameters out of range, features of inconsistent or different shapes, or a feature that
    /// is NaN or infinite.
    pub fn correlate(
        &mut self,
        reference: &Features,
        query: &Features,
        params: &CorrelationParams,
    ) -> Result<CorrVector> {
        params.check()?;
        reference.check("reference")?;
        query.check("query")?;
        if (reference.channels, reference.rows, reference.cols) != (query.channels, query.rows, query.cols) {
            return Err(Error::Shape(format!(
                "reference features {} x {} x {}, query features {} x {} x {}",
                reference.channels, reference.rows, reference.cols, query.channels, query.rows, query.cols
            )));
        }
        let (channels, h, w) = (reference.channels, reference.rows, reference.cols);
        let shape = ChannelShape {
            h,
            w,
            t_max: params.max_shift_cols(w),
        };
        let mut values = vec![0.0; 2 * channels];
        for k in 0..channels {
            self.channel(reference.channel(k), query.channel(k), shape);
            // a NaN or infinite feature makes its channel's sum of squares so (finite f32 values
            // cannot overflow it)
            let (r_squares, q_squares) = (self.prefix[2 * w + 1], self.prefix[4 * w + 3]);
            for (features, what, total) in [(reference, "reference", r_squares), (query, "query", q_squares)] {
                if !total.is_finite() {
                    return Err(non_finite(features, what, k));
                }
            }
            let (tau_cols, peak) = refined_peak(&self.curve, shape.t_max);
            values[k] = tau_cols * params.column_m;
            values[channels + k] = peak;
        }
        Ok(CorrVector {
            values,
            max_shift_cols: shape.t_max,
        })
    }
}

impl Correlator {
    /// `r(T)` of one channel (`r`, `q`: `h x w`, row-major) into `self.curve`, its column
    /// prefix sums left in `self.prefix`. Uses AVX2 and FMA where the CPU has them (fused
    /// multiply-adds: the result may differ from the portable one in the last bit).
    fn channel(&mut self, r: &[f32], q: &[f32], shape: ChannelShape) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA, checked just above.
            unsafe { self.channel_avx2(r, q, shape) };
            return;
        }
        self.channel_with(r, q, shape, |rp, qp, s, out| {
            shifted_products(rp, qp, s, out, |a, b, c| a * b + c)
        });
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn channel_avx2(&mut self, r: &[f32], q: &[f32], shape: ChannelShape) {
        self.channel_with(r, q, shape, |rp, qp, s, out| shifted_products_avx2(rp, qp, s, out));
    }

    /// [`Correlator::channel`] with `products` for [`shifted_products`].
    #[inline(always)]
    fn channel_with(
        &mut self,
        r: &[f32],
        q: &[f32],
        shape: ChannelShape,
        products: impl Fn(&[f64], &[f64], ChannelShape, &mut [f64]),
    ) {
        let w = shape.w;
        self.prefix.clear();
        self.prefix.resize(4 * (w + 1), 0.0);
        let (r_sums, rest) = self.prefix.split_at_mut(w + 1);
        let (r_squares, rest) = rest.split_at_mut(w + 1);
        let (q_sums, q_squares) = rest.split_at_mut(w + 1);
        prepare_channel::<TILE_I, false>(r, shape, &mut self.reference, r_sums, r_squares);
        prepare_channel::<TILE_J, true>(q, shape, &mut self.query, q_sums, q_squares);
        let section = DIAGONALS_PAST_W + 2 * w;
        self.products.clear();
        self.products.resize(TILE_I * section, 0.0);
        products(&self.reference, &self.query, shape, &mut self.products);
        // the shifts tried, -t_max..=t_max: diagonal t is at t + w + TILE_J - 1 - a of section a
        let first = w + TILE_J - 1 - shape.t_max;
        for x in first..first + 2 * shape.t_max + 1 {
            let sum: f64 = (1..TILE_I).map(|a| self.products[a * section + x - a]).sum();
            self.products[x] += sum;
        }
        let tried = &self.products[first..first + 2 * shape.t_max + 1];
        channel_curve(shape, tried, &self.prefix, &mut self.curve);
    }
}

/// Rows, columns and largest shift of one channel's images.
#[derive(Debug, Clone, Copy)]
struct ChannelShape {
    h: usize,
    w: usize,
    t_max: usize,
}

/// The error naming the first NaN or infinite value of channel `k`.
fn non_finite(features: &Features, what: &str, k: usize) -> Error {
    let channel = features.channel(k);
    let i = channel.iter().position(|v| !v.is_finite()).unwrap_or(0);
    Error::Shape(format!(
        "{what} features: channel {k}, row {}, col {} is {}",
        i / features.cols,
        i % features.cols,
        channel.get(i).copied().unwrap_or(f32::NAN)
    ))
}

/// One channel's `h x w` image (row-major) as f64 in panels of `W` columns into `panels`: per
/// panel `p`, per row, the columns `p W .. (p + 1) W` (zeros past the last column; in
/// decreasing order when `REVERSED`), so that a tile's rows are contiguous; and in the same
/// pass its column prefix sums of values and of squares into `sums` and `squares` (`w + 1`
/// each, entry `c` summing the columns `< c`).
#[inline(always)]
fn prepare_channel<const W: usize, const REVERSED: bool>(
    image: &[f32],
    shape: ChannelShape,
    panels: &mut Vec<f64>,
    sums: &mut [f64],
    squares: &mut [f64],
) {
    let ChannelShape { h, w, .. } = shape;
    panels.clear();
    panels.resize(w.div_ceil(W) * h * W, 0.0);
    let (sums, squares) = (&mut sums[1..], &mut squares[1..]);
    for (row, src) in image.chunks_exact(w).enumerate() {
        let full = src.chunks_exact(W);
        let rest = full.remainder();
        let (sum_full, square_full) = (sums.chunks_exact_mut(W), squares.chunks_exact_mut(W));
        for (p, (chunk, (sum, square))) in full.zip(sum_full.zip(square_full)).enumerate() {
            let dst = panels.get_mut((p * h + row) * W..(p * h + row + 1) * W);
            // fixed-size arrays: the loop below unrolls and vectorises
            let (Ok(chunk), Ok(sum), Ok(square), Some(Ok(dst))) = (
                <&[f32; W]>::try_from(chunk),
                <&mut [f64; W]>::try_from(sum),
                <&mut [f64; W]>::try_from(square),
                dst.map(<&mut [f64; W]>::try_from),
            ) else {
                continue;
            };
            let x: [f64; W] = std::array::from_fn(|o| f64::from(chunk[o]));
            for o in 0..W {
                sum[o] += x[o];
                square[o] += x[o] * x[o];
                dst[if REVERSED { W - 1 - o } else { o }] = x[o];
            }
        }
        if !rest.is_empty() {
            let (p, c0) = (w / W, w - rest.len());
            let Some(dst) = panels.get_mut((p * h + row) * W..(p * h + row + 1) * W) else {
                continue;
            };
            for (o, &v) in rest.iter().enumerate() {
                let x = f64::from(v);
                dst[if REVERSED { W - 1 - o } else { o }] = x;
                sums[c0 + o] += x;
                squares[c0 + o] += x * x;
            }
        }
    }
    for c in 1..w {
        sums[c] += sums[c - 1];
        squares[c] += squares[c - 1];
    }
}

/// `r(T)` for `T` in `-t_max..=t_max` of one channel into `curve`, from `products` (`Σ AB` per
/// shift) and `prefix` (reference sums, reference squares, query sums, query squares, as
/// [`prepare_channel`] leaves them).
fn channel_curve(shape: ChannelShape, products: &[f64], prefix: &[f64], curve: &mut Vec<f64>) {
    let ChannelShape { h, w, t_max } = shape;
    let (pr, rest) = prefix.split_at(w + 1);
    let (prr, rest) = rest.split_at(w + 1);
    let (pq, pqq) = rest.split_at(w + 1);
    curve.clear();
    let t_max = t_max as isize;
    for (t, &sab) in (-t_max..=t_max).zip(products) {
        // query columns [q0, q1) over reference columns [q0 + t, q1 + t)
        let q0 = (-t).max(0) as usize;
        let q1 = (w as isize - t.max(0)) as usize;
        let (r0, r1) = ((q0 as isize + t) as usize, (q1 as isize + t) as usize);
        let count = (h * (q1 - q0)) as f64;
        let (sa, saa) = (pr[r1] - pr[r0], prr[r1] - prr[r0]);
        let (sb, sbb) = (pq[q1] - pq[q0], pqq[q1] - pqq[q0]);
        let var_a = saa - sa * sa / count;
        let var_b = sbb - sb * sb / count;
        let flat = |var: f64, sq: f64| var <= FLAT_VARIANCE_FRACTION * sq;
        let corr = if flat(var_a, saa) || flat(var_b, sbb) {
            0.0
        } else {
            (sab - sa * sb / count) / (var_a.sqrt() * var_b.sqrt())
        };
        curve.push(corr);
    }
}

/// Reference columns per tile of `D` (and per reference panel).
const TILE_I: usize = 4;

/// Query columns per tile of `D` (and per query panel).
const TILE_J: usize = 8;

/// [`shifted_products`] with fused multiply-adds, compiled on its own (inlined into the rest,
/// the tile loop lost its vector registers).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline(never)]
fn shifted_products_avx2(r_panels: &[f64], q_panels: &[f64], shape: ChannelShape, out: &mut [f64]) {
    shifted_products(r_panels, q_panels, shape, out, f64::mul_add);
}

/// A section of [`shifted_products`]' `out` holds `2 w` and this many diagonals.
const DIAGONALS_PAST_W: usize = TILE_I + TILE_J - 1;

/// `Σ AB` of one channel for every shift added into `out`: the diagonal sums of
/// `D[i][j] = Σ_rows r[row][i] q[row][j]`, split by `a = i mod TILE_I` into `TILE_I` sections
/// of `2 w + DIAGONALS_PAST_W` (section `a` holds diagonal `i - j` at `i - j + w + TILE_J - 1 -
/// a`; apart, a tile's rows never store into overlapping ranges back to back), from the
/// channel's panels ([`prepare_channel`]: the reference in panels of [`TILE_I`]
/// columns, the query in panels of [`TILE_J`] columns in decreasing order, so that a tile's
/// row `a` holds the diagonals `ib - jb - 7 + a ..= ib - jb + a`, in increasing order); only
/// the tiles that touch a shift in `-t_max..=t_max`; `madd(a, b, c) = a b + c`.
#[inline(always)]
fn shifted_products(
    r_panels: &[f64],
    q_panels: &[f64],
    shape: ChannelShape,
    out: &mut [f64],
    madd: impl Fn(f64, f64, f64) -> f64,
) {
    let ChannelShape { h, w, t_max } = shape;
    let t_max = t_max as isize;
    let section_len = 2 * w + DIAGONALS_PAST_W;
    for (pi, r_panel) in r_panels.chunks_exact(h * TILE_I).enumerate() {
        let ib = pi * TILE_I;
        for (pj, q_panel) in q_panels.chunks_exact(h * TILE_J).enumerate() {
            let jb = pj * TILE_J;
            // the tile's shifts i - j span [ib - jb - 7, ib - jb + 3]
            let (lo, hi) = (
                ib as isize - (jb + TILE_J - 1) as isize,
                (ib + TILE_I - 1) as isize - jb as isize,
            );
            if hi < -t_max || lo > t_max {
                continue;
            }
            let mut acc = [[0.0f64; TILE_J]; TILE_I];
            for (ri, qj) in r_panel.chunks_exact(TILE_I).zip(q_panel.chunks_exact(TILE_J)) {
                for (acc_a, &ra) in acc.iter_mut().zip(ri) {
                    for (s, &qb) in acc_a.iter_mut().zip(qj) {
                        *s = madd(ra, qb, *s);
                    }
                }
            }
            // row a, lane l: i = ib + a, j = jb + 7 - l, at ib - jb + l + w of section a
            let base = ib + w - jb;
            for (section, acc_a) in out.chunks_exact_mut(section_len).zip(&acc) {
                let Some(dst) = section.get_mut(base..base + TILE_J) else {
                    continue;
                };
                for (d, &s) in dst.iter_mut().zip(acc_a) {
                    *d += s;
                }
            }
        }
    }
}

/// The argmax of `curve` (shifts `-t_max..=t_max`; the smallest shift on ties) refined by the
/// parabola through it and its neighbours: `(T* + delta, r(T*))`, in columns.
fn refined_peak(curve: &[f64], t_max: usize) -> (f64, f64) {
    let mut best = 0;
    for (i, &r) in curve.iter().enumerate() {
        if r > curve[best] {
            best = i;
        }
    }
    let Some(&peak) = curve.get(best) else {
        return (0.0, 0.0);
    };
    let mut delta = 0.0;
    if best > 0 && best + 1 < curve.len() {
        let (a, b, c) = (curve[best - 1], peak, curve[best + 1]);
        let denom = a - 2.0 * b + c;
        if denom < 0.0 {
            delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
        }
    }
    (best as f64 - t_max as f64 + delta, peak)
}

// ---------------------------------------------------------------------------------------------
// The head

/// Which head a file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadKind {
    /// One layer, no activation.
    Linear,
    /// Hidden layers with ReLU, then a layer with one output and no activation.
    Nonlinear,
}

/// Activation of a head layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// Identity.
    None,
    /// `max(0, x)`.
    Relu,
}

/// One dense layer: `u = act(W u + b)`.
#[derive(Debug, Clone, PartialEq)]
pub struct HeadLayer {
    /// `outputs x inputs`, row-major.
    weights: Vec<f64>,
    bias: Vec<f64>,
    inputs: usize,
    activation: Activation,
}

impl HeadLayer {
    /// Outputs of the layer.
    pub fn outputs(&self) -> usize {
        self.bias.len()
    }

    /// Inputs of the layer.
    pub fn inputs(&self) -> usize {
        self.inputs
    }

    /// The layer's activation.
    pub fn activation(&self) -> Activation {
        self.activation
    }
}

/// The channel agreement check (SPEC "Do these two share features"): a pair is registered only
/// when at least `min_fraction` of the channels put their own shift `tau_k` within
/// `tolerance_m` of the head's shift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Agreement {
    /// Largest `|tau_k - shift|` of an agreeing channel, m.
    pub tolerance_m: f64,
    /// Smallest fraction of agreeing channels, in `[0, 1]`.
    pub min_fraction: f64,
}

impl Agreement {
    fn parse(rd: &HeadReader<'_>, value: &Value) -> Result<Agreement> {
        let obj = rd.object(value, "agreement")?;
        rd.only_keys(obj, "agreement", &["tolerance_m", "min_fraction", "rule"])?;
        let tolerance_m = rd.number(rd.field(obj, "agreement", "tolerance_m")?, "agreement.tolerance_m")?;
        if tolerance_m <= 0.0 {
            return Err(rd.error("agreement.tolerance_m", format!("{tolerance_m}, expected > 0")));
        }
        let min_fraction = rd.number(rd.field(obj, "agreement", "min_fraction")?, "agreement.min_fraction")?;
        if !(0.0..=1.0).contains(&min_fraction) {
            return Err(rd.error("agreement.min_fraction", format!("{min_fraction}, expected in [0, 1]")));
        }
        Ok(Agreement {
            tolerance_m,
            min_fraction,
        })
    }

    /// The fraction of the channels of `corr` whose `tau_k` lies within `tolerance_m` of
    /// `shift_m`.
    pub fn fraction(&self, corr: &CorrVector, shift_m: f64) -> f64 {
        let tau = corr.tau_m();
        if tau.is_empty() {
            return 0.0;
        }
        let agreeing = tau.iter().filter(|&&t| (t - shift_m).abs() <= self.tolerance_m).count();
        agreeing as f64 / tau.len() as f64
    }
}

/// The regression head and the model's constants (SPEC "Head"), as read from its JSON file.
#[derive(Debug, Clone, PartialEq)]
pub struct Head {
    /// Linear or nonlinear.
    pub kind: HeadKind,
    /// Encoder channels, `K`.
    pub channels: usize,
    /// The encoder's stride along columns.
    pub column_stride: usize,
    /// Largest shift tried either way, m.
    pub max_shift_m: f64,
    /// Smallest shared region, as a fraction of the feature columns.
    pub min_overlap: f64,
    /// Pairs whose `mean_k m_k` is below this share no features.
    pub share_threshold: f64,
    /// The channel agreement check, when the head has one.
    pub agreement: Option<Agreement>,
    /// Robust standard deviation of the head on held-out pairs, m.
    pub sigma_m: f64,
    /// Mean target of the training pairs (the zeroth-order model), m.
    pub zeroth_m: f64,
    /// CRC-32 of the encoder file the head was fitted on, when the file names one: a head
    /// fits only its own encoder's features.
    pub encoder_crc32: Option<u32>,
    /// The file's free-form `training` record (`null` when absent).
    pub training: Value,
    mean: Vec<f64>,
    std: Vec<f64>,
    layers: Vec<HeadLayer>,
}

/// Reads the fields of a head file, each error naming the file and the field.
struct HeadReader<'a> {
    file: &'a Path,
}

impl HeadReader<'_> {
    fn error(&self, field: &str, message: impl Into<String>) -> Error {
        Error::Head {
            file: self.file.to_path_buf(),
            field: field.to_string(),
            message: message.into(),
        }
    }

    fn object<'v>(&self, value: &'v Value, field: &str) -> Result<&'v Map<String, Value>> {
        value
            .as_object()
            .ok_or_else(|| self.error(field, format!("expected an object, got {}", kind_of(value))))
    }

    fn field<'v>(&self, obj: &'v Map<String, Value>, prefix: &str, key: &str) -> Result<&'v Value> {
        obj.get(key).ok_or_else(|| self.error(&join(prefix, key), "missing"))
    }

    fn only_keys(&self, obj: &Map<String, Value>, prefix: &str, known: &[&str]) -> Result<()> {
        match obj.keys().find(|k| !known.contains(&k.as_str())) {
            Some(k) => Err(self.error(&join(prefix, k), format!("unknown field (known: {})", known.join(", ")))),
            None => Ok(()),
        }
    }

    fn string<'v>(&self, value: &'v Value, field: &str) -> Result<&'v str> {
        value
            .as_str()
            .ok_or_else(|| self.error(field, format!("expected a string, got {}", kind_of(value))))
    }

    fn number(&self, value: &Value, field: &str) -> Result<f64> {
        match value.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(self.error(field, format!("expected a finite number, got {}", kind_of(value)))),
        }
    }

    fn count(&self, value: &Value, field: &str) -> Result<usize> {
        match value.as_u64().and_then(|n| usize::try_from(n).ok()) {
            Some(n) if n > 0 => Ok(n),
            _ => Err(self.error(field, format!("expected an integer >= 1, got {value}"))),
        }
    }

    fn numbers(&self, value: &Value, field: &str, len: usize) -> Result<Vec<f64>> {
        let items = value
            .as_array()
            .ok_or_else(|| self.error(field, format!("expected an array, got {}", kind_of(value))))?;
        if items.len() != len {
            return Err(self.error(field, format!("{} values, expected {len}", items.len())));
        }
        items
            .iter()
            .enumerate()
            .map(|(i, v)| self.number(v, &format!("{field}[{i}]")))
            .collect()
    }
}

fn join(prefix: &str, key: &str) -> String {
    if prefix.is_empty() {
        key.to_string()
    } else {
        format!("{prefix}.{key}")
    }
}

fn kind_of(value: &Value) -> String {
    match value {
        Value::Null => "null".into(),
        Value::Bool(b) => format!("{b}"),
        Value::Number(n) => format!("{n}"),
        Value::String(s) => format!("{s:?}"),
        Value::Array(a) => format!("an array of {}", a.len()),
        Value::Object(_) => "an object".into(),
    }
}

const HEAD_KEYS: &[&str] = &[
    "format",
    "version",
    "kind",
    "channels",
    "column_stride",
    "max_shift_m",
    "min_overlap",
    "normalise",
    "layers",
    "share_threshold",
    "agreement",
    "sigma_m",
    "zeroth_m",
    "encoder_crc32",
    "training",
];

impl Head {
    /// Reads and checks a head file.
    ///
    /// # Errors
    /// [`Error::Io`] when the file cannot be read, [`Error::Head`] naming the field that is
    /// missing, malformed or of the wrong shape.
    pub fn from_json(path: &Path) -> Result<Head> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Head::parse(&text, path)
    }

    /// Parses and checks the text of a head file; `path` names it in errors.
    ///
    /// # Errors
    /// [`Error::Head`] naming the field that is missing, malformed or of the wrong shape.
    pub fn parse(text: &str, path: &Path) -> Result<Head> {
        let rd = HeadReader { file: path };
        let root: Value = serde_json::from_str(text).map_err(|e| rd.error("(file)", format!("not JSON: {e}")))?;
        let obj = rd.object(&root, "(file)")?;
        rd.only_keys(obj, "", HEAD_KEYS)?;
        let format = rd.string(rd.field(obj, "", "format")?, "format")?;
        if format != HEAD_FORMAT {
            return Err(rd.error("format", format!("{format:?}, expected {HEAD_FORMAT:?}")));
        }
        let version = rd.field(obj, "", "version")?;
        if version.as_u64() != Some(HEAD_VERSION) {
            return Err(rd.error("version", format!("{version}, this reader knows {HEAD_VERSION}")));
        }
        let kind = match rd.string(rd.field(obj, "", "kind")?, "kind")? {
            "linear" => HeadKind::Linear,
            "nonlinear" => HeadKind::Nonlinear,
            other => return Err(rd.error("kind", format!("{other:?}, expected \"linear\" or \"nonlinear\""))),
        };
        let channels = rd.count(rd.field(obj, "", "channels")?, "channels")?;
        let column_stride = rd.count(rd.field(obj, "", "column_stride")?, "column_stride")?;
        let max_shift_m = rd.number(rd.field(obj, "", "max_shift_m")?, "max_shift_m")?;
        if max_shift_m < 0.0 {
            return Err(rd.error("max_shift_m", format!("{max_shift_m}, expected >= 0")));
        }
        let min_overlap = rd.number(rd.field(obj, "", "min_overlap")?, "min_overlap")?;
        if !(min_overlap > 0.0 && min_overlap <= 1.0) {
            return Err(rd.error("min_overlap", format!("{min_overlap}, expected in (0, 1]")));
        }
        let inputs = 2 * channels;
        let normalise = rd.object(rd.field(obj, "", "normalise")?, "normalise")?;
        rd.only_keys(normalise, "normalise", &["mean", "std"])?;
        let mean = rd.numbers(rd.field(normalise, "normalise", "mean")?, "normalise.mean", inputs)?;
        let std = rd.numbers(rd.field(normalise, "normalise", "std")?, "normalise.std", inputs)?;
        if let Some(i) = std.iter().position(|&s| s <= 0.0) {
            return Err(rd.error(&format!("normalise.std[{i}]"), format!("{}, expected > 0", std[i])));
        }
        let layers = Head::parse_layers(&rd, rd.field(obj, "", "layers")?, kind, inputs)?;
        let share_threshold = rd.number(rd.field(obj, "", "share_threshold")?, "share_threshold")?;
        let agreement = match obj.get("agreement") {
            None | Some(Value::Null) => None,
            Some(value) => Some(Agreement::parse(&rd, value)?),
        };
        let sigma_m = rd.number(rd.field(obj, "", "sigma_m")?, "sigma_m")?;
        if sigma_m <= 0.0 {
            return Err(rd.error("sigma_m", format!("{sigma_m}, expected > 0")));
        }
        let zeroth_m = rd.number(rd.field(obj, "", "zeroth_m")?, "zeroth_m")?;
        let encoder_crc32 = match obj.get("encoder_crc32") {
            None | Some(Value::Null) => None,
            Some(value) => {
                let text = rd.string(value, "encoder_crc32")?;
                let parsed = (text.len() == 8).then(|| u32::from_str_radix(text, 16).ok()).flatten();
                Some(parsed.ok_or_else(|| rd.error("encoder_crc32", format!("{text:?}, expected 8 hex digits")))?)
            }
        };
        Ok(Head {
            kind,
            channels,
            column_stride,
            max_shift_m,
            min_overlap,
            share_threshold,
            agreement,
            sigma_m,
            zeroth_m,
            encoder_crc32,
            training: obj.get("training").cloned().unwrap_or(Value::Null),
            mean,
            std,
            layers,
        })
    }

    fn parse_layers(rd: &HeadReader<'_>, value: &Value, kind: HeadKind, inputs: usize) -> Result<Vec<HeadLayer>> {
        let items = value
            .as_array()
            .ok_or_else(|| rd.error("layers", format!("expected an array, got {}", kind_of(value))))?;
        match (kind, items.len()) {
            (_, 0) => return Err(rd.error("layers", "empty")),
            (HeadKind::Linear, n) if n != 1 => {
                return Err(rd.error("layers", format!("{n} layers, a linear head has 1")));
            }
            (HeadKind::Nonlinear, 1) => {
                return Err(rd.error("layers", "1 layer, a nonlinear head has hidden layers"));
            }
            _ => {}
        }
        let mut layers = Vec::with_capacity(items.len());
        let mut width = inputs;
        for (i, item) in items.iter().enumerate() {
            let field = format!("layers[{i}]");
            let obj = rd.object(item, &field)?;
            rd.only_keys(obj, &field, &["weights", "bias", "activation"])?;
            let last = i + 1 == items.len();
            let activation = match rd.string(rd.field(obj, &field, "activation")?, &join(&field, "activation"))? {
                "none" => Activation::None,
                "relu" => Activation::Relu,
                other => {
                    return Err(rd.error(
                        &join(&field, "activation"),
                        format!("{other:?}, expected \"none\" or \"relu\""),
                    ));
                }
            };
            let expected = if last { Activation::None } else { Activation::Relu };
            if activation != expected {
                return Err(rd.error(
                    &join(&field, "activation"),
                    format!(
                        "{activation:?}, expected {expected:?} ({})",
                        if last { "the output layer" } else { "a hidden layer" }
                    ),
                ));
            }
            let weights_field = join(&field, "weights");
            let rows = rd.field(obj, &field, "weights")?;
            let rows = rows.as_array().ok_or_else(|| {
                rd.error(
                    &weights_field,
                    format!("expected an array of rows, got {}", kind_of(rows)),
                )
            })?;
            let bias_value = rd.field(obj, &field, "bias")?;
            let outputs = if last {
                1
            } else {
                bias_value.as_array().map_or(0, Vec::len)
            };
            if outputs == 0 {
                return Err(rd.error(&join(&field, "bias"), "expected a non-empty array"));
            }
            if rows.len() != outputs {
                return Err(rd.error(&weights_field, format!("{} rows, expected {outputs}", rows.len())));
            }
            let bias = rd.numbers(bias_value, &join(&field, "bias"), outputs)?;
            let mut weights = Vec::with_capacity(outputs * width);
            for (r, row) in rows.iter().enumerate() {
                weights.extend(rd.numbers(row, &format!("{weights_field}[{r}]"), width)?);
            }
            layers.push(HeadLayer {
                weights,
                bias,
                inputs: width,
                activation,
            });
            width = outputs;
        }
        Ok(layers)
    }

    /// The layers, input first.
    pub fn layers(&self) -> &[HeadLayer] {
        &self.layers
    }

    /// Length of the correlation vector the head takes, `2K`.
    pub fn inputs(&self) -> usize {
        self.mean.len()
    }

    /// The predicted shift `z`, m, of the correlation vector `v` (`2K` values; extra values are
    /// ignored, missing ones count as the training mean).
    pub fn predict(&self, v: &[f64]) -> f64 {
        let widest = self.layers.iter().map(HeadLayer::outputs).max().unwrap_or(1);
        let mut buf = vec![0.0; self.inputs() + 2 * widest];
        let (u, rest) = buf.split_at_mut(self.inputs());
        for (i, x) in u.iter_mut().enumerate() {
            *x = (v.get(i).copied().unwrap_or(self.mean[i]) - self.mean[i]) / self.std[i];
        }
        let (mut a, mut b) = rest.split_at_mut(widest);
        let mut input: &[f64] = u;
        for layer in &self.layers {
            let out = &mut a[..layer.outputs()];
            for (o, y) in out.iter_mut().enumerate() {
                let row = &layer.weights[o * layer.inputs..(o + 1) * layer.inputs];
                let z = layer.bias[o] + row.iter().zip(input).map(|(w, x)| w * x).sum::<f64>();
                *y = match layer.activation {
                    Activation::None => z,
                    Activation::Relu => z.max(0.0),
                };
            }
            std::mem::swap(&mut a, &mut b);
            input = &b[..layer.outputs()];
        }
        input.first().copied().unwrap_or(self.zeroth_m)
    }

    /// The correlation parameters for submaps of `resolution_m` per column.
    pub fn correlation_params(&self, resolution_m: f64) -> CorrelationParams {
        CorrelationParams {
            column_m: resolution_m * self.column_stride as f64,
            max_shift_m: self.max_shift_m,
            min_overlap: self.min_overlap,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The model

/// A registration by the learned model.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedMatch {
    /// Along-body-x position of the query's ground-order column 0 over the reference, m.
    pub shift_m: f64,
    /// `mean_k m_k`, in -1..=1: how much the two share features.
    pub share_score: f64,
    /// The fraction of channels agreeing with `shift_m` (1 when the head has no agreement
    /// check).
    pub agreement: f64,
    /// `sigma_m^2`, m².
    pub variance_m2: f64,
    /// The correlation vector the head took, `[tau_1 .. tau_K, m_1 .. m_K]`.
    pub corr: Vec<f64>,
}

/// Encoder, head and correlation buffers: the learned registration model.
#[derive(Debug)]
pub struct Model {
    /// The ONNX encoder.
    pub encoder: Encoder,
    /// The head and the model's constants.
    pub head: Head,
    correlator: Correlator,
}

impl Model {
    /// Loads the encoder (`onnx`) and the head (`head_json`); `ort_library` as in
    /// [`Encoder::load`].
    ///
    /// # Errors
    /// See [`Encoder::load`] and [`Head::from_json`]; [`Error::Head`] (`encoder_crc32`) when
    /// the head names another encoder file than `onnx`.
    pub fn load(onnx: &Path, head_json: &Path, ort_library: Option<&Path>) -> Result<Model> {
        let head = Head::from_json(head_json)?;
        if let Some(expected) = head.encoder_crc32 {
            let bytes = std::fs::read(onnx).map_err(|source| Error::Io {
                path: onnx.to_path_buf(),
                source,
            })?;
            let found = crc32fast::hash(&bytes);
            if found != expected {
                return Err(Error::Head {
                    file: head_json.to_path_buf(),
                    field: "encoder_crc32".into(),
                    message: format!(
                        "{expected:08x}, but {} has {found:08x}: the head was fitted on another encoder (give the model's encoder and head together)",
                        onnx.display()
                    ),
                });
            }
        }
        let encoder = Encoder::load(onnx, ort_library)?;
        Ok(Model {
            encoder,
            head,
            correlator: Correlator::default(),
        })
    }

    /// The features of `submap` (ground order, not standardised), checked against the head:
    /// `K` channels and `ceil(cols / column_stride)` columns.
    ///
    /// # Errors
    /// See [`Encoder::encode_into`]; [`Error::Onnx`] when the features do not fit the head.
    pub fn encode(&mut self, submap: &SubmapView<'_>) -> Result<Features> {
        let mut features = Features::default();
        self.encode_into(submap, &mut features)?;
        Ok(features)
    }

    /// [`Model::encode`] into `features`, whose buffer is reused.
    ///
    /// # Errors
    /// See [`Model::encode`].
    pub fn encode_into(&mut self, submap: &SubmapView<'_>, features: &mut Features) -> Result<()> {
        self.encoder.encode_into(submap, features)?;
        let cols = submap.cols.div_ceil(self.head.column_stride);
        if features.channels != self.head.channels || features.cols != cols {
            return Err(Error::Onnx {
                model: self.encoder.model_path.clone(),
                message: format!(
                    "features {} x {} x {} for a {} x {} submap, the head expects {} channels and {cols} columns (stride {})",
                    features.channels,
                    features.rows,
                    features.cols,
                    submap.rows,
                    submap.cols,
                    self.head.channels,
                    self.head.column_stride
                ),
            });
        }
        Ok(())
    }

    /// The correlation vector of `query` over `reference` (features of submaps with
    /// `resolution_m` per column) with the head's parameters.
    ///
    /// # Errors
    /// See [`Correlator::correlate`]; features with other than the head's channel count.
    pub fn correlate(&mut self, reference: &Features, query: &Features, resolution_m: f64) -> Result<CorrVector> {
        if reference.channels != self.head.channels {
            return Err(Error::Shape(format!(
                "reference features have {} channels, the head {}",
                reference.channels, self.head.channels
            )));
        }
        self.correlator
            .correlate(reference, query, &self.head.correlation_params(resolution_m))
    }

    /// Registers `query` on `reference`: `None` when they share no features
    /// (`mean_k m_k < share_threshold`, or, where the head has an [`Agreement`] check, too few
    /// channels agree with the head's shift), else the head's shift and `sigma_m^2`.
    ///
    /// # Errors
    /// See [`Model::correlate`].
    pub fn register(
        &mut self,
        reference: &Features,
        query: &Features,
        resolution_m: f64,
    ) -> Result<Option<LearnedMatch>> {
        let (found, refusal) = self.assess(reference, query, resolution_m)?;
        Ok(refusal.is_none().then_some(found))
    }

    /// What [`Model::register`] decides, with its numbers either way: the match (shift, share
    /// score, agreement) and why it was refused, if it was.
    ///
    /// # Errors
    /// See [`Model::correlate`].
    pub fn assess(
        &mut self,
        reference: &Features,
        query: &Features,
        resolution_m: f64,
    ) -> Result<(LearnedMatch, Option<Refusal>)> {
        let corr = self.correlate(reference, query, resolution_m)?;
        Ok(self.decide(corr))
    }

    /// [`Model::assess`] of the query seen several ways (`queries`: its features at each
    /// travel-time stretch the stage tries, [`crate::stretch`]) over `reference`: the one whose
    /// share score (mean channel peak) is highest decides, refused or not. Returns the decision
    /// and the index of that query.
    ///
    /// # Errors
    /// See [`Model::correlate`]; [`Error::Shape`] when `queries` is empty.
    pub fn assess_best(
        &mut self,
        reference: &Features,
        queries: &[Features],
        resolution_m: f64,
    ) -> Result<(LearnedMatch, Option<Refusal>, usize)> {
        let mut best: Option<(CorrVector, usize)> = None;
        for (i, query) in queries.iter().enumerate() {
            let corr = self.correlate(reference, query, resolution_m)?;
            if best.as_ref().is_none_or(|(b, _)| corr.share_score() > b.share_score()) {
                best = Some((corr, i));
            }
        }
        let Some((corr, i)) = best else {
            return Err(Error::Shape("no query features to register".into()));
        };
        let (found, refusal) = self.decide(corr);
        Ok((found, refusal, i))
    }

    /// The head's shift and the two checks on one correlation vector.
    fn decide(&self, corr: CorrVector) -> (LearnedMatch, Option<Refusal>) {
        let share_score = corr.share_score();
        let shift_m = self.head.predict(&corr.values);
        let (agreement, agrees) = match self.head.agreement {
            Some(check) => {
                let fraction = check.fraction(&corr, shift_m);
                (fraction, fraction >= check.min_fraction)
            }
            None => (1.0, true),
        };
        let refusal = if share_score < self.head.share_threshold {
            Some(Refusal::NoSharedFeatures)
        } else if !agrees {
            Some(Refusal::ChannelsDisagree)
        } else {
            None
        };
        let found = LearnedMatch {
            shift_m,
            share_score,
            agreement,
            variance_m2: self.head.sigma_m * self.head.sigma_m,
            corr: corr.values,
        };
        (found, refusal)
    }
}

/// Why the learned model refused a pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// `mean_k m_k < share_threshold`.
    NoSharedFeatures,
    /// Fewer than the agreement check's `min_fraction` of the channels agree with the shift.
    ChannelsDisagree,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Agreement of the fast correlation with the direct one.
    const EXACT: f64 = 1e-9;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect()
    }

    fn features(k: usize, h: usize, w: usize, seed: u64) -> Features {
        Features {
            channels: k,
            rows: h,
            cols: w,
            data: random(k * h * w, seed),
        }
    }

    /// Pearson correlation of the shared block, two passes, straight from the definition.
    fn direct_r(r: &[f32], q: &[f32], h: usize, w: usize, t: i64) -> f64 {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for row in 0..h {
            for c in 0..w as i64 {
                let rc = c + t;
                if (0..w as i64).contains(&rc) {
                    a.push(f64::from(r[row * w + rc as usize]));
                    b.push(f64::from(q[row * w + c as usize]));
                }
            }
        }
        let n = a.len() as f64;
        let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
        let ab: f64 = a.iter().zip(&b).map(|(x, y)| (x - ma) * (y - mb)).sum();
        let aa: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
        let bb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
        if aa == 0.0 || bb == 0.0 {
            0.0
        } else {
            ab / (aa.sqrt() * bb.sqrt())
        }
    }

    /// The correlation vector straight from SPEC.
    fn direct(reference: &Features, query: &Features, p: &CorrelationParams) -> Vec<f64> {
        let (k, h, w) = (reference.channels, reference.rows, reference.cols);
        let t_max = (p.max_shift_m / p.column_m).floor() as i64;
        let min_shared = (p.min_overlap * w as f64).ceil() as i64;
        let shifts: Vec<i64> = (-t_max..=t_max).filter(|t| w as i64 - t.abs() >= min_shared).collect();
        let mut v = vec![0.0; 2 * k];
        for ch in 0..k {
            let curve: Vec<f64> = shifts
                .iter()
                .map(|&t| direct_r(reference.channel(ch), query.channel(ch), h, w, t))
                .collect();
            let mut best = 0;
            for i in 0..curve.len() {
                if curve[i] > curve[best] {
                    best = i;
                }
            }
            let mut delta = 0.0;
            if best > 0 && best + 1 < curve.len() {
                let (a, b, c) = (curve[best - 1], curve[best], curve[best + 1]);
                if a - 2.0 * b + c < 0.0 {
                    delta = (0.5 * (a - c) / (a - 2.0 * b + c)).clamp(-0.5, 0.5);
                }
            }
            v[ch] = (shifts[best] as f64 + delta) * p.column_m;
            v[k + ch] = curve[best];
        }
        v
    }

    const PARAMS: CorrelationParams = CorrelationParams {
        column_m: 0.06,
        max_shift_m: 1.5,
        min_overlap: 0.5,
    };

    #[test]
    fn fast_correlation_matches_the_direct_one_on_random_features() {
        let mut corr = Correlator::default();
        for (seed, (k, h, w)) in [(3, 7, 11), (2, 1, 1), (4, 13, 50), (1, 5, 8), (2, 9, 33)]
            .into_iter()
            .enumerate()
        {
            for params in [
                PARAMS,
                CorrelationParams {
                    max_shift_m: 0.2,
                    ..PARAMS
                },
                CorrelationParams {
                    min_overlap: 1.0,
                    ..PARAMS
                },
                CorrelationParams {
                    min_overlap: 0.1,
                    max_shift_m: 100.0,
                    ..PARAMS
                },
            ] {
                let r = features(k, h, w, 2 * seed as u64 + 1);
                let mut q = features(k, h, w, 2 * seed as u64 + 2);
                // a correlated query: the reference moved by 3 columns plus noise
                for ch in 0..k {
                    for row in 0..h {
                        for c in 0..w.saturating_sub(3) {
                            let i = (ch * h + row) * w + c;
                            q.data[i] = r.data[(ch * h + row) * w + c + 3] + 0.3 * q.data[i];
                        }
                    }
                }
                let fast = corr.correlate(&r, &q, &params).expect("valid");
                let slow = direct(&r, &q, &params);
                for (i, (a, b)) in fast.values.iter().zip(&slow).enumerate() {
                    assert!((a - b).abs() <= EXACT, "{k}x{h}x{w} {params:?}: v[{i}] {a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn the_portable_arithmetic_matches_the_dispatched_one() {
        let (h, w) = (9, 37);
        let (r, q) = (features(1, h, w, 11), features(1, h, w, 12));
        let shape = ChannelShape { h, w, t_max: 17 };
        let mut corr = Correlator::default();
        corr.channel(&r.data, &q.data, shape);
        let dispatched = corr.curve.clone();
        corr.channel_with(&r.data, &q.data, shape, |rp, qp, s, out| {
            shifted_products(rp, qp, s, out, |a, b, c| a * b + c)
        });
        assert_eq!(dispatched.len(), 2 * 17 + 1);
        for (t, (a, b)) in dispatched.iter().zip(&corr.curve).enumerate() {
            assert!((a - b).abs() <= 1e-12, "shift {}: {a} vs {b}", t as i64 - 17);
        }
    }

    #[test]
    fn a_shifted_feature_image_peaks_at_its_shift() {
        let (k, h, w) = (2, 10, 40);
        let wide = features(k, h, w + 10, 7);
        let crop = |c0: usize| Features {
            channels: k,
            rows: h,
            cols: w,
            data: (0..k * h)
                .flat_map(|kr| wide.data[kr * (w + 10) + c0..kr * (w + 10) + c0 + w].to_vec())
                .collect(),
        };
        // query column c is the wide image's column c + 6, the reference's column c + 4
        let (reference, query) = (crop(2), crop(6));
        let v = correlate(&reference, &query, &PARAMS).expect("valid");
        for ch in 0..k {
            // the parabola through noise-level neighbours moves it a little
            assert!(
                (v.tau_m()[ch] - 4.0 * PARAMS.column_m).abs() < 0.1 * PARAMS.column_m,
                "{:?}",
                v.tau_m()
            );
            assert!((v.peaks()[ch] - 1.0).abs() < 1e-9);
        }
        assert!((v.share_score() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn flat_channels_correlate_as_zero_and_bad_features_are_refused() {
        let mut a = features(2, 4, 10, 1);
        let mut b = features(2, 4, 10, 2);
        a.data[..40].fill(0.0);
        b.data[..40].fill(2.5);
        let v = correlate(&a, &b, &PARAMS).expect("valid");
        assert_eq!(v.peaks()[0], 0.0);
        assert_eq!(v.tau_m()[0], -(PARAMS.max_shift_cols(10) as f64) * PARAMS.column_m);
        b.data[45] = f32::NAN;
        let e = correlate(&a, &b, &PARAMS).expect_err("NaN");
        assert!(
            e.to_string().contains("query features: channel 1, row 0, col 5 is NaN"),
            "{e}"
        );
        let e = correlate(&a, &features(2, 4, 9, 3), &PARAMS).expect_err("shape");
        assert!(e.to_string().contains("4 x 9"), "{e}");
        let e = correlate(
            &a,
            &a,
            &CorrelationParams {
                column_m: 0.0,
                ..PARAMS
            },
        )
        .expect_err("column");
        assert!(e.to_string().starts_with("column_m:"), "{e}");
    }

    fn head_json(kind: &str, layers: &str) -> String {
        format!(
            r#"{{ "format": "gprflow-register-head", "version": 1, "kind": "{kind}",
                "channels": 2, "column_stride": 4, "max_shift_m": 1.5, "min_overlap": 0.5,
                "normalise": {{ "mean": [0, 0, 0.5, 0.5], "std": [1, 1, 0.5, 0.5] }},
                "layers": {layers},
                "share_threshold": 0.3, "sigma_m": 0.05, "zeroth_m": 0.1,
                "training": {{ "pairs": 10 }} }}"#
        )
    }

    #[test]
    fn a_model_can_move_to_another_thread() {
        fn send<T: Send>() {}
        send::<Model>();
        send::<Correlator>();
    }

    #[test]
    fn heads_predict_their_layers() {
        let path = Path::new("h.json");
        let linear = Head::parse(
            &head_json(
                "linear",
                r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#,
            ),
            path,
        )
        .expect("valid");
        // u = [1, 3, 1, -1]
        assert!((linear.predict(&[1.0, 3.0, 1.0, 0.0]) - (0.25 + 0.5 + 1.5 - 1.0)).abs() < 1e-15);
        let nonlinear = Head::parse(
            &head_json(
                "nonlinear",
                r#"[{"weights": [[1, 0, 0, 0], [-1, 0, 0, 0]], "bias": [0, 0], "activation": "relu"},
                    {"weights": [[2, 3]], "bias": [-1], "activation": "none"}]"#,
            ),
            path,
        )
        .expect("valid");
        assert_eq!(nonlinear.predict(&[2.0, 0.0, 0.5, 0.5]), 2.0 * 2.0 - 1.0);
        assert_eq!(nonlinear.predict(&[-2.0, 0.0, 0.5, 0.5]), 3.0 * 2.0 - 1.0);
        assert_eq!(nonlinear.training["pairs"], 10);
    }

    #[test]
    fn the_agreement_check_counts_the_channels_near_the_shift() {
        let corr = CorrVector {
            values: vec![0.10, 0.12, 0.50, -0.30, 0.9, 0.9, 0.9, 0.9],
            max_shift_cols: 10,
        };
        let check = Agreement {
            tolerance_m: 0.05,
            min_fraction: 0.5,
        };
        assert_eq!(check.fraction(&corr, 0.11), 0.5);
        assert_eq!(check.fraction(&corr, 0.52), 0.25);
        assert_eq!(check.fraction(&corr, 2.0), 0.0);
        let path = Path::new("h.json");
        let one = r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#;
        let with = head_json("linear", one).replace(
            "\"share_threshold\": 0.3",
            "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 0.5, \"rule\": \"r\"}",
        );
        assert_eq!(Head::parse(&with, path).expect("valid").agreement, Some(check));
        assert_eq!(
            Head::parse(&head_json("linear", one), path).expect("valid").agreement,
            None
        );
    }

    #[test]
    fn malformed_heads_name_the_file_and_the_field() {
        let path = Path::new("models/ground_encoding.head.json");
        let one = r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#;
        let cases = [
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1,1],[1,1,1,1],[1,1,1,1]], "bias": [0], "activation": "none"}]"#,
                ),
                "ground_encoding.head.json: layers[0].weights: 3 rows, expected 1",
            ),
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1]], "bias": [0], "activation": "none"}]"#,
                ),
                "layers[0].weights[0]: 3 values, expected 4",
            ),
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1,1]], "bias": [0], "activation": "relu"}]"#,
                ),
                "layers[0].activation: Relu, expected None",
            ),
            (head_json("nonlinear", one), "layers: 1 layer"),
            (head_json("cubic", one), "kind: \"cubic\""),
            (head_json("linear", "{}"), "layers: expected an array"),
            (
                head_json("linear", one).replace("\"version\": 1", "\"version\": 2"),
                "version: 2",
            ),
            (
                head_json("linear", one).replace("[1, 1, 0.5, 0.5]", "[1, 0, 0.5, 0.5]"),
                "normalise.std[1]: 0",
            ),
            (
                head_json("linear", one).replace("[0, 0, 0.5, 0.5]", "[0, 0, 0.5]"),
                "normalise.mean: 3 values, expected 4",
            ),
            (
                head_json("linear", one).replace("\"sigma_m\": 0.05,", ""),
                "sigma_m: missing",
            ),
            (
                head_json("linear", one).replace("\"channels\": 2", "\"channels\": 0"),
                "channels: expected an integer >= 1",
            ),
            (
                head_json("linear", one).replace("\"zeroth_m\"", "\"zeroth\""),
                "zeroth: unknown field",
            ),
            (
                head_json("linear", one).replace("\"share_threshold\": 0.3", "\"share_threshold\": \"x\""),
                "share_threshold: expected a finite number",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 1.5}",
                ),
                "agreement.min_fraction: 1.5, expected in [0, 1]",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"min_fraction\": 0.5}",
                ),
                "agreement.tolerance_m: missing",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 0.5, \"x\": 1}",
                ),
                "agreement.x: unknown field",
            ),
            (
                head_json("linear", one)
                    .replace("\"zeroth_m\": 0.1", "\"zeroth_m\": 0.1, \"encoder_crc32\": \"12345\""),
                "encoder_crc32: \"12345\", expected 8 hex digits",
            ),
            (
                head_json("linear", one).replace(
                    "\"zeroth_m\": 0.1",
                    "\"zeroth_m\": 0.1, \"encoder_crc32\": \"1234567g\"",
                ),
                "encoder_crc32: \"1234567g\", expected 8 hex digits",
            ),
            ("[1, 2".to_string(), "(file): not JSON"),
            ("[]".to_string(), "(file): expected an object"),
        ];
        for (text, want) in cases {
            let e = Head::parse(&text, path).expect_err(want);
            assert!(matches!(e, Error::Head { .. }), "{e:?}");
            let msg = e.to_string();
            assert!(msg.starts_with("models/ground_encoding.head.json: "), "{msg}");
            assert!(msg.contains(want), "{msg}\n  wanted: {want}");
        }
    }

    proptest::proptest! {
        #[test]
        fn head_parsing_never_panics(text in ".{0,200}") {
            let _ = Head::parse(&text, Path::new("x.json"));
        }

        #[test]
        fn correlation_of_any_features_is_bounded(
            data in proptest::collection::vec(-1e3f32..1e3, 2 * 3 * 12),
            max_shift_m in 0.0f64..5.0,
        ) {
            let r = Features { channels: 2, rows: 3, cols: 12, data: data[..72].to_vec() };
            let q = Features { channels: 2, rows: 3, cols: 12, data: data.iter().rev().copied().collect() };
            let v = correlate(&r, &q, &CorrelationParams { max_shift_m, ..PARAMS }).expect("valid");
            for &m in v.peaks() {
                proptest::prop_assert!((-1.0 - 1e-9..=1.0 + 1e-9).contains(&m));
            }
        }
    }
}
