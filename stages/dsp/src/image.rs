//! Image-level filters (Table 3.1): wavelet denoising (BayesShrink, soft threshold) and
//! gaussian smoothing.
//!
//! An image (a B-scan or a submap) is `rows x cols` values, row-major: row `r` is sample `r`
//! (depth), column `c` is trace `c` (along track), value `(r, c)` at `r * cols + c`.
//!
//! The 2-D discrete wavelet transform is written here as a separable filter bank with
//! PyWavelets' conventions (`symmetric` extension, `floor((n + L - 1) / 2)` coefficients per
//! axis), so that [`denoise_wavelet`] matches `skimage.restoration.denoise_wavelet` to 1e-5
//! relative (`tests/dsp_peer.rs`).

use serde::Deserialize;

use crate::trace::{check_len, param, reflect_index};
use gprflow_params as params;

use crate::{Error, ParamError, Result};

/// The size of an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shape {
    /// Rows: samples per trace (depth).
    pub rows: usize,
    /// Columns: traces (along track).
    pub cols: usize,
}

impl Shape {
    /// `rows x cols`.
    pub fn new(rows: usize, cols: usize) -> Self {
        Self { rows, cols }
    }

    /// Number of values, `rows · cols`.
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    /// Whether the image has no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Errors with [`Error::Size`] unless `values` holds `rows · cols` values.
    pub fn check(&self, what: &str, values: usize) -> Result<()> {
        check_len(what, self.len(), values)
    }
}

pub(crate) fn check_finite(what: &str, values: &[f32]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(Error::NonFinite {
            what: what.to_owned(),
            index,
            value: f64::from(values[index]),
        }),
        None => Ok(()),
    }
}

// ---------------------------------------------------------------------------------------------
// Wavelets and the 2-D DWT

/// An orthogonal Daubechies wavelet (`haar` is `db1`).
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "lowercase")]
pub enum Wavelet {
    /// Haar, the same as `db1`.
    Haar,
    /// Daubechies 1 (2 taps), scikit-image's default.
    #[default]
    Db1,
    /// Daubechies 2 (4 taps).
    Db2,
    /// Daubechies 3 (6 taps).
    Db3,
    /// Daubechies 4 (8 taps).
    Db4,
}

const DB1: [f64; 2] = [std::f64::consts::FRAC_1_SQRT_2, std::f64::consts::FRAC_1_SQRT_2];
const DB2: [f64; 4] = [
    0.482_962_913_144_534_16,
    0.836_516_303_737_807_9,
    0.224_143_868_042_013_4,
    -0.129_409_522_551_260_37,
];
const DB3: [f64; 6] = [
    0.332_670_552_950_082_63,
    0.806_891_509_311_092_5,
    0.459_877_502_118_491_54,
    -0.135_011_020_010_254_58,
    -0.085_441_273_882_026_66,
    0.035_226_291_885_709_53,
];
const DB4: [f64; 8] = [
    0.230_377_813_308_896_5,
    0.714_846_570_552_915_7,
    0.630_880_767_929_858_9,
    -0.027_983_769_416_859_854,
    -0.187_034_811_719_093_09,
    0.030_841_381_835_560_764,
    0.032_883_011_666_885_2,
    -0.010_597_401_785_069_032,
];

/// The four filters of a wavelet's filter bank.
#[derive(Clone, Debug, PartialEq)]
pub struct FilterBank {
    /// Decomposition low-pass.
    pub dec_lo: Vec<f64>,
    /// Decomposition high-pass.
    pub dec_hi: Vec<f64>,
    /// Reconstruction low-pass.
    pub rec_lo: Vec<f64>,
    /// Reconstruction high-pass.
    pub rec_hi: Vec<f64>,
}

