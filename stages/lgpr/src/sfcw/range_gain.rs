//! The fixed range gain (seed 001 §2.1.3: "a fixed range gain is applied to compensate for
//! soil attenuation and geometric spreading").

use serde::Deserialize;

use crate::error::Result;

/// Parameters of the range gain `G(t) = (max(t, t_ref) / t_ref)^p * 10^(alpha max(t, 0) / 20)`,
/// with `t` the two-way time since the antenna (sample time minus the chain's `delay_ns`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct RangeGainParams {
    /// Spreading exponent `p`: amplitude falls as `1 / range^p` (1: spherical spreading). 0
    /// turns the spreading term off. Default 1.
    pub spreading_exponent: f64,
    /// Two-way time `t_ref` below which the spreading term is 1, ns (about the ground bounce
    /// of an array 15 cm up plus the first decimetres of road). Default 2 ns.
    pub reference_ns: f64,
    /// Two-way soil attenuation compensated, `alpha`, dB per ns of two-way time. 0 turns it
    /// off. Default 0.4 dB/ns: 4 dB/m one way at 0.1 m/ns (eps_r ~ 9), the middle of the
    /// simulated highway's layers (2-6 dB/m).
    pub attenuation_db_per_ns: f64,
}

impl Default for RangeGainParams {
    fn default() -> Self {
        Self {
            spreading_exponent: 1.0,
            reference_ns: 2.0,
            attenuation_db_per_ns: 0.4,
        }
    }
}

/// The gain per range sample, computed once.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeGain {
    gains: Vec<f64>,
}

impl RangeGain {
    /// The gain `G(n dt - time_zero_ns)` for samples `n < samples`, `dt = sample_interval_ns`.
    ///
    /// Errors (`Param`, naming the key): a non-finite or negative exponent or attenuation, a
    /// reference time that is not finite and positive, or a gain that overflows `f64`.
    pub fn new(params: &RangeGainParams, time_zero_ns: f64, sample_interval_ns: f64, samples: usize) -> Result<Self> {
        gprflow_params::non_negative("range_gain.spreading_exponent", params.spreading_exponent)?;
        gprflow_params::positive("range_gain.reference_ns", params.reference_ns)?;
        gprflow_params::non_negative("range_gain.attenuation_db_per_ns", params.attenuation_db_per_ns)?;
        let gains: Vec<f64> = (0..samples)
            .map(|n| {
                let t_ns = n as f64 * sample_interval_ns - time_zero_ns;
                let spreading = (t_ns.max(params.reference_ns) / params.reference_ns).powf(params.spreading_exponent);
                spreading * 10f64.powf(params.attenuation_db_per_ns * t_ns.max(0.0) / 20.0)
            })
            .collect();
        if let Some(g) = gains.iter().find(|g| !g.is_finite()) {
            return Err(crate::error::param(
                "range_gain",
                format!("the gain reaches {g} within the kept samples"),
            ));
        }
        Ok(Self { gains })
    }

    /// The gain per sample.
    pub fn gains(&self) -> &[f64] {
        &self.gains
    }
}
