//! Where each channel of the LGPR array sits on the vehicle (seed 001 Table I: 12 elements
//! 12.7 cm apart across track, 11 transmit/receive pairs, each channel measured at the midpoint
//! of its pair).

use serde::Deserialize;

use crate::error::{Error, param};

/// The array's geometry in the body frame (x forward, y left, metres).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct ArrayGeometry {
    /// Element spacing across track, m. Default 0.127 (seed 001).
    pub element_spacing_m: f64,
    /// Array centre in the body frame `[x forward, y left]`, m. Default `[0, 0]`.
    pub mount_m: [f64; 2],
}

impl Default for ArrayGeometry {
    fn default() -> Self {
        Self {
            element_spacing_m: 0.127,
            mount_m: [0.0, 0.0],
        }
    }
}

impl ArrayGeometry {
    /// Checks the values; `prefix` is the key of this block in the graph file (`array`).
    ///
    /// # Errors
    /// `Param`: a spacing that is not positive and finite, a mount that is not finite.
    pub fn check(&self, prefix: &str) -> Result<(), Error> {
        if !(self.element_spacing_m.is_finite() && self.element_spacing_m > 0.0) {
            return Err(param(
                &format!("{prefix}.element_spacing_m"),
                format!("must be positive and finite, got {}", self.element_spacing_m),
            ));
        }
        if !self.mount_m.iter().all(|v| v.is_finite()) {
            return Err(param(
                &format!("{prefix}.mount_m"),
                format!("must be finite, got {:?}", self.mount_m),
            ));
        }
        Ok(())
    }

    /// Lateral position (body y, left positive) of channel `k` of `channels`, mount included:
    /// the channels are centred on the mount, `element_spacing_m` apart.
    pub fn channel_y_m(&self, k: usize, channels: usize) -> f64 {
        self.mount_m[1] + (k as f64 - (channels as f64 - 1.0) / 2.0) * self.element_spacing_m
    }

    /// Lateral positions of all `channels`.
    pub fn channel_offsets_m(&self, channels: usize) -> Vec<f64> {
        (0..channels).map(|k| self.channel_y_m(k, channels)).collect()
    }

    /// World `(x, y)` of a body-frame point `(bx, by)` with the body at `(x, y)` heading `yaw`.
    pub fn to_world(x: f64, y: f64, yaw_rad: f64, bx: f64, by: f64) -> (f64, f64) {
        let (s, c) = yaw_rad.sin_cos();
        (x + c * bx - s * by, y + s * bx + c * by)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eleven_channels_are_centred_and_spaced() {
        let g = ArrayGeometry::default();
        let o = g.channel_offsets_m(11);
        assert!((o[5]).abs() < 1e-12);
        assert!((o[0] + 5.0 * 0.127).abs() < 1e-12);
        assert!((o[10] - 5.0 * 0.127).abs() < 1e-12);
        let (x, y) = ArrayGeometry::to_world(1.0, 2.0, std::f64::consts::FRAC_PI_2, 0.0, 0.5);
        assert!((x - 0.5).abs() < 1e-12 && (y - 2.0).abs() < 1e-12);
    }

    #[test]
    fn bad_spacing_is_named() {
        let g = ArrayGeometry {
            element_spacing_m: 0.0,
            ..ArrayGeometry::default()
        };
        let e = g.check("array").expect_err("must fail").to_string();
        assert!(e.contains("array.element_spacing_m"), "{e}");
    }
}