impl Wavelet {
    /// The scaling (reconstruction low-pass) filter, `Σ = √2`.
    pub fn scaling_filter(self) -> &'static [f64] {
        match self {
            Self::Haar | Self::Db1 => &DB1,
            Self::Db2 => &DB2,
            Self::Db3 => &DB3,
            Self::Db4 => &DB4,
        }
    }

    /// Filter length `L`.
    pub fn filter_len(self) -> usize {
        self.scaling_filter().len()
    }

    /// The filter bank from the scaling filter `g`: `rec_lo = g`, `dec_lo[k] = g[L-1-k]`,
    /// `rec_hi[k] = (-1)^k g[L-1-k]`, `dec_hi[k] = rec_hi[L-1-k]` (PyWavelets' layout).
    pub fn filter_bank(self) -> FilterBank {
        let g = self.scaling_filter();
        let l = g.len();
        let rec_hi: Vec<f64> = (0..l)
            .map(|k| if k % 2 == 0 { g[l - 1 - k] } else { -g[l - 1 - k] })
            .collect();
        FilterBank {
            dec_lo: g.iter().rev().copied().collect(),
            dec_hi: rec_hi.iter().rev().copied().collect(),
            rec_lo: g.to_vec(),
            rec_hi,
        }
    }
}

/// The deepest useful level for `len` samples and a filter of `filter_len` taps (PyWavelets'
/// `dwt_max_level`): `floor(log2(len / (filter_len - 1)))`, 0 when `len < filter_len - 1`.
pub fn dwt_max_level(len: usize, filter_len: usize) -> usize {
    let base = filter_len.saturating_sub(1).max(1);
    if len < base {
        return 0;
    }
    // Largest j with base · 2^j <= len, in integers (no rounding at exact powers of two).
    let mut level = 0;
    while base << (level + 1) <= len {
        level += 1;
    }
    level
}

/// A 2-D array of f64, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// `rows · cols` values, `(r, c)` at `r * cols + c`.
    pub data: Vec<f64>,
}

impl Plane {
    /// A plane from f32 image values.
    pub fn from_image(image: &[f32], shape: Shape) -> Result<Self> {
        shape.check("image", image.len())?;
        Ok(Self {
            rows: shape.rows,
            cols: shape.cols,
            data: image.iter().map(|&v| f64::from(v)).collect(),
        })
    }

    fn zeros(rows: usize, cols: usize) -> Self {
        Self {
            rows,
            cols,
            data: vec![0.0; rows * cols],
        }
    }

    fn transposed(&self) -> Self {
        let mut t = Self::zeros(self.cols, self.rows);
        for r in 0..self.rows {
            for c in 0..self.cols {
                t.data[c * self.rows + r] = self.data[r * self.cols + c];
            }
        }
        t
    }

    /// The top-left `rows x cols` corner.
    fn cropped(&self, rows: usize, cols: usize) -> Self {
        if (rows, cols) == (self.rows, self.cols) {
            return self.clone();
        }
        let mut out = Self::zeros(rows, cols);
        for r in 0..rows {
            out.data[r * cols..(r + 1) * cols].copy_from_slice(&self.data[r * self.cols..r * self.cols + cols]);
        }
        out
    }
}

/// The three detail subbands of one level; the first letter is the filter along axis 0
/// (rows, depth), the second along axis 1 (columns, along track), as PyWavelets names them.
#[derive(Clone, Debug, PartialEq)]
pub struct Details {
    /// Low-pass along axis 0, high-pass along axis 1.
    pub ad: Plane,
    /// High-pass along axis 0, low-pass along axis 1.
    pub da: Plane,
    /// High-pass along both axes (the finest one gives the noise estimate).
    pub dd: Plane,
}

impl Details {
    fn planes_mut(&mut self) -> [&mut Plane; 3] {
        [&mut self.ad, &mut self.da, &mut self.dd]
    }
}

/// A multilevel 2-D decomposition: the coarsest approximation and the details, coarsest first
/// (PyWavelets' `wavedecn` order).
#[derive(Clone, Debug, PartialEq)]
pub struct Decomposition {
    /// Approximation at the deepest level.
    pub approx: Plane,
    /// Details, `details[0]` the deepest level, `details[last]` the finest.
    pub details: Vec<Details>,
}

