//! The SFCW processing of one LGPR sweep (seed 001 §2.1.3, eq. 2-7), from the complex tones of
//! every channel to real range samples:
//!
//! 1. self calibration, eq. 2: `S_hat = S_ant / S_cal` ([`self_calibrate`]);
//! 2. factory calibration, eq. 3-4: `S_hathat = S_hat / S_hat_factorycal - 1`
//!    ([`FactoryCalibration`]);
//! 3. the delay: `* exp(-j 2 pi f tau)`, `tau = 8 ns`, so that the part of the pulse before
//!    time zero does not wrap to the end of the record ([`tone_weights`]);
//! 4. the Dolph-Chebyshev window, 45 dB side lobes ([`chebyshev_window`]), scaled so its taps
//!    sum to 1 ([`tone_weights`]);
//! 5. the complex-to-real inverse transform to N = 1024 samples `dt = 1 / (N df)` apart
//!    ([`InverseTransform`]);
//! 6. the distance-based IIR high-pass, eq. 5-7 ([`DistanceHighPass`]);
//! 7. the fixed range gain ([`RangeGain`]) and the crop to the first `keep_samples`.
//!
//! [`SfcwChain`] runs them all with everything precomputed: steps 2-4 fold into one complex
//! coefficient per channel and tone, so a sweep costs one complex multiply-add per tone, one
//! N-point FFT per channel and a few operations per kept sample; nothing is allocated per
//! sweep. The steps are public for tests and for looking at intermediate results.
//!
//! Scaling: with the window's taps summing to 1, a point reflector whose calibrated response
//! is `a exp(-j 2 pi f t_r)` at every tone gives a pulse peaking at `a` at `t = t_r + tau`
//! (before the high-pass and the gain). The output is in units of the factory-calibrated
//! response (eq. 4: relative to the element's direct coupling), or of the self-calibrated one
//! without a factory calibration.
//!
//! Layout: tones arrive as `f32` pairs `(re, im)`, channel-major (`values[(ch * bins + m) * 2
//! + {0, 1}]`), the calibration channel as `bins` pairs; range samples leave channel-major,
//! `out[ch * out_samples + n]`.

mod calibration;
mod high_pass;
mod range_gain;
mod transform;
mod window;

use std::f64::consts::TAU;

use rustfft::num_complex::Complex64;
use serde::Deserialize;

pub use self::calibration::{FactoryCalibration, self_calibrate};
pub use self::high_pass::DistanceHighPass;
pub use self::range_gain::{RangeGain, RangeGainParams};
pub use self::transform::{InverseTransform, MAX_TIME_SAMPLES};
pub use self::window::{MAX_WINDOW_ATTENUATION_DB, MAX_WINDOW_LEN, chebyshev_window};
use crate::error::{Error, Result};

/// Smallest magnitude divided by (a calibration tone, a factory ratio of eq. 3); below it the
/// division is an error rather than a huge or non-finite result.
pub const MIN_DIVISOR_MAGNITUDE: f64 = 1e-12;

/// Most channels per sweep accepted by [`SfcwChain::new`].
pub const MAX_CHANNELS: usize = 1024;

/// Parameters of the SFCW chain, parsed once at start-up.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct SfcwParams {
    /// The delay `tau` applied before the inverse transform, ns; time zero (the antenna) lands
    /// at sample `tau / dt`. Default 8 ns (seed 001).
    pub delay_ns: f64,
    /// Side-lobe attenuation of the Chebyshev window over the tones, dB. Default 45 dB
    /// (seed 001).
    pub window_attenuation_db: f64,
    /// Length N of the inverse transform, samples; `dt = 1 / (N df)`. Default 1024 (seed 001:
    /// 0.163 ns with 6 MHz steps, a 167 ns record).
    pub time_samples: usize,
    /// Samples kept from the start of each channel's record, samples (`1..=time_samples`).
    /// Default 369, the depth of the paper's data product: 60 ns, i.e. 52 ns of two-way time
    /// after the 8 ns delay, 2.6 m at 0.1 m/ns, the LGPR's 2-3 m penetration; the rest of the
    /// record is below the noise.
    pub keep_samples: usize,
    /// Half-life distance `d_iir` of the IIR high-pass (eq. 7), m. Default 5 m (seed 001).
    pub iir_distance_m: f64,
    /// The range gain (spreading and attenuation compensation).
    pub range_gain: RangeGainParams,
}

