//! Trace-level filters of an impulse GPR (seed 000 §3.2.2, Table 3.1): dewow, zero-time
//! correction, FIR band-pass, SEC gain (eq. 3.1) and stacking.
//!
//! A trace (A-scan) is one `&mut [f32]` of `samples` values, sample `k` at time
//! `k · sample_interval_ns`. Each filter is built once from its `Params` and the
//! [`TraceFormat`] (which precomputes windows, taps and gains and owns its scratch buffers),
//! then applied to any number of traces without allocating.
//!
//! Each filter matches a reference implementation (scipy.ndimage, scipy.signal) to 1e-5
//! relative on the same input; see `tests/dsp_peer.rs` and `tools/peer/dsp_fixtures.py`.

use serde::Deserialize;

use gprflow_params as params;

use crate::{Error, ParamError, Result};

/// The shape of the traces of one radar channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceFormat {
    /// Samples per trace (CMU-GPR: 201).
    pub samples: usize,
    /// Time between samples, ns (CMU-GPR: 0.2 ns, 5 GHz sampling).
    pub sample_interval_ns: f64,
    /// Centre frequency of the antenna, Hz (CMU-GPR: 500 MHz).
    pub center_frequency_hz: f64,
}

impl TraceFormat {
    /// Checks that the format describes a usable trace: at least 2 samples, a positive finite
    /// sample interval and centre frequency below the Nyquist frequency `1 / (2 dt)`.
    pub fn validate(&self) -> Result<()> {
        if self.samples < 2 {
            return Err(param("samples", format!("need at least 2, got {}", self.samples)));
        }
        if !(self.sample_interval_ns.is_finite() && self.sample_interval_ns > 0.0) {
            return Err(param(
                "sample_interval_ns",
                format!("must be positive and finite, got {}", self.sample_interval_ns),
            ));
        }
        let nyquist_hz = 0.5 / (self.sample_interval_ns * 1e-9);
        if !(self.center_frequency_hz.is_finite()
            && self.center_frequency_hz > 0.0
            && self.center_frequency_hz < nyquist_hz)
        {
            return Err(param(
                "center_frequency_hz",
                format!(
                    "must be in (0, {nyquist_hz}) (the Nyquist frequency), got {}",
                    self.center_frequency_hz
                ),
            ));
        }
        Ok(())
    }

    /// Sampling frequency `fs = 1 / dt`, Hz.
    pub fn sampling_frequency_hz(&self) -> f64 {
        1e9 / self.sample_interval_ns
    }

    /// A format with `samples` samples at `sample_interval_ns` and the centre frequency.
    pub fn new(samples: usize, sample_interval_ns: f64, center_frequency_hz: f64) -> Self {
        Self {
            samples,
            sample_interval_ns,
            center_frequency_hz,
        }
    }

    /// Errors with [`Error::Size`] unless `trace` has `samples` values.
    pub fn check(&self, what: &str, trace: &[f32]) -> Result<()> {
        check_len(what, self.samples, trace.len())
    }
}

pub(crate) fn param(key: &str, message: String) -> Error {
    Error::Param(ParamError::new(key, message))
}

pub(crate) fn check_len(what: &str, expected: usize, got: usize) -> Result<()> {
    if expected == got {
        Ok(())
    } else {
        Err(Error::Size {
            what: what.to_owned(),
            expected,
            got,
        })
    }
}

/// Index of `i` in `0..n` under a half-sample symmetric extension (`d c b a | a b c d | d c b a`,
/// scipy.ndimage `reflect`, PyWavelets `symmetric`), for any `i` and `n >= 1`.
pub(crate) fn reflect_index(i: isize, n: usize) -> usize {
    let period = 2 * n as isize;
    let m = i.rem_euclid(period);
    if m < n as isize {
        m as usize
    } else {
        (period - 1 - m) as usize
    }
}

// ---------------------------------------------------------------------------------------------
// Dewow

