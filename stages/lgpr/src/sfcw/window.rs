//! The Dolph-Chebyshev window over the tones of a sweep (seed 001 §2.1.3: "a Chebyshev window
//! with 45-dB attenuation").

use std::f64::consts::PI;

use crate::error::Result;

/// Largest side-lobe attenuation accepted, dB (beyond it `10^(dB/20)` leaves `f64` range
/// for the Chebyshev polynomial of long windows).
pub const MAX_WINDOW_ATTENUATION_DB: f64 = 300.0;

/// Longest window computed (its cost grows as the square of the length).
pub const MAX_WINDOW_LEN: usize = 4096;

/// Chebyshev polynomial of the first kind, `T_n(x)`, for any real `x`:
/// `cos(n acos x)` on `|x| <= 1`, `sign(x)^n cosh(n acosh |x|)` outside.
fn chebyshev_polynomial(order: f64, parity_odd: bool, x: f64) -> f64 {
    if x.abs() <= 1.0 {
        (order * x.acos()).cos()
    } else {
        let magnitude = (order * x.abs().acosh()).cosh();
        if x < 0.0 && parity_odd { -magnitude } else { magnitude }
    }
}

/// The symmetric Dolph-Chebyshev window of `len` taps whose side lobes all lie
/// `attenuation_db` below the main lobe, normalised to a largest tap of 1 (the definition of
/// `scipy.signal.windows.chebwin(len, attenuation_db, sym=True)`).
///
/// With `n = len - 1` and `x0 = cosh(acosh(10^(A/20)) / n)`, the window's spectrum at the `len`
/// frequencies `k / len` is `T_n(x0 cos(pi k / len))`; the taps are its inverse DFT centred on
/// the middle tap:
/// `w[i] ∝ sum_k T_n(x0 cos(pi k / len)) cos(2 pi k (i - n/2) / len)`, `i = 0..len`
/// (for even `len` the centre `n/2` falls between two taps: the half-sample shift).
/// Costs `O(len^2)`, once at start-up.
///
/// Errors: `len` not in `1..=MAX_WINDOW_LEN` (key `bin_count`), or `attenuation_db` not in
/// `(0, MAX_WINDOW_ATTENUATION_DB]` (key `window_attenuation_db`).
pub fn chebyshev_window(len: usize, attenuation_db: f64) -> Result<Vec<f64>> {
    if !(attenuation_db > 0.0 && attenuation_db <= MAX_WINDOW_ATTENUATION_DB) {
        return Err(crate::error::param(
            "window_attenuation_db",
            format!("must be in (0, {MAX_WINDOW_ATTENUATION_DB}] dB, got {attenuation_db}"),
        ));
    }
    if !(1..=MAX_WINDOW_LEN).contains(&len) {
        return Err(crate::error::param(
            "bin_count",
            format!("the window over the tones needs 1..={MAX_WINDOW_LEN} taps, got {len}"),
        ));
    }
    match len {
        1 => Ok(vec![1.0]),
        _ => {
            let size = len as f64;
            let order = size - 1.0;
            let parity_odd = (len - 1) % 2 == 1;
            let ripple = 10f64.powf(attenuation_db / 20.0);
            let x0 = (ripple.acosh() / order).cosh();
            let spectrum: Vec<f64> = (0..len)
                .map(|k| chebyshev_polynomial(order, parity_odd, x0 * (PI * k as f64 / size).cos()))
                .collect();
            let centre = order / 2.0;
            let mut taps: Vec<f64> = (0..len)
                .map(|i| {
                    let offset = i as f64 - centre;
                    spectrum
                        .iter()
                        .enumerate()
                        .map(|(k, p)| p * (2.0 * PI * k as f64 * offset / size).cos())
                        .sum()
                })
                .collect();
            let peak = taps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            taps.iter_mut().for_each(|w| *w /= peak);
            Ok(taps)
        }
    }
}
