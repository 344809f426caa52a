//! Self calibration (eq. 2) and factory calibration (eq. 3-4) of SFCW tones.
//!
//! Tones arrive as `f32` pairs `(re, im)`, channel-major: tone `m` of channel `ch` is
//! `values[(ch * bins + m) * 2 ..][..2]`; the calibration channel is `bins` such pairs.

use rustfft::num_complex::Complex64;

use super::MIN_DIVISOR_MAGNITUDE;
use crate::error::{Error, Result, ToneIndex};

/// Checks that `data` holds `channels x bins` finite complex tones (`channels = None`: the
/// calibration channel, `bins` tones).
pub(crate) fn check_tones(what: &'static str, data: &[f32], channels: Option<usize>, bins: usize) -> Result<()> {
    let expected = channels.unwrap_or(1).saturating_mul(bins).saturating_mul(2);
    if data.len() != expected {
        return Err(Error::Size {
            what,
            expected,
            got: data.len(),
        });
    }
    let bins = bins.max(1);
    match data
        .chunks_exact(2)
        .position(|z| !(z[0].is_finite() && z[1].is_finite()))
    {
        None => Ok(()),
        Some(k) => Err(Error::NonFinite {
            what,
            at: ToneIndex {
                channel: channels.map(|_| k / bins),
                tone: k % bins,
            },
            re: f64::from(data[2 * k]),
            im: f64::from(data[2 * k + 1]),
        }),
    }
}

/// `1 / z`, or the error naming `at` when `|z| < MIN_DIVISOR_MAGNITUDE`.
pub(crate) fn checked_inverse(what: &'static str, z: Complex64, at: ToneIndex) -> Result<Complex64> {
    let magnitude = z.norm();
    if magnitude < MIN_DIVISOR_MAGNITUDE {
        return Err(Error::ZeroDivisor { what, at, magnitude });
    }
    Ok(z.inv())
}

/// The complex tone at pair index `k` of an interleaved `(re, im)` slice.
pub(crate) fn tone(data: &[f32], k: usize) -> Complex64 {
    Complex64::new(f64::from(data[2 * k]), f64::from(data[2 * k + 1]))
}

/// `1 / S_cal` per tone of a calibration channel (`bins` interleaved tones) into `out`,
/// after checking its length, finiteness and that no tone is ~0.
pub(crate) fn inverse_calibration(what: &'static str, calibration: &[f32], out: &mut [Complex64]) -> Result<()> {
    check_tones(what, calibration, None, out.len())?;
    for (m, inv) in out.iter_mut().enumerate() {
        let at = ToneIndex { channel: None, tone: m };
        *inv = checked_inverse(what, tone(calibration, m), at)?;
    }
    Ok(())
}

/// Self calibration, eq. 2: `S_hat[ch][m] = S_ant[ch][m] / S_cal[m]` for every channel `ch`
/// and tone `m` of one sweep, written channel-major into `out` (`channels x bins`).
///
/// `values` is `channels x bins` interleaved tones, `calibration` `bins` interleaved tones.
/// Errors: wrong lengths, a non-finite tone (named by channel and tone), a calibration tone
/// with magnitude below [`MIN_DIVISOR_MAGNITUDE`].
pub fn self_calibrate(
    values: &[f32],
    calibration: &[f32],
    channels: usize,
    bins: usize,
    out: &mut [Complex64],
) -> Result<()> {
    let count = channels.saturating_mul(bins);
    if out.len() != count {
        return Err(Error::Size {
            what: "self-calibrated output",
            expected: count,
            got: out.len(),
        });
    }
    check_tones("values", values, Some(channels), bins)?;
    let mut inverse = vec![Complex64::default(); bins];
    inverse_calibration("calibration", calibration, &mut inverse)?;
    for (k, s) in out.iter_mut().enumerate() {
        *s = tone(values, k) * inverse[k % bins];
    }
    Ok(())
}

/// The one-off factory calibration of the array (anechoic chamber, no ground), reduced once
/// to the ratio of eq. 3 per channel and tone:
/// `S_hat_factorycal[ch][m] = S_factorycal[ch][m] / S_factorycal_cal[m]`.
#[derive(Debug, Clone, PartialEq)]
pub struct FactoryCalibration {
    channels: usize,
    bins: usize,
    /// Eq. 3 per channel and tone, channel-major.
    ratio: Vec<Complex64>,
}

impl FactoryCalibration {
    /// Eq. 3 from the factory sweep: `values` (`channels x bins` interleaved tones) and its
    /// calibration channel (`bins` interleaved tones).
    ///
    /// Errors: wrong lengths, a non-finite tone, a calibration tone or a resulting ratio with
    /// magnitude below [`MIN_DIVISOR_MAGNITUDE`] (eq. 4 divides by it).
    pub fn new(values: &[f32], calibration: &[f32], channels: usize, bins: usize) -> Result<Self> {
        // the lengths first: they bound what is allocated
        check_tones("factory values", values, Some(channels), bins)?;
        let mut ratio = vec![Complex64::default(); channels * bins];
        let mut inverse = vec![Complex64::default(); bins];
        inverse_calibration("factory calibration", calibration, &mut inverse)?;
        for (k, r) in ratio.iter_mut().enumerate() {
            *r = tone(values, k) * inverse[k % bins];
            let at = ToneIndex {
                channel: Some(k / bins),
                tone: k % bins,
            };
            checked_inverse("factory ratio (eq. 3)", *r, at)?;
        }
        Ok(Self { channels, bins, ratio })
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Number of tones per channel.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// Eq. 3 per channel and tone, channel-major (`channels x bins`).
    pub fn ratio(&self) -> &[Complex64] {
        &self.ratio
    }

    /// Factory calibration, eq. 4, in place on self-calibrated tones (eq. 2, `channels x
    /// bins`, channel-major): `S_hathat = S_hat / S_hat_factorycal - 1`.
    pub fn apply(&self, self_calibrated: &mut [Complex64]) -> Result<()> {
        if self_calibrated.len() != self.ratio.len() {
            return Err(Error::Size {
                what: "self-calibrated tones",
                expected: self.ratio.len(),
                got: self_calibrated.len(),
            });
        }
        for (s, r) in self_calibrated.iter_mut().zip(&self.ratio) {
            *s = *s / *r - 1.0;
        }
        Ok(())
    }
}