/// Dewow: DC subtraction and a low-cut tied to the centre frequency (Jol 2009, the thesis's
/// reference \[55\]: a running mean over about one period of the centre frequency).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct DewowParams {
    /// Length of the running-mean window in periods of the centre frequency (dimensionless;
    /// default 1.0). The window in samples is the odd integer nearest to
    /// `window_periods / (fc · dt)` (ties up): 11 samples for 500 MHz at 0.2 ns; it must be at
    /// least 3.
    pub window_periods: f64,
}

impl Default for DewowParams {
    fn default() -> Self {
        Self { window_periods: 1.0 }
    }
}

impl DewowParams {
    /// Checks what does not depend on the trace format: a positive window.
    pub fn check(&self) -> params::Result {
        params::positive("dewow.window_periods", self.window_periods)
    }
}

/// The dewow filter of one trace format (see [`Dewow::apply`]).
#[derive(Clone, Debug)]
pub struct Dewow {
    samples: usize,
    half_window: usize,
    /// `δ[d - h] - 1/w`, `d = 0..w`: the trace minus its running mean, as one kernel.
    kernel: Vec<f32>,
    extended: Vec<f32>,
}

impl Dewow {
    /// Builds the filter; errors if the window is shorter than 3 samples or not finite.
    pub fn new(params: &DewowParams, format: &TraceFormat) -> Result<Self> {
        params.check()?;
        format.validate()?;
        let samples_per_period = 1e9 / (format.center_frequency_hz * format.sample_interval_ns);
        let raw = params.window_periods * samples_per_period;
        if !(3.0..1e9).contains(&raw) {
            return Err(param(
                "dewow.window_periods",
                format!(
                    "gives a window of {raw} samples ({} periods of {} samples): need >= 3",
                    params.window_periods, samples_per_period
                ),
            ));
        }
        // Nearest odd integer, ties up: 2 floor(raw / 2) + 1.
        let half_window = (raw / 2.0).floor() as usize;
        let w = 2 * half_window + 1;
        let kernel = (0..w)
            .map(|d| f32::from(u8::from(d == half_window)) - 1.0 / w as f32)
            .collect();
        Ok(Self {
            samples: format.samples,
            half_window,
            kernel,
            extended: vec![0.0; format.samples + 2 * half_window],
        })
    }

    /// Window length `w = 2h + 1` of the running mean, samples.
    pub fn window_samples(&self) -> usize {
        2 * self.half_window + 1
    }

