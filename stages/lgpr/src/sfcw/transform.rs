//! The complex-to-real inverse transform of a sweep's tones to real time samples.

use std::f64::consts::TAU;
use std::sync::Arc;

use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use crate::error::{Error, Result};

/// Largest inverse-transform length accepted (`time_samples`).
pub const MAX_TIME_SAMPLES: usize = 1 << 20;

/// The inverse transform of `bins` tones at `f_m = f0 + m df` to `time_samples` (N) real
/// samples `dt = 1 / (N df)` apart, of which the first `keep_samples` are kept:
///
/// `x_n = Re( sum_m S_m exp(j 2 pi f_m n dt) ) = Re( exp(j 2 pi f0 n dt) * Y_n )`,
/// `Y_n = sum_{m<bins} S_m exp(j 2 pi m n / N)` (the unnormalised N-point inverse DFT of the
/// tones zero-padded to N).
///
/// No scale is applied here: a tone `S_m = a` alone gives a cosine of amplitude `|a|`. The
/// chain puts its scale in the window (taps summing to 1).
///
/// `f0` need not be a multiple of `df` (the LGPR: 100 MHz in 6 MHz steps), hence the phase
/// ramp `exp(j 2 pi f0 n dt)` rather than a shift of the tones by whole bins. The FFT plan,
/// the ramp and the buffers are made once; [`InverseTransform::process`] allocates nothing.
pub struct InverseTransform {
    bins: usize,
    time_samples: usize,
    sample_interval_ns: f64,
    fft: Arc<dyn Fft<f64>>,
    /// `exp(j 2 pi f0 n dt)` for the kept samples.
    ramp: Vec<Complex64>,
    buffer: Vec<Complex64>,
    scratch: Vec<Complex64>,
}

impl std::fmt::Debug for InverseTransform {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InverseTransform")
            .field("bins", &self.bins)
            .field("time_samples", &self.time_samples)
            .field("keep_samples", &self.ramp.len())
            .field("sample_interval_ns", &self.sample_interval_ns)
            .finish_non_exhaustive()
    }
}

impl InverseTransform {
    /// The transform of `bins` tones from `start_frequency_hz` in steps of `frequency_step_hz`
    /// to `time_samples` samples, keeping the first `keep_samples`.
    ///
    /// Errors (`Param`, naming the key): `bins == 0`, a start frequency that is not finite or
    /// negative, a step that is not finite and positive, `time_samples` below `bins` or above
    /// [`MAX_TIME_SAMPLES`], `keep_samples` not in `1..=time_samples`.
    pub fn new(
        bins: usize,
        start_frequency_hz: f64,
        frequency_step_hz: f64,
        time_samples: usize,
        keep_samples: usize,
    ) -> Result<Self> {
        let param = |key, message: String| Err(crate::error::param(key, message));
        if bins == 0 {
            return param("bin_count", "a sweep needs at least one tone".into());
        }
        if !(start_frequency_hz.is_finite() && start_frequency_hz >= 0.0) {
            return param(
                "start_frequency_hz",
                format!("must be finite and >= 0, got {start_frequency_hz}"),
            );
        }
        if !(frequency_step_hz.is_finite() && frequency_step_hz > 0.0) {
            return param(
                "frequency_step_hz",
                format!("must be finite and > 0, got {frequency_step_hz}"),
            );
        }
        if !(bins..=MAX_TIME_SAMPLES).contains(&time_samples) {
            return param(
                "time_samples",
                format!("must be in {bins}..={MAX_TIME_SAMPLES} (at least the tone count), got {time_samples}"),
            );
        }
        if !(1..=time_samples).contains(&keep_samples) {
            return param(
                "keep_samples",
                format!("must be in 1..={time_samples}, got {keep_samples}"),
            );
        }
        let n = time_samples as f64;
        let start_in_steps = start_frequency_hz / frequency_step_hz;
        // f0 n dt = (f0 / df) n / N cycles; only its fraction matters
        let ramp = (0..keep_samples)
            .map(|k| Complex64::from_polar(1.0, TAU * (start_in_steps * k as f64 / n).fract()))
            .collect();
        let fft = FftPlanner::new().plan_fft_inverse(time_samples);
        let scratch = vec![Complex64::default(); fft.get_inplace_scratch_len()];
        Ok(Self {
            bins,
            time_samples,
            sample_interval_ns: 1e9 / (n * frequency_step_hz),
            fft,
            ramp,
            buffer: vec![Complex64::default(); time_samples],
            scratch,
        })
    }

    /// Number of tones in.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// Inverse-transform length N.
    pub fn time_samples(&self) -> usize {
        self.time_samples
    }

    /// Number of samples out (the first ones of the N).
    pub fn keep_samples(&self) -> usize {
        self.ramp.len()
    }

    /// Time between samples, `dt = 1 / (N df)`, ns.
    pub fn sample_interval_ns(&self) -> f64 {
        self.sample_interval_ns
    }

    /// `x_n` for `n < keep_samples` of one channel's `bins` tones into `out`.
    pub fn process(&mut self, spectrum: &[Complex64], out: &mut [f64]) -> Result<()> {
        if spectrum.len() != self.bins {
            return Err(Error::Size {
                what: "spectrum",
                expected: self.bins,
                got: spectrum.len(),
            });
        }
        if out.len() != self.ramp.len() {
            return Err(Error::Size {
                what: "time samples",
                expected: self.ramp.len(),
                got: out.len(),
            });
        }
        let (tones, padding) = self.buffer.split_at_mut(self.bins);
        tones.copy_from_slice(spectrum);
        padding.fill(Complex64::default());
        self.fft.process_with_scratch(&mut self.buffer, &mut self.scratch);
        for ((x, y), r) in out.iter_mut().zip(&self.buffer).zip(&self.ramp) {
            *x = r.re * y.re - r.im * y.im;
        }
        Ok(())
    }
}
