//! Odometry-based submaps (seed 000 §4.4, eq. 4.11): traces resampled uniformly along track
//! by wheel distance, the validity rule, and the saliency score.
//!
//! A submap `S_t = F({(o_t, w_t) | w_start <= w_t < w_end})` is an image of `rows` samples
//! (depth) by `cols` along-track positions `resolution_m` apart. [`SubmapBuilder`] takes traces,
//! wheel distances and IMU rates in stamp order and emits a submap every `spacing_m` of
//! travel once `length_m` has been covered (the thesis tools: 3 m at 0.015 m/px, a new submap
//! every 0.02 m).
//!
//! - Resampling ("rubber band", [`rubber_band`]): the distance of a trace is the wheel distance
//!   interpolated at its stamp; traces falling in one along-track bin are averaged (stacking),
//!   empty bins are filled by linear interpolation between their nearest filled neighbours.
//! - Validity ([`ValidityParams`]): inside the submap the z gyro rate and the y (lateral)
//!   acceleration stay within thresholds and the encoder moves one way only (no
//!   forward-backward motion; standing still adds no columns); and no run of empty columns
//!   is longer than `max_gap_m` (the radar did not stop while the wheel moved).
//! - Saliency ([`saliency`]): the row-wise standard deviation across columns, average-pooled
//!   over the rows.
//! - Poses: a planar dead-reckoning ([`PlanarOdometry`]: wheel distance along the heading
//!   integrated from the z gyro) gives the odometry pose at the start and the end of a submap.
//!
//! Columns are in travel order: column 0 is the oldest. A submap recorded while driving
//! backwards has `end_distance_m < start_distance_m`.
//!
//! `node` (feature `node`, default): the `submap` stage.

#[cfg(feature = "node")]
pub mod node;

mod builder;
mod odometry;

pub use builder::{Submap, SubmapBuilder, SubmapStats};
pub use gprflow_dsp::image::saliency;
pub use odometry::PlanarOdometry;

pub use gprflow_params::ParamError;

/// What can go wrong in this crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of range; its path names it as in the graph file.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// A measurement is unusable (non-finite, wrong length, stamp going backwards); it was not used.
    #[error("{0}")]
    BadMeasurement(String),
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;

/// Size and spacing of submaps.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct SubmapParams {
    /// Along-track length of a submap, m (default 3.0).
    pub length_m: f64,
    /// Along-track size of a column, m (default 0.015).
    pub resolution_m: f64,
    /// Travel between the starts of consecutive submaps, m (default 0.02).
    pub spacing_m: f64,
    /// The validity rule.
    pub validity: ValidityParams,
    /// Also emit submaps that fail the validity rule, flagged `valid = false` (default false:
    /// they are counted, not emitted).
    pub emit_invalid: bool,
}

impl Default for SubmapParams {
    fn default() -> Self {
        Self {
            length_m: 3.0,
            resolution_m: 0.015,
            spacing_m: 0.02,
            validity: ValidityParams::default(),
            emit_invalid: false,
        }
    }
}

/// The validity rule of seed 000 §4.4.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct ValidityParams {
    /// Largest |z gyro rate| inside a valid submap, rad/s (default 0.35, about 20 deg/s).
    pub max_gyro_z_radps: f64,
    /// Largest |y acceleration| (lateral) inside a valid submap, m/s^2 (default 1.5).
    pub max_accel_y_mps2: f64,
    /// Longest run of columns without a trace that the rubber band may bridge, m (default
    /// 0.1): beyond it the radar stopped while the wheel moved, and the interpolated image
    /// would be invented.
    pub max_gap_m: f64,
}

impl Default for ValidityParams {
    fn default() -> Self {
        Self {
            max_gyro_z_radps: 0.35,
            max_accel_y_mps2: 1.5,
            max_gap_m: 0.1,
        }
    }
}

impl SubmapParams {
    /// Columns of a submap: `round(length_m / resolution_m)`.
    pub fn cols(&self) -> usize {
        (self.length_m / self.resolution_m).round() as usize
    }