impl Default for SfcwParams {
    fn default() -> Self {
        Self {
            delay_ns: 8.0,
            window_attenuation_db: 45.0,
            time_samples: 1024,
            keep_samples: 369,
            iir_distance_m: 5.0,
            range_gain: RangeGainParams::default(),
        }
    }
}

/// Steps 3-4 as one weight per tone: `w_m / sum_k w_k * exp(-j 2 pi f_m tau)`, `f_m = f0 + m df`,
/// `w` the Chebyshev window of `window_attenuation_db` ([`chebyshev_window`]), `tau = delay_ns`.
/// Multiplying calibrated tones by these gives the delayed, windowed spectrum.
///
/// Errors (`Param`): a non-finite delay (`delay_ns`), a bad window attenuation, `bins == 0`.
pub fn tone_weights(
    bins: usize,
    start_frequency_hz: f64,
    frequency_step_hz: f64,
    params: &SfcwParams,
) -> Result<Vec<Complex64>> {
    gprflow_params::finite("delay_ns", params.delay_ns)?;
    let window = chebyshev_window(bins, params.window_attenuation_db)?;
    let sum: f64 = window.iter().sum();
    let delay_s = params.delay_ns * 1e-9;
    Ok(window
        .iter()
        .enumerate()
        .map(|(m, w)| {
            let f_hz = start_frequency_hz + m as f64 * frequency_step_hz;
            // exp(-j 2 pi f tau), reduced to a fraction of a cycle first
            Complex64::from_polar(w / sum, -TAU * (f_hz * delay_s).fract())
        })
        .collect())
}

/// The whole chain for sweeps of `channels x bins` tones, with its high-pass state.
#[derive(Debug)]
pub struct SfcwChain {
    params: SfcwParams,
    channels: usize,
    bins: usize,
    /// Per channel and tone: the weight of steps 3-4 divided by the factory ratio of eq. 3
    /// (or the weight alone without a factory calibration).
    coefficients: Vec<Complex64>,
    /// Per tone: the weight again, times the `- 1` of eq. 4 (empty without a factory
    /// calibration).
    offsets: Vec<Complex64>,
    inverse_calibration: Vec<Complex64>,
    spectrum: Vec<Complex64>,
    transform: InverseTransform,
    time: Vec<f64>,
    high_pass: DistanceHighPass,
    gain: RangeGain,
    sweeps: u64,
}

impl SfcwChain {
    /// The chain for sweeps of `channels` channels of `bins` tones from `start_frequency_hz`
    /// in steps of `frequency_step_hz`, with the factory calibration if there is one (without,
    /// eq. 4 is skipped: the output is relative to the calibration channel only).
    ///
    /// Errors (`Param`, naming the key): any parameter out of range, `channels` not in
    /// `1..=MAX_CHANNELS`, more tones than [`MAX_WINDOW_LEN`], a
    /// factory calibration of another shape (`factory`).
    pub fn new(
        params: SfcwParams,
        channels: usize,
        bins: usize,
        start_frequency_hz: f64,
        frequency_step_hz: f64,
        factory: Option<FactoryCalibration>,
    ) -> Result<Self> {
        if !(1..=MAX_CHANNELS).contains(&channels) {
            return Err(crate::error::param(
                "channel_count",
                format!("a sweep needs 1..={MAX_CHANNELS} channels, got {channels}"),
            ));
        }
        let transform = InverseTransform::new(
            bins,
            start_frequency_hz,
            frequency_step_hz,
            params.time_samples,
            params.keep_samples,
        )?;
        let weights = tone_weights(bins, start_frequency_hz, frequency_step_hz, &params)?;
        let (coefficients, offsets) = match &factory {
            Some(f) if (f.channels(), f.bins()) != (channels, bins) => {
                return Err(crate::error::param(
                    "factory",
                    format!(
                        "the factory calibration has {} channels x {} tones, the sweeps {channels} x {bins}",
                        f.channels(),
                        f.bins()
                    ),
                ));
            }
            Some(f) => (
                f.ratio()
                    .iter()
                    .enumerate()
                    .map(|(k, r)| weights[k % bins] / r)
                    .collect(),
                weights,
            ),
            None => (weights.repeat(channels), Vec::new()),
        };
        let keep = params.keep_samples;
        let high_pass = DistanceHighPass::new(channels * keep, params.iir_distance_m)?;
        let gain = RangeGain::new(
            &params.range_gain,
            params.delay_ns,
            transform.sample_interval_ns(),
            keep,
        )?;
        Ok(Self {
            params,
            channels,
            bins,
            coefficients,
            offsets,
            inverse_calibration: vec![Complex64::default(); bins],
            spectrum: vec![Complex64::default(); bins],
            transform,
            time: vec![0.0; channels * keep],
            high_pass,
            gain,
            sweeps: 0,
        })
    }