    /// Dewows one trace in place:
    ///
    /// `y[i] = x'[i] - (1/w) Σ_{j=i-h}^{i+h} x'[clamp(j, 0, n-1)]`,  with `x' = x - mean(x)`,
    ///
    /// i.e. the DC-free trace minus its running mean over `w = 2h + 1` samples with the edges
    /// held at the end values (scipy.ndimage.uniform_filter1d, mode `nearest`). The running
    /// mean of a constant is that constant, so the DC subtraction is implied by the second
    /// step; the filter computes `x - running_mean(x)` directly, as one f32 convolution of
    /// the edge-extended trace with the kernel `δ[d - h] - 1/w`.
    pub fn apply(&mut self, trace: &mut [f32]) -> Result<()> {
        check_len("dewow trace", self.samples, trace.len())?;
        let (n, h) = (trace.len(), self.half_window);
        let ext = &mut self.extended;
        ext[..h].fill(trace[0]);
        ext[h..h + n].copy_from_slice(trace);
        ext[h + n..].fill(trace[n - 1]);
        convolve_valid(&self.kernel, ext, trace);
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Zero time

/// Zero-time correction: the zero time of a trace is its first negative peak (§3.2.2).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct ZeroTimeParams {
    /// A negative peak counts when it is below `-threshold · max|x|` (fraction of the trace's
    /// largest magnitude, in (0, 1]; default 0.5: the direct coupling wave is the strongest
    /// event of a raw trace, so half its amplitude skips noise and the precursor wiggle while
    /// keeping a direct wave that is somewhat weaker than a late reflection).
    pub threshold: f64,
}

impl Default for ZeroTimeParams {
    fn default() -> Self {
        Self { threshold: 0.5 }
    }
}

impl ZeroTimeParams {
    /// Checks `0 < threshold <= 1`.
    pub fn check(&self) -> params::Result {
        params::fraction("zero_time.threshold", self.threshold)
    }
}

/// Index of the first negative peak of a trace: with `T = threshold · max_k |x[k]|`, the first
/// run of consecutive samples with `x[k] < -T`, and in it the (first) index of the smallest
/// value. `None` when `max|x|` is zero or infinite or no sample is below `-T` (NaN samples
/// never count). Taking the minimum of the whole run (rather than its first local minimum) keeps a
/// noise wiggle on the flank of the lobe from being picked.
pub fn zero_time_index(trace: &[f32], params: &ZeroTimeParams) -> Option<usize> {
    let peak = trace.iter().fold(0.0_f32, |m, v| m.max(v.abs()));
    if !(peak.is_finite() && peak > 0.0) {
        return None;
    }
    let limit = -(params.threshold * f64::from(peak)) as f32;
    let start = trace.iter().position(|&v| v < limit)?;
    let mut best = start;
    for (k, &v) in trace.iter().enumerate().skip(start + 1) {
        if v >= limit {
            break;
        }
        if v < trace[best] {
            best = k;
        }
    }
    Some(best)
}

/// Moves sample `index` to sample 0: `y[k] = x[k + index]` for `k + index < n`, `y[k] = 0`
/// after. The caller records the zero time `index · dt`. An `index >= n` zeroes the trace.
pub fn shift_to_zero_time(trace: &mut [f32], index: usize) {
    let n = trace.len();
    let index = index.min(n);
    trace.copy_within(index.., 0);
    trace[n - index..].fill(0.0);
}

// ---------------------------------------------------------------------------------------------
// FIR band-pass

/// FIR band-pass with a triangular window, applied forward and backward (zero phase).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct BandpassParams {
    /// Number of taps, odd, >= 3 (default 31: 6.2 ns at 0.2 ns, about three periods of a
    /// 500 MHz wavelet). The trace must be longer than `3 · taps` (filtfilt's padding).
    pub taps: usize,
    /// Low cut-off as a multiple of the centre frequency (default 0.5: 250 MHz for a 500 MHz
    /// antenna).
    pub low_cutoff_ratio: f64,
    /// High cut-off as a multiple of the centre frequency (default 2.0: 1 GHz for a 500 MHz
    /// antenna, 0.4 of the 2.5 GHz Nyquist frequency at 0.2 ns). An impulse antenna's band
    /// spans about one octave either side of its centre; above that is noise.
    pub high_cutoff_ratio: f64,
}

impl Default for BandpassParams {
    fn default() -> Self {
        Self {
            taps: 31,
            low_cutoff_ratio: 0.5,
            high_cutoff_ratio: 2.0,
        }
    }
}

impl BandpassParams {
    /// Checks what does not depend on the trace format: odd taps >= 3 and
    /// `0 < low_cutoff_ratio < high_cutoff_ratio` (the Nyquist bound needs the format).
    pub fn check(&self) -> params::Result {
        if self.taps < 3 || self.taps.is_multiple_of(2) {
            return Err(ParamError::new(
                "bandpass.taps",
                format!("must be odd and >= 3, got {}", self.taps),
            ));
        }
        params::positive("bandpass.low_cutoff_ratio", self.low_cutoff_ratio)?;
        params::finite("bandpass.high_cutoff_ratio", self.high_cutoff_ratio)?;
        if self.high_cutoff_ratio <= self.low_cutoff_ratio {
            return Err(ParamError::new(
                "bandpass.high_cutoff_ratio",
                format!(
                    "must be above low_cutoff_ratio {}, got {}",
                    self.low_cutoff_ratio, self.high_cutoff_ratio
                ),
            ));
        }
        Ok(())
    }
}