/// One level along axis 1 of every row: with `x` extended symmetrically
/// (`x[-1-i] = x[i]`, `x[n+i] = x[n-1-i]`) and `m = floor((n + L - 1) / 2)`,
/// `a[k] = Σ_j lo[j] x[2k + 1 - j]`, `d[k] = Σ_j hi[j] x[2k + 1 - j]`, `k = 0..m`.
fn dwt_rows(x: &Plane, bank: &FilterBank) -> (Plane, Plane) {
    let l = bank.dec_lo.len();
    let n = x.cols;
    let m = (n + l - 1) / 2;
    let mut a = Plane::zeros(x.rows, m);
    let mut d = Plane::zeros(x.rows, m);
    for r in 0..x.rows {
        let row = &x.data[r * n..(r + 1) * n];
        for k in 0..m {
            let (mut sa, mut sd) = (0.0, 0.0);
            for j in 0..l {
                let v = row[reflect_index(2 * k as isize + 1 - j as isize, n)];
                sa += bank.dec_lo[j] * v;
                sd += bank.dec_hi[j] * v;
            }
            a.data[r * m + k] = sa;
            d.data[r * m + k] = sd;
        }
    }
    (a, d)
}

/// The inverse of [`dwt_rows`] for `m` coefficients per row: `n = 2m - L + 2` samples,
/// `y[i] = Σ_j (lo[j] a[p] + hi[j] d[p])` over `j` with `i + L - 2 - j = 2p`, `0 <= p < m`.
fn idwt_rows(a: &Plane, d: &Plane, bank: &FilterBank) -> Plane {
    let l = bank.rec_lo.len();
    let m = a.cols;
    let n = 2 * m + 2 - l;
    let mut y = Plane::zeros(a.rows, n);
    for r in 0..a.rows {
        let (ar, dr) = (&a.data[r * m..(r + 1) * m], &d.data[r * m..(r + 1) * m]);
        for i in 0..n {
            let t = i + l - 2;
            let mut s = 0.0;
            // j with the parity of t, p = (t - j) / 2 in 0..m.
            let mut j = t % 2;
            while j < l {
                if j <= t {
                    let p = (t - j) / 2;
                    if p < m {
                        s += bank.rec_lo[j] * ar[p] + bank.rec_hi[j] * dr[p];
                    }
                }
                j += 2;
            }
            y.data[r * n + i] = s;
        }
    }
    y
}

/// One level of the 2-D DWT (`pywt.dwtn(x, w, mode='symmetric')`): the approximation and the
/// three details, each `floor((rows + L - 1) / 2) x floor((cols + L - 1) / 2)`.
pub fn dwt2(x: &Plane, wavelet: Wavelet) -> (Plane, Details) {
    let bank = wavelet.filter_bank();
    // Axis 0 (along columns) by transposing, then axis 1.
    let (a0, d0) = dwt_rows(&x.transposed(), &bank);
    let (aa, ad) = dwt_rows(&a0.transposed(), &bank);
    let (da, dd) = dwt_rows(&d0.transposed(), &bank);
    (aa, Details { ad, da, dd })
}

/// The inverse of [`dwt2`] (`pywt.idwtn`): `2m - L + 2` values per axis. An approximation
/// one larger than the details along an axis (odd sizes one level up) is cropped first, as
/// `pywt.waverecn` does.
pub fn idwt2(approx: &Plane, details: &Details, wavelet: Wavelet) -> Plane {
    let bank = wavelet.filter_bank();
    let aa = approx.cropped(details.dd.rows, details.dd.cols);
    let a0 = idwt_rows(&aa, &details.ad, &bank).transposed();
    let d0 = idwt_rows(&details.da, &details.dd, &bank).transposed();
    idwt_rows(&a0, &d0, &bank).transposed()
}

