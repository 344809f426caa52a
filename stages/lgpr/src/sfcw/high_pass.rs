//! The distance-based IIR high-pass along track (seed 001 eq. 5-7): a running mean per range
//! sample whose memory halves every `d_iir` metres travelled, subtracted from each sweep.

use crate::error::{Error, Result};

/// The mean-removal filter of eq. 5-7 over sweeps of `len` samples (all channels of a sweep
/// side by side):
///
/// - eq. 7: `beta = 2^(-d_i / d_iir)`, `d_i` the along-track distance since the previous sweep;
/// - eq. 5: `M_i = beta M_{i-1} + (1 - beta) C_i`;
/// - eq. 6: `C_i,mr = C_i - M_i`.
///
/// Start: `M_0 = C_0` (the first sweep's own values, so its output is zero). The filter exists
/// to remove the ground bounce and internal reflections, which are present from the first
/// sweep on; starting from `M_0 = 0` would pass them at full strength and let them decay only
/// over the first ~5 m (a half-life), a transient as long as a submap. With `M_0 = C_0` the
/// output is the change since the first sweep from the start; the price is that a feature
/// under the array at the first sweep is subtracted (it reappears, inverted, as it leaves).
///
/// A vehicle at rest (`d_i = 0`) gives `beta = 1`: the mean holds and the output is the change
/// since it stopped.
#[derive(Debug, Clone, PartialEq)]
pub struct DistanceHighPass {
    half_distance_m: f64,
    mean: Vec<f64>,
    sweeps: u64,
}

impl DistanceHighPass {
    /// A filter for sweeps of `len` samples with half-life `half_distance_m` (`d_iir`).
    ///
    /// Errors: `half_distance_m` not finite and positive (key `iir_distance_m`).
    pub fn new(len: usize, half_distance_m: f64) -> Result<Self> {
        gprflow_params::positive("iir_distance_m", half_distance_m)?;
        Ok(Self {
            half_distance_m,
            mean: vec![0.0; len],
            sweeps: 0,
        })
    }

    /// Eq. 7: the decay `beta` over `distance_m` travelled.
    pub fn decay(&self, distance_m: f64) -> f64 {
        (-distance_m / self.half_distance_m).exp2()
    }

    /// Sweeps seen since creation or [`reset`](Self::reset).
    pub fn sweeps(&self) -> u64 {
        self.sweeps
    }

    /// The running mean `M_i` after the last sweep.
    pub fn running_mean(&self) -> &[f64] {
        &self.mean
    }

    /// Forgets the running mean: the next sweep starts the filter again (`M_0 = C_0`).
    pub fn reset(&mut self) {
        self.sweeps = 0;
    }

    /// Checks `distance_since_last_m` for the next sweep (what [`apply`](Self::apply) would
    /// refuse), without changing the filter.
    pub fn check_distance(&self, distance_since_last_m: f64) -> Result<()> {
        if distance_since_last_m.is_finite() && distance_since_last_m >= 0.0 {
            Ok(())
        } else {
            Err(Error::Distance {
                sweep: self.sweeps,
                distance_m: distance_since_last_m,
            })
        }
    }

    /// Eq. 5-6 in place: `sweep` (`C_i`) becomes `C_i - M_i`. `distance_since_last_m` (`d_i`)
    /// is ignored for the first sweep.
    ///
    /// Errors: a length other than `len`; a negative or non-finite distance (naming the sweep
    /// index). On error the filter is unchanged.
    pub fn apply(&mut self, sweep: &mut [f64], distance_since_last_m: f64) -> Result<()> {
        if sweep.len() != self.mean.len() {
            return Err(Error::Size {
                what: "high-pass sweep",
                expected: self.mean.len(),
                got: sweep.len(),
            });
        }
        self.check_distance(distance_since_last_m)?;
        if self.sweeps == 0 {
            self.mean.copy_from_slice(sweep);
            sweep.fill(0.0);
        } else {
            let beta = self.decay(distance_since_last_m);
            let gain = 1.0 - beta;
            for (c, m) in sweep.iter_mut().zip(&mut self.mean) {
                *m = beta * *m + gain * *c;
                *c -= *m;
            }
        }
        self.sweeps += 1;
        Ok(())
    }
}