/// Band-pass taps as `scipy.signal.firwin(taps, [low, high], pass_zero=False,
/// window='triang', fs=fs)`: with `α = (taps - 1) / 2`, `m = k - α`, normalised cut-offs
/// `l = low / (fs/2)`, `u = high / (fs/2)` and `sinc(x) = sin(πx) / (πx)`,
///
/// `h[k] = w[k] (u sinc(u m) - l sinc(l m))`,  `w` the symmetric triangular window
/// `w[k] = 2 (k+1) / (taps + 1)` for `k <= α` (mirrored after),
///
/// scaled so that the gain at the centre of the passband `(l + u) / 2` is one:
/// `h /= Σ_k h[k] cos(π m (l + u) / 2)`. Errors unless `taps` is odd and >= 3 and
/// `0 < low < high < fs/2`.
pub fn firwin_bandpass(taps: usize, low_hz: f64, high_hz: f64, sampling_frequency_hz: f64) -> Result<Vec<f64>> {
    if taps < 3 || taps.is_multiple_of(2) {
        return Err(param("bandpass.taps", format!("must be odd and >= 3, got {taps}")));
    }
    let nyquist_hz = 0.5 * sampling_frequency_hz;
    if !(low_hz > 0.0 && low_hz < high_hz && high_hz < nyquist_hz) {
        return Err(param(
            "bandpass",
            format!(
                "cut-offs must satisfy 0 < low < high < {nyquist_hz} Hz (Nyquist), got low {low_hz} Hz, high {high_hz} Hz"
            ),
        ));
    }
    let (l, u) = (low_hz / nyquist_hz, high_hz / nyquist_hz);
    let alpha = 0.5 * (taps - 1) as f64;
    let sinc = |x: f64| {
        if x == 0.0 {
            1.0
        } else {
            let px = std::f64::consts::PI * x;
            px.sin() / px
        }
    };
    let half = taps.div_ceil(2);
    let window = |k: usize| {
        let k = if k < half { k } else { taps - 1 - k };
        2.0 * (k + 1) as f64 / (taps + 1) as f64
    };
    let mut h: Vec<f64> = (0..taps)
        .map(|k| {
            let m = k as f64 - alpha;
            window(k) * (u * sinc(u * m) - l * sinc(l * m))
        })
        .collect();
    let centre = 0.5 * (l + u);
    let gain: f64 = h
        .iter()
        .enumerate()
        .map(|(k, v)| v * (std::f64::consts::PI * (k as f64 - alpha) * centre).cos())
        .sum();
    h.iter_mut().for_each(|v| *v /= gain);
    Ok(h)
}

/// The zero-phase FIR band-pass of one trace format (see [`Bandpass::apply`]).
#[derive(Clone, Debug)]
pub struct Bandpass {
    taps: Vec<f64>,
    /// `b ⋆ b`, the autocorrelation of the taps (length `2 taps - 1`, symmetric).
    kernel: Vec<f32>,
    samples: usize,
    extended: Vec<f32>,
}

impl Bandpass {
    /// Designs the taps ([`firwin_bandpass`] with the cut-offs `ratio · fc`) for this format;
    /// errors if `3 · taps >= samples` (scipy's filtfilt refuses it too).
    pub fn new(params: &BandpassParams, format: &TraceFormat) -> Result<Self> {
        params.check()?;
        format.validate()?;
        let fc = format.center_frequency_hz;
        let taps = firwin_bandpass(
            params.taps,
            params.low_cutoff_ratio * fc,
            params.high_cutoff_ratio * fc,
            format.sampling_frequency_hz(),
        )?;
        let padlen = 3 * params.taps;
        if padlen >= format.samples {
            return Err(param(
                "bandpass.taps",
                format!(
                    "3 x {} taps = {padlen} must be below the {} samples of a trace",
                    params.taps, format.samples
                ),
            ));
        }
        let n_taps = taps.len();
        let kernel = (0..2 * n_taps - 1)
            .map(|d| {
                // d - (n_taps - 1) = j - i
                let lag = d as isize - (n_taps as isize - 1);
                (0..n_taps)
                    .filter_map(|i| {
                        let j = i as isize + lag;
                        (0..n_taps as isize).contains(&j).then(|| taps[i] * taps[j as usize])
                    })
                    .sum::<f64>() as f32
            })
            .collect();
        Ok(Self {
            taps,
            kernel,
            samples: format.samples,
            extended: vec![0.0; format.samples + 2 * (n_taps - 1)],
        })
    }

    /// The FIR taps `b`.
    pub fn taps(&self) -> &[f64] {
        &self.taps
    }