    /// Checks every field.
    ///
    /// # Errors
    /// A [`ParamError`] naming the first bad field.
    pub fn check(&self) -> gprflow_params::Result {
        let positive = [
            ("length_m", self.length_m),
            ("resolution_m", self.resolution_m),
            ("spacing_m", self.spacing_m),
            ("validity.max_gyro_z_radps", self.validity.max_gyro_z_radps),
            ("validity.max_accel_y_mps2", self.validity.max_accel_y_mps2),
            ("validity.max_gap_m", self.validity.max_gap_m),
        ];
        for (key, v) in positive {
            gprflow_params::positive(key, v)?;
        }
        let cols = self.length_m / self.resolution_m;
        if !(2.0..=100_000.0).contains(&cols) {
            return Err(ParamError::new(
                "length_m",
                format!(
                    "length_m / resolution_m must give 2 to 100000 columns, got {cols:.1} ({} / {})",
                    self.length_m, self.resolution_m
                ),
            ));
        }
        Ok(())
    }
}

/// Fills empty columns of a `rows x cols` row-major image by linear interpolation between
/// the nearest filled columns on either side (the "rubber band"); columns before the first
/// or after the last filled one copy it. `filled[c]` says whether column `c` holds data.
/// Returns false (and leaves the image alone) when no column is filled.
pub fn rubber_band(pixels: &mut [f32], rows: usize, cols: usize, filled: &[bool]) -> bool {
    debug_assert_eq!(pixels.len(), rows * cols);
    let known: Vec<usize> = (0..cols).filter(|&c| filled[c]).collect();
    let (Some(&first), Some(&last)) = (known.first(), known.last()) else {
        return false;
    };
    let copy_col = |px: &mut [f32], from: usize, to: usize| {
        for r in 0..rows {
            px[r * cols + to] = px[r * cols + from];
        }
    };
    for c in 0..first {
        copy_col(pixels, first, c);
    }
    for c in last + 1..cols {
        copy_col(pixels, last, c);
    }
    for pair in known.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        for c in a + 1..b {
            let w = (c - a) as f32 / (b - a) as f32;
            for r in 0..rows {
                let (va, vb) = (pixels[r * cols + a], pixels[r * cols + b]);
                pixels[r * cols + c] = va + w * (vb - va);
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rubber_band_interpolates_gaps_and_holds_the_ends() {
        // 2 rows x 6 cols; columns 1 and 4 filled
        let mut px = vec![0.0, 1.0, 0.0, 0.0, 4.0, 0.0, 0.0, -2.0, 0.0, 0.0, 4.0, 0.0];
        let filled = [false, true, false, false, true, false];
        assert!(rubber_band(&mut px, 2, 6, &filled));
        assert_eq!(&px[..6], &[1.0, 1.0, 2.0, 3.0, 4.0, 4.0]);
        assert_eq!(&px[6..], &[-2.0, -2.0, 0.0, 2.0, 4.0, 4.0]);
        let mut empty = vec![7.0; 4];
        assert!(!rubber_band(&mut empty, 2, 2, &[false, false]));
        assert_eq!(empty, vec![7.0; 4]);
    }

    #[test]
    fn saliency_is_zero_for_flat_rows_and_grows_with_along_track_structure() {
        let flat: Vec<f32> = (0..3).flat_map(|r| vec![r as f32; 4]).collect();
        assert_eq!(saliency(&flat, 3, 4), 0.0);
        // one row alternating +-1 (std 1), one flat row: average 0.5
        let px = vec![1.0, -1.0, 1.0, -1.0, 5.0, 5.0, 5.0, 5.0];
        assert!((saliency(&px, 2, 4) - 0.5).abs() < 1e-6);
    }

    #[test]
    fn params_are_checked_with_the_key_named() {
        assert!(SubmapParams::default().check().is_ok());
        assert_eq!(SubmapParams::default().cols(), 200);
        let bad = SubmapParams {
            spacing_m: f64::NAN,
            ..SubmapParams::default()
        };
        assert!(bad.check().expect_err("refused").to_string().starts_with("spacing_m:"));
        let tiny = SubmapParams {
            length_m: 0.01,
            ..SubmapParams::default()
        };
        assert!(tiny.check().expect_err("refused").to_string().starts_with("length_m:"));
    }
}