/// `levels` levels of [`dwt2`] (`pywt.wavedecn(x, w, mode='symmetric', level=levels)`).
pub fn wavedec2(x: &Plane, wavelet: Wavelet, levels: usize) -> Decomposition {
    let mut approx = x.clone();
    let mut details = Vec::with_capacity(levels);
    for _ in 0..levels {
        let (a, d) = dwt2(&approx, wavelet);
        approx = a;
        details.push(d);
    }
    details.reverse();
    Decomposition { approx, details }
}

/// The inverse of [`wavedec2`] (`pywt.waverecn`); crop the result to the original size (it
/// is one larger along an axis of odd length).
pub fn waverec2(dec: &Decomposition, wavelet: Wavelet) -> Plane {
    dec.details
        .iter()
        .fold(dec.approx.clone(), |a, d| idwt2(&a, d, wavelet))
}

// ---------------------------------------------------------------------------------------------
// Wavelet denoising

/// `0.6744897501960817`, the 75th percentile of the standard normal (`norm.ppf(0.75)`).
const NORMAL_Q75: f64 = 0.674_489_750_196_081_7;

/// Wavelet denoising with BayesShrink thresholds and soft thresholding.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct WaveletDenoiseParams {
    /// Wavelet (`haar`, `db1`..`db4`; default `db1`, scikit-image's default).
    pub wavelet: Wavelet,
    /// Decomposition levels (default `None`: scikit-image's choice,
    /// `max(dwt_max_level(min(rows, cols), L) - 3, 1)`, which skips the coarsest scales).
    pub levels: Option<usize>,
}

impl Default for WaveletDenoiseParams {
    fn default() -> Self {
        Self {
            wavelet: Wavelet::Db1,
            levels: None,
        }
    }
}

impl WaveletDenoiseParams {
    /// Checks `levels >= 1` when given.
    pub fn check(&self) -> params::Result {
        self.levels
            .map_or(Ok(()), |levels| params::at_least("wavelet.levels", levels, 1))
    }
}

/// What [`denoise_wavelet`] estimated.
#[derive(Clone, Debug, PartialEq)]
pub struct WaveletDenoiseSummary {
    /// Levels used.
    pub levels: usize,
    /// Noise standard deviation estimated from the finest diagonal detail.
    pub sigma: f64,
    /// BayesShrink thresholds `[ad, da, dd]` per level, coarsest first.
    pub thresholds: Vec<[f64; 3]>,
}