    /// Filters one trace in place, zero phase, as `scipy.signal.filtfilt(b, [1.0], x)`
    /// (padtype `odd`, padlen `3 L`, initial conditions `lfilter_zi · edge value`).
    ///
    /// filtfilt extends `x` by `ext[-k] = 2 x[0] - x[k]`, `ext[n-1+k] = 2 x[n-1] - x[n-1-k]`
    /// (`k = 1..=3L`), filters forward `v[i] = Σ_j b[j] ext[i-j]`, backward
    /// `z[i] = Σ_j b[j] v[i+j]`, and keeps `i = 0..n`. For an FIR filter the initial conditions
    /// only stand for samples before the extension, and with `3L > L - 1` no kept sample reaches
    /// them, so the kept output is exactly
    ///
    /// `y[i] = Σ_{d=-(L-1)}^{L-1} r[d] ext[i+d]`,  `r[d] = Σ_j b[j] b[j+d]`,
    ///
    /// which needs only `L - 1` extended samples per side. Computed in f32 (kernel from f64).
    pub fn apply(&mut self, trace: &mut [f32]) -> Result<()> {
        check_len("band-pass trace", self.samples, trace.len())?;
        let n = trace.len();
        let pad = self.taps.len() - 1;
        let (first, last) = (trace[0], trace[n - 1]);
        let ext = &mut self.extended;
        for k in 1..=pad {
            ext[pad - k] = 2.0 * first - trace[k];
            ext[pad + n - 1 + k] = 2.0 * last - trace[n - 1 - k];
        }
        ext[pad..pad + n].copy_from_slice(trace);
        convolve_valid(&self.kernel, ext, trace);
        Ok(())
    }
}