    /// The parameters the chain was built with.
    pub fn params(&self) -> &SfcwParams {
        &self.params
    }

    /// Channels per sweep.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Tones per channel in.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// Range samples per channel out (`keep_samples`).
    pub fn out_samples(&self) -> usize {
        self.params.keep_samples
    }

    /// Time between range samples, `1 / (N df)`, ns.
    pub fn sample_interval_ns(&self) -> f64 {
        self.transform.sample_interval_ns()
    }

    /// Time of the antenna's zero (the delay) in the output record, ns.
    pub fn time_zero_ns(&self) -> f64 {
        self.params.delay_ns
    }

    /// Sweeps processed since creation or [`reset`](Self::reset).
    pub fn sweeps(&self) -> u64 {
        self.sweeps
    }

    /// Restarts the high-pass: the next sweep is treated as the first (a new run, or a gap in
    /// the data).
    pub fn reset(&mut self) {
        self.high_pass.reset();
        self.sweeps = 0;
    }

    /// One sweep: `values` (`channels x bins` interleaved tones), its `calibration` channel
    /// (`bins` interleaved tones) and the along-track distance since the previous sweep
    /// (`d_i` of eq. 7, m; ignored for the first) into `out` (`channels x out_samples`,
    /// channel-major).
    ///
    /// Errors: wrong lengths; a non-finite tone (channel and tone named); a calibration tone
    /// below [`MIN_DIVISOR_MAGNITUDE`]; a negative or non-finite distance (sweep named). These
    /// leave the chain unchanged. `Overflow` (an output beyond `f32`, only for inputs near the
    /// `f32` range) comes after the high-pass has taken the sweep in.
    pub fn process(
        &mut self,
        values: &[f32],
        calibration: &[f32],
        distance_since_last_m: f64,
        out: &mut [f32],
    ) -> Result<()> {
        let keep = self.params.keep_samples;
        if out.len() != self.time.len() {
            return Err(Error::Size {
                what: "out",
                expected: self.time.len(),
                got: out.len(),
            });
        }
        calibration::check_tones("values", values, Some(self.channels), self.bins)?;
        calibration::inverse_calibration("calibration", calibration, &mut self.inverse_calibration)?;
        self.high_pass.check_distance(distance_since_last_m)?;

        for (ch, time) in self.time.chunks_exact_mut(keep).enumerate() {
            let first = ch * self.bins;
            let coefficients = &self.coefficients[first..first + self.bins];
            for (m, s) in self.spectrum.iter_mut().enumerate() {
                *s = coefficients[m] * calibration::tone(values, first + m) * self.inverse_calibration[m];
            }
            for (s, o) in self.spectrum.iter_mut().zip(&self.offsets) {
                *s -= o;
            }
            self.transform.process(&self.spectrum, time)?;
        }
        self.high_pass.apply(&mut self.time, distance_since_last_m)?;

        let sweep = self.sweeps;
        self.sweeps += 1;
        let gains = self.gain.gains();
        for (ch, (time, out)) in self.time.chunks_exact(keep).zip(out.chunks_exact_mut(keep)).enumerate() {
            for (n, ((o, x), g)) in out.iter_mut().zip(time).zip(gains).enumerate() {
                let value = x * g;
                *o = value as f32;
                if !o.is_finite() {
                    return Err(Error::Overflow {
                        sweep,
                        channel: ch,
                        sample: n,
                        value,
                    });
                }
            }
        }
        Ok(())
    }
}