/// Denoises an image in place as `skimage.restoration.denoise_wavelet(img, wavelet=w,
/// mode='soft', method='BayesShrink', rescale_sigma=True)` does for a float image:
///
/// 1. `J` levels of the 2-D DWT ([`wavedec2`]), `J` from [`WaveletDenoiseParams::levels`];
/// 2. noise `σ = median(|dd₁|) / 0.6744897501960817` over the non-zero coefficients of the
///    finest diagonal detail `dd₁` (σ = 0, hence no change, when all are zero);
/// 3. per detail subband `D`: BayesShrink `t = σ² / sqrt(max(mean(D²) - σ², ε))`, ε the f64
///    machine epsilon;
/// 4. soft threshold `D ← sign(D) · max(|D| - t, 0)`; the approximation is kept;
/// 5. inverse DWT ([`waverec2`]), cropped to `rows x cols`.
///
/// scikit-image clips its output to [-1, 1] or [0, 1] only for integer images; a float image,
/// as here, is not clipped (and `rescale_sigma` only matters for integer images). Computed in
/// f64. Errors on a size mismatch, an empty image or non-finite values.
pub fn denoise_wavelet(
    image: &mut [f32],
    shape: Shape,
    params: &WaveletDenoiseParams,
) -> Result<WaveletDenoiseSummary> {
    shape.check("image", image.len())?;
    if shape.is_empty() {
        return Err(param("image", format!("{shape:?} has no values")));
    }
    check_finite("image", image)?;
    let wavelet = params.wavelet;
    params.check()?;
    let levels = match params.levels {
        Some(levels) => levels,
        None => {
            let max = dwt_max_level(shape.rows.min(shape.cols), wavelet.filter_len());
            max.saturating_sub(3).max(1)
        }
    };
    let mut dec = wavedec2(&Plane::from_image(image, shape)?, wavelet, levels);
    let finest = &dec.details[levels - 1].dd.data;
    let sigma = median_abs_nonzero(finest) / NORMAL_Q75;
    let var = sigma * sigma;
    let mut thresholds = Vec::with_capacity(levels);
    for level in &mut dec.details {
        let mut t = [0.0; 3];
        for (slot, band) in t.iter_mut().zip(level.planes_mut()) {
            let power = band.data.iter().map(|v| v * v).sum::<f64>() / band.data.len() as f64;
            let threshold = var / (power - var).max(f64::EPSILON).sqrt();
            band.data
                .iter_mut()
                .for_each(|v| *v = v.signum() * (v.abs() - threshold).max(0.0));
            *slot = threshold;
        }
        thresholds.push(t);
    }
    let out = waverec2(&dec, wavelet);
    for r in 0..shape.rows {
        for c in 0..shape.cols {
            image[r * shape.cols + c] = out.data[r * out.cols + c] as f32;
        }
    }
    Ok(WaveletDenoiseSummary {
        levels,
        sigma,
        thresholds,
    })
}

/// Median of `|v|` over the non-zero values (mean of the two middle ones for an even count),
/// 0 when all are zero.
fn median_abs_nonzero(values: &[f64]) -> f64 {
    let mut mags: Vec<f64> = values.iter().filter(|v| **v != 0.0).map(|v| v.abs()).collect();
    if mags.is_empty() {
        return 0.0;
    }
    // The middle order statistics by selection, not a whole sort (the sort was 7 % of the
    // submap filter's time on the localisation graph).
    let n = mags.len();
    let (below, upper, _) = mags.select_nth_unstable_by(n / 2, f64::total_cmp);
    let upper = *upper;
    if n % 2 == 1 {
        upper
    } else {
        let lower = below.iter().copied().max_by(f64::total_cmp).unwrap_or(upper);
        0.5 * (lower + upper)
    }
}

// ---------------------------------------------------------------------------------------------
// Gaussian smoothing

/// Gaussian smoothing along track (and optionally along depth).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct GaussianParams {
    /// Standard deviation along track (axis 1, across traces), pixels (> 0; default 1.0).
    pub sigma_along_track_px: f64,
    /// Standard deviation along depth (axis 0, across samples), pixels (default `None`: off).
    pub sigma_depth_px: Option<f64>,
    /// Kernel radius in standard deviations (default 4.0, scipy's `truncate`).
    pub truncate: f64,
}

impl Default for GaussianParams {
    fn default() -> Self {
        Self {
            sigma_along_track_px: 1.0,
            sigma_depth_px: None,
            truncate: 4.0,
        }
    }
}

impl GaussianParams {
    /// Checks both kernels ([`gaussian_kernel`]'s conditions), keys under `gaussian.`.
    pub fn check(&self) -> params::Result {
        check_kernel("sigma_along_track_px", self.sigma_along_track_px, self.truncate)
            .map_err(|e| e.within("gaussian"))?;
        self.sigma_depth_px.map_or(Ok(()), |sigma| {
            check_kernel("sigma_depth_px", sigma, self.truncate).map_err(|e| e.within("gaussian"))
        })
    }
}

/// `σ > 0` and `truncate >= 0` finite, with a radius below 1e6 px.
fn check_kernel(sigma_key: &str, sigma_px: f64, truncate: f64) -> params::Result {
    params::positive(sigma_key, sigma_px)?;
    if !(truncate.is_finite() && truncate >= 0.0 && truncate * sigma_px < 1e6) {
        return Err(ParamError::new(
            "truncate",
            format!("must be >= 0 with a radius below 1e6 px, got {truncate}"),
        ));
    }
    Ok(())
}