/// `out[i] = Σ_d kernel[d] input[i + d]` over `i = 0..out.len()`
/// (`input.len() = out.len() + kernel.len() - 1`) for a kernel symmetric about its centre
/// `c` (odd length `2c + 1`, `kernel[c + d] = kernel[c - d]`; both filters here are), folded
/// so that each tap pair costs one multiply: `out[i] = k[c] in[i+c] + Σ_{d=1}^{c} k[c+d]
/// (in[i+c-d] + in[i+c+d])`. Axpy passes that vectorise; with AVX2 where the CPU has it.
pub(crate) fn convolve_valid(kernel: &[f32], input: &[f32], out: &mut [f32]) {
    debug_assert!(kernel.len() % 2 == 1);
    debug_assert!(
        (0..kernel.len() / 2).all(|d| kernel[d] == kernel[kernel.len() - 1 - d]),
        "kernel not symmetric"
    );
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2, checked just above.
        unsafe { convolve_valid_avx2(kernel, input, out) };
        return;
    }
    convolve_valid_portable(kernel, input, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn convolve_valid_avx2(kernel: &[f32], input: &[f32], out: &mut [f32]) {
    convolve_valid_portable(kernel, input, out);
}

#[inline(always)]
fn convolve_valid_portable(kernel: &[f32], input: &[f32], out: &mut [f32]) {
    let n = out.len();
    let c = kernel.len() / 2;
    let k0 = kernel[c];
    for (o, &x) in out.iter_mut().zip(&input[c..c + n]) {
        *o = k0 * x;
    }
    for d in 1..=c {
        let k = kernel[c + d];
        let (left, right) = (&input[c - d..c - d + n], &input[c + d..c + d + n]);
        for ((o, &l), &r) in out.iter_mut().zip(left).zip(right) {
            *o += k * (l + r);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// SEC gain

/// Spreading and Exponential Compensation gain (eq. 3.1) on the sample index, as the CMU-GPR
/// tools use it. Their per-site settings: NSH highbay a=0.015 b=0.01 threshold=100; NSH B level
/// a=0.06 b=0.5 threshold=80; NREC a=0.03 b=0 threshold=110; Gates garage a=0.03 b=0.7
/// threshold=80 (the default).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct SecGainParams {
    /// Exponential gain constant `a`, per sample (default 0.03).
    pub a: f64,
    /// Power (spreading) gain constant `b`, dimensionless, >= 0 (default 0.7).
    pub b: f64,
    /// Sample index after which the gain is held flat (default 80).
    pub threshold: usize,
}

impl Default for SecGainParams {
    fn default() -> Self {
        Self {
            a: 0.03,
            b: 0.7,
            threshold: 80,
        }
    }
}

impl SecGainParams {
    /// Checks `a` finite and `b` finite and >= 0 (`k^b` at `k = 0`).
    pub fn check(&self) -> params::Result {
        params::finite("sec_gain.a", self.a)?;
        params::non_negative("sec_gain.b", self.b)
    }
}

/// The precomputed SEC gain vector of one trace length (see [`SecGain::new`]).
#[derive(Clone, Debug)]
pub struct SecGain {
    gain: Vec<f32>,
}

impl SecGain {
    /// `G(k) = exp(a k) · k^b` for `k <= threshold`, `G(threshold)` for `k > threshold`,
    /// `k = 0..samples` (so `G(0) = 0` when `b > 0`, `1` when `b = 0`). Errors if `b < 0` or
    /// `a` is not finite, or a gain overflows f32.
    pub fn new(params: &SecGainParams, samples: usize) -> Result<Self> {
        params.check()?;
        let g = |k: usize| (params.a * k as f64).exp() * (k as f64).powf(params.b);
        let gain: Vec<f32> = (0..samples).map(|k| g(k.min(params.threshold)) as f32).collect();
        if let Some(k) = gain.iter().position(|v| !v.is_finite()) {
            return Err(param(
                "sec_gain.a",
                format!("gain at sample {k} overflows ({} per sample)", params.a),
            ));
        }
        Ok(Self { gain })
    }

    /// The gain per sample.
    pub fn gain(&self) -> &[f32] {
        &self.gain
    }

    /// `x[k] *= G(k)`.
    pub fn apply(&self, trace: &mut [f32]) -> Result<()> {
        check_len("SEC gain trace", self.gain.len(), trace.len())?;
        trace.iter_mut().zip(&self.gain).for_each(|(x, g)| *x *= g);
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Stacking

/// Stacking: the mean of `traces` consecutive traces.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct StackParams {
    /// Traces per stack, >= 1 (default 1: pass through).
    pub traces: usize,
}

impl Default for StackParams {
    fn default() -> Self {
        Self { traces: 1 }
    }
}

impl StackParams {
    /// Checks `traces >= 1`.
    pub fn check(&self) -> params::Result {
        params::at_least("stack.traces", self.traces, 1)
    }
}

/// Averages every `N` consecutive traces: `y = (1/N) Σ_{i=1}^{N} x_i` (sums in f64).
#[derive(Clone, Debug)]
pub struct Stacker {
    traces: usize,
    count: usize,
    sum: Vec<f64>,
    mean: Vec<f32>,
}

impl Stacker {
    /// Errors if `traces == 0`.
    pub fn new(params: &StackParams, samples: usize) -> Result<Self> {
        params.check()?;
        Ok(Self {
            traces: params.traces,
            count: 0,
            sum: vec![0.0; samples],
            mean: vec![0.0; samples],
        })
    }

    /// Adds a trace; returns the mean of the last `N` traces when this one completes them.
    pub fn push(&mut self, trace: &[f32]) -> Result<Option<&[f32]>> {
        check_len("stacked trace", self.sum.len(), trace.len())?;
        self.sum.iter_mut().zip(trace).for_each(|(s, &x)| *s += f64::from(x));
        self.count += 1;
        if self.count < self.traces {
            return Ok(None);
        }
        finish_mean(&mut self.sum, &mut self.count, &mut self.mean);
        Ok(Some(&self.mean))
    }

    /// Traces waiting in the current (incomplete) stack.
    pub fn pending(&self) -> usize {
        self.count
    }
}

fn finish_mean(sum: &mut [f64], count: &mut usize, mean: &mut [f32]) {
    let inv = 1.0 / *count as f64;
    mean.iter_mut().zip(sum.iter_mut()).for_each(|(m, s)| {
        *m = (*s * inv) as f32;
        *s = 0.0;
    });
    *count = 0;
}

/// Stacking by distance along track: the mean of the traces that fall in the same bin.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct DistanceStackParams {
    /// Bin width along track, m (> 0; default 0.015 m, the thesis's submap pixel).
    pub bin_m: f64,
}

impl Default for DistanceStackParams {
    fn default() -> Self {
        Self { bin_m: 0.015 }
    }
}

impl DistanceStackParams {
    /// Checks a positive, finite bin.
    pub fn check(&self) -> params::Result {
        params::positive("stack.bin_m", self.bin_m)
    }
}

/// A finished distance bin.
#[derive(Clone, Copy, Debug)]
pub struct DistanceStack<'a> {
    /// Bin index `floor(distance_m / bin_m)`.
    pub bin: i64,
    /// Mean of the traces of the bin.
    pub trace: &'a [f32],
    /// Number of traces averaged.
    pub traces: usize,
    /// Mean distance of the traces averaged, m.
    pub distance_m: f64,
}

/// Averages consecutive traces that share a distance bin; a bin is emitted when a trace of
/// another bin arrives (or on [`DistanceStacker::flush`]). A bin revisited later (the robot
/// reversing) starts a new stack.
#[derive(Clone, Debug)]
pub struct DistanceStacker {
    bin_m: f64,
    bin: i64,
    count: usize,
    distance_sum_m: f64,
    sum: Vec<f64>,
    mean: Vec<f32>,
}

impl DistanceStacker {
    /// Errors unless `bin_m` is positive and finite.
    pub fn new(params: &DistanceStackParams, samples: usize) -> Result<Self> {
        params.check()?;
        Ok(Self {
            bin_m: params.bin_m,
            bin: 0,
            count: 0,
            distance_sum_m: 0.0,
            sum: vec![0.0; samples],
            mean: vec![0.0; samples],
        })
    }

    /// Adds a trace taken at `distance_m`; returns the previous bin's mean when this trace
    /// opens a new bin.
    pub fn push(&mut self, trace: &[f32], distance_m: f64) -> Result<Option<DistanceStack<'_>>> {
        check_len("stacked trace", self.sum.len(), trace.len())?;
        if !distance_m.is_finite() {
            return Err(Error::NonFinite {
                what: "stack distance_m".to_owned(),
                index: 0,
                value: distance_m,
            });
        }
        let bin = (distance_m / self.bin_m).floor() as i64;
        let mut finished = None;
        if self.count > 0 && bin != self.bin {
            finished = Some((self.bin, self.count, self.distance_sum_m / self.count as f64));
            finish_mean(&mut self.sum, &mut self.count, &mut self.mean);
            self.distance_sum_m = 0.0;
        }
        // The finished mean stays in `mean` while the new bin accumulates in `sum`.
        self.bin = bin;
        self.count += 1;
        self.distance_sum_m += distance_m;
        self.sum.iter_mut().zip(trace).for_each(|(s, &x)| *s += f64::from(x));
        Ok(finished.map(|(bin, traces, distance_m)| DistanceStack {
            bin,
            trace: &self.mean,
            traces,
            distance_m,
        }))
    }

    /// Emits the current bin, if any traces are waiting.
    pub fn flush(&mut self) -> Option<DistanceStack<'_>> {
        if self.count == 0 {
            return None;
        }
        let (bin, traces, distance_m) = (self.bin, self.count, self.distance_sum_m / self.count as f64);
        finish_mean(&mut self.sum, &mut self.count, &mut self.mean);
        self.distance_sum_m = 0.0;
        Some(DistanceStack {
            bin,
            trace: &self.mean,
            traces,
            distance_m,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TIGHT: f64 = 1e-12;

    #[test]
    fn firwin_has_unit_gain_at_the_passband_centre() {
        let fs = 5e9;
        let b = firwin_bandpass(31, 250e6, 1e9, fs).expect("valid");
        let centre_hz = 0.5 * (250e6 + 1e9);
        let alpha = 15.0;
        let (re, im) = b.iter().enumerate().fold((0.0, 0.0), |(re, im), (k, v)| {
            let phase = 2.0 * std::f64::consts::PI * centre_hz / fs * (k as f64 - alpha);
            (re + v * phase.cos(), im - v * phase.sin())
        });
        assert!((re - 1.0).abs() < TIGHT && im.abs() < TIGHT, "gain {re} + {im}i");
        // Linear phase: symmetric taps.
        for k in 0..31 {
            assert!((b[k] - b[30 - k]).abs() < TIGHT);
        }
    }

    #[test]
    fn firwin_refuses_bad_cutoffs_and_even_taps() {
        assert!(firwin_bandpass(30, 250e6, 1e9, 5e9).is_err());
        assert!(firwin_bandpass(31, 1e9, 250e6, 5e9).is_err());
        assert!(firwin_bandpass(31, 250e6, 2.5e9, 5e9).is_err());
        assert!(firwin_bandpass(31, 0.0, 1e9, 5e9).is_err());
    }

    #[test]
    fn sec_gain_is_flat_after_the_threshold() {
        let params = SecGainParams {
            a: 0.06,
            b: 0.5,
            threshold: 80,
        };
        let g = SecGain::new(&params, 201).expect("valid");
        let g80 = ((0.06_f64 * 80.0).exp() * 80.0_f64.sqrt()) as f32;
        assert_eq!(g.gain()[0], 0.0);
        assert_eq!(g.gain()[80], g80);
        assert!(g.gain()[81..].iter().all(|&v| v == g80));
        assert!(g.gain()[..=80].windows(2).all(|w| w[0] < w[1]));
        let flat = SecGain::new(&SecGainParams { b: 0.0, ..params }, 3).expect("valid");
        assert_eq!(flat.gain()[0], 1.0);
    }

    #[test]
    fn zero_time_finds_the_first_negative_peak() {
        let mut t = vec![0.0_f32; 40];
        t[3] = -0.2; // precursor, below threshold
        t[10] = -0.6;
        t[11] = -0.9; // the peak of the first lobe below -0.5
        t[12] = -0.7;
        t[20] = -1.0; // a later, stronger negative peak
        t[25] = 0.8;
        let p = ZeroTimeParams::default();
        assert_eq!(zero_time_index(&t, &p), Some(11));
        shift_to_zero_time(&mut t, 11);
        assert_eq!(t[0], -0.9);
        assert_eq!(t[9], -1.0);
        assert!(t[29..].iter().all(|&v| v == 0.0));
        assert_eq!(zero_time_index(&[0.0; 5], &p), None);
        assert_eq!(zero_time_index(&[1.0, 0.2, 0.3], &p), None);
    }

    #[test]
    fn dewow_window_is_one_period_odd() {
        let f = TraceFormat::new(201, 0.2, 500e6);
        let d = Dewow::new(&DewowParams::default(), &f).expect("valid");
        assert_eq!(d.window_samples(), 11);
        let short = DewowParams { window_periods: 0.1 };
        assert!(Dewow::new(&short, &f).is_err());
    }

    #[test]
    fn stackers_average() {
        let mut s = Stacker::new(&StackParams { traces: 2 }, 2).expect("valid");
        assert!(s.push(&[1.0, 2.0]).expect("len").is_none());
        assert_eq!(s.push(&[3.0, 6.0]).expect("len"), Some(&[2.0_f32, 4.0][..]));
        assert_eq!(s.pending(), 0);
        let mut d = DistanceStacker::new(&DistanceStackParams { bin_m: 0.1 }, 1).expect("valid");
        assert!(d.push(&[1.0], 0.01).expect("ok").is_none());
        assert!(d.push(&[3.0], 0.05).expect("ok").is_none());
        let done = d.push(&[7.0], 0.15).expect("ok").expect("bin 0 done");
        assert_eq!((done.bin, done.traces, done.trace[0]), (0, 2, 2.0));
        assert!((done.distance_m - 0.03).abs() < TIGHT);
        let last = d.flush().expect("bin 1");
        assert_eq!((last.bin, last.traces, last.trace[0]), (1, 1, 7.0));
        assert!(d.flush().is_none());
    }

    #[test]
    fn reflect_index_is_half_sample_symmetric() {
        let got: Vec<usize> = (-5..9).map(|i| reflect_index(i, 3)).collect();
        assert_eq!(got, [1, 2, 2, 1, 0, 0, 1, 2, 2, 1, 0, 0, 1, 2]);
    }
}