/// The normalised kernel of `scipy.ndimage.gaussian_filter1d`: radius
/// `r = floor(truncate · σ + 0.5)`, `w[k] = exp(-k² / (2σ²)) / Σ_j exp(-j² / (2σ²))`,
/// `k = -r..=r`. Errors unless `σ > 0` and `truncate >= 0` are finite.
pub fn gaussian_kernel(sigma_px: f64, truncate: f64) -> Result<Vec<f64>> {
    check_kernel("sigma", sigma_px, truncate).map_err(|e| e.within("gaussian"))?;
    let radius = (truncate * sigma_px + 0.5).floor() as isize;
    let w: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k * k) as f64 / (sigma_px * sigma_px)).exp())
        .collect();
    let total: f64 = w.iter().sum();
    Ok(w.into_iter().map(|v| v / total).collect())
}

/// Correlates `line` in place with a centred `kernel`, mode `reflect`
/// (`y[i] = Σ_k w[k] x[reflect(i + k - r)]`), using `ext` as scratch.
fn smooth_line(line: &mut [f64], kernel: &[f64], ext: &mut Vec<f64>) {
    let n = line.len();
    if n == 0 {
        return; // an image with no rows or columns: nothing to smooth
    }
    let r = (kernel.len() / 2) as isize;
    ext.clear();
    ext.extend((-r..n as isize + r).map(|i| line[reflect_index(i, n)]));
    for (i, y) in line.iter_mut().enumerate() {
        *y = kernel.iter().zip(&ext[i..]).map(|(w, x)| w * x).sum();
    }
}

/// Smooths an image in place as `scipy.ndimage.gaussian_filter1d(img, σ_track, axis=1,
/// mode='reflect', truncate=truncate)`, then, if `sigma_depth_px` is set, the same along
/// axis 0: `y[r, c] = Σ_k w[k] x[r, reflect(c + k - R)]` with the kernel of
/// [`gaussian_kernel`]. Computed in f64. Errors on a size mismatch, bad sigmas or non-finite
/// values.
pub fn gaussian_smooth(image: &mut [f32], shape: Shape, params: &GaussianParams) -> Result<()> {
    shape.check("image", image.len())?;
    check_finite("image", image)?;
    let along = gaussian_kernel(params.sigma_along_track_px, params.truncate)?;
    let depth = params
        .sigma_depth_px
        .map(|s| gaussian_kernel(s, params.truncate))
        .transpose()?;
    let (rows, cols) = (shape.rows, shape.cols);
    let mut line = Vec::with_capacity(rows.max(cols));
    let mut ext = Vec::new();
    for r in 0..rows {
        let row = &mut image[r * cols..(r + 1) * cols];
        line.clear();
        line.extend(row.iter().map(|&v| f64::from(v)));
        smooth_line(&mut line, &along, &mut ext);
        row.iter_mut().zip(&line).for_each(|(v, &s)| *v = s as f32);
    }
    if let Some(kernel) = depth {
        for c in 0..cols {
            line.clear();
            line.extend((0..rows).map(|r| f64::from(image[r * cols + c])));
            smooth_line(&mut line, &kernel, &mut ext);
            for (r, &s) in line.iter().enumerate() {
                image[r * cols + c] = s as f32;
            }
        }
    }
    Ok(())
}

/// Saliency of a `rows x cols` row-major image (seed 000 §4.4): the standard deviation of
/// each row across the columns, average-pooled over the rows. Flat images (no along-track structure) score 0.
pub fn saliency(pixels: &[f32], rows: usize, cols: usize) -> f32 {
    if rows == 0 || cols == 0 {
        return 0.0;
    }
    let mut total = 0.0f64;
    for row in pixels.chunks_exact(cols).take(rows) {
        let mean = row.iter().map(|&v| f64::from(v)).sum::<f64>() / cols as f64;
        let var = row.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / cols as f64;
        total += var.sqrt();
    }
    (total / rows as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    const RECONSTRUCTION: f64 = 1e-12;
    const ALL: [Wavelet; 5] = [Wavelet::Haar, Wavelet::Db1, Wavelet::Db2, Wavelet::Db3, Wavelet::Db4];

    #[test]
    fn median_of_the_non_zero_magnitudes_by_selection_equals_the_sorted_middle() {
        let sorted_median = |values: &[f64]| {
            let mut m: Vec<f64> = values.iter().filter(|v| **v != 0.0).map(|v| v.abs()).collect();
            m.sort_by(f64::total_cmp);
            match m.len() {
                0 => 0.0,
                n if n % 2 == 1 => m[n / 2],
                n => 0.5 * (m[n / 2 - 1] + m[n / 2]),
            }
        };
        for n in 0..40 {
            let values: Vec<f64> = (0..n)
                .map(|i| {
                    if i % 5 == 0 {
                        0.0
                    } else {
                        ((i * 7919) % 101) as f64 / 10.0 - 5.0
                    }
                })
                .collect();
            assert_eq!(median_abs_nonzero(&values), sorted_median(&values), "n = {n}");
        }
        assert_eq!(median_abs_nonzero(&[0.0, 0.0]), 0.0);
        assert_eq!(median_abs_nonzero(&[-3.0, 1.0, 0.0, 2.0, -4.0]), 2.5);
    }

    fn plane(rows: usize, cols: usize) -> Plane {
        let data = (0..rows * cols)
            .map(|i| ((i * 7919) % 1013) as f64 / 1013.0 - 0.5 + (i as f64 * 0.01).sin())
            .collect();
        Plane { rows, cols, data }
    }

    #[test]
    fn dwt_reconstructs_perfectly() {
        for wavelet in ALL {
            for (rows, cols) in [(201, 200), (16, 16), (7, 5), (1, 9), (33, 2)] {
                let x = plane(rows, cols);
                let levels = dwt_max_level(rows.min(cols), wavelet.filter_len()).max(1);
                let dec = wavedec2(&x, wavelet, levels);
                let y = waverec2(&dec, wavelet).cropped(rows, cols);
                let err = x
                    .data
                    .iter()
                    .zip(&y.data)
                    .fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
                assert!(err < RECONSTRUCTION, "{wavelet:?} {rows}x{cols}: {err}");
            }
        }
    }

    #[test]
    fn filter_banks_are_orthonormal() {
        for wavelet in ALL {
            let b = wavelet.filter_bank();
            let l = b.rec_lo.len();
            for shift in (0..l).step_by(2) {
                let dot = |p: &[f64], q: &[f64]| -> f64 { (0..l - shift).map(|k| p[k] * q[k + shift]).sum() };
                let want = if shift == 0 { 1.0 } else { 0.0 };
                assert!((dot(&b.rec_lo, &b.rec_lo) - want).abs() < RECONSTRUCTION);
                assert!(dot(&b.rec_lo, &b.rec_hi).abs() < RECONSTRUCTION);
            }
        }
    }

    #[test]
    fn max_level_matches_pywt() {
        assert_eq!(dwt_max_level(200, 2), 7);
        assert_eq!(dwt_max_level(200, 4), 6);
        assert_eq!(dwt_max_level(200, 8), 4);
        assert_eq!(dwt_max_level(64, 2), 6);
        assert_eq!(dwt_max_level(5, 8), 0);
    }

    #[test]
    fn gaussian_kernel_is_normalised() {
        let w = gaussian_kernel(1.5, 4.0).expect("valid");
        assert_eq!(w.len(), 13);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < RECONSTRUCTION);
        assert!(gaussian_kernel(0.0, 4.0).is_err());
    }
}
