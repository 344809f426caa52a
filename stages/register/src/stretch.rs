//! Travel-time stretch of a submap, for the learned method's stretch search.
//!
//! Drying (or wetting) soil changes the wave speed between two passes over the same ground:
//! every reflector of the later pass arrives earlier or later by the same factor of its
//! travel time, so the two submaps differ by a stretch of the time (row) axis, about the
//! surface (row 0). The stage tries the query at a few such stretches and keeps the one whose
//! features share most with the reference (docs/localisation.md).

use crate::Result;
use crate::SubmapView;

/// Largest relative stretch accepted (`|factor - 1|`): beyond it a submap's lower rows would
/// come from outside the image for most of its depth.
pub const MAX_STRETCH: f64 = 0.25;

/// The factors `1 + k * step` for `k` in `-steps..=steps`, in increasing order (`[1.0]` when
/// `steps` is 0).
///
/// # Errors
/// [`Error::Param`](crate::Error::Param) (`stretch_step`) as [`check_factors`].
pub fn factors(step: f64, steps: usize) -> Result<Vec<f64>> {
    if steps == 0 {
        return Ok(vec![1.0]);
    }
    check_factors(step, steps)?;
    let n = steps as i64;
    Ok((-n..=n).map(|k| 1.0 + k as f64 * step).collect())
}

/// `Ok` when `steps` is 0 (no search), or `step` is positive and finite and every factor
/// lies within `1 +- MAX_STRETCH`.
///
/// # Errors
/// A [`gprflow_params::ParamError`] at `stretch_step` otherwise.
pub fn check_factors(step: f64, steps: usize) -> gprflow_params::Result {
    if steps == 0 || (step.is_finite() && step > 0.0 && step * steps as f64 <= MAX_STRETCH) {
        Ok(())
    } else {
        Err(gprflow_params::ParamError::new(
            "stretch_step",
            format!("must be positive with stretch_steps x stretch_step <= {MAX_STRETCH}, got {step} x {steps}"),
        ))
    }
}

/// `submap`'s rows resampled so that row `r` holds what the submap has at row `r * factor`
/// (linear interpolation between rows, per column; 0 past the last row), into `out`
/// (`rows x cols`, row-major). `factor > 1` reads deeper rows: it undoes a slower pass's later
/// arrivals.
///
/// # Errors
/// [`Error::Shape`](crate::Error::Shape) for an inconsistent submap;
/// [`Error::Param`](crate::Error::Param) (`stretch`) for a factor that
/// is not finite or lies outside `1 +- MAX_STRETCH`.
pub fn stretch_rows(submap: &SubmapView<'_>, factor: f64, out: &mut Vec<f32>) -> Result<()> {
    submap.check("submap")?;
    if !(factor.is_finite() && (factor - 1.0).abs() <= MAX_STRETCH) {
        return Err(crate::param(
            "stretch",
            format!("must be within 1 +- {MAX_STRETCH}, got {factor}"),
        ));
    }
    let (rows, cols) = (submap.rows, submap.cols);
    out.clear();
    out.resize(rows * cols, 0.0);
    let last = (rows - 1) as f64;
    for r in 0..rows {
        let src = r as f64 * factor;
        if src > last {
            // every later row is further still
            break;
        }
        let r0 = src.floor() as usize;
        let a = (src - r0 as f64) as f32;
        let dst = &mut out[r * cols..(r + 1) * cols];
        let upper = &submap.pixels[r0 * cols..(r0 + 1) * cols];
        if r0 + 1 < rows && a > 0.0 {
            let lower = &submap.pixels[(r0 + 1) * cols..(r0 + 2) * cols];
            for ((d, &u), &l) in dst.iter_mut().zip(upper).zip(lower) {
                *d = u + a * (l - u);
            }
        } else {
            dst.copy_from_slice(upper);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(pixels: &[f32], rows: usize, cols: usize) -> SubmapView<'_> {
        SubmapView {
            pixels,
            rows,
            cols,
            resolution_m: 0.015,
        }
    }

    #[test]
    fn factors_are_symmetric_about_one() {
        assert_eq!(factors(0.015, 0).expect("no search"), vec![1.0]);
        let f = factors(0.015, 2).expect("valid");
        assert_eq!(f.len(), 5);
        assert_eq!(f[2], 1.0);
        assert!((f[0] - 0.97).abs() < 1e-12 && (f[4] - 1.03).abs() < 1e-12);
        for bad in [0.0, -0.01, f64::NAN, 0.2] {
            assert!(factors(bad, 2).is_err(), "{bad}");
        }
    }

    #[test]
    fn no_stretch_is_the_identity() {
        let pixels: Vec<f32> = (0..35).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut out = Vec::new();
        stretch_rows(&view(&pixels, 7, 5), 1.0, &mut out).expect("stretches");
        assert_eq!(out, pixels);
    }

    #[test]
    fn a_stretch_moves_a_reflector_by_its_depth_times_the_factor() {
        // a column that is its own row index: row r of the result must read r * factor
        let (rows, cols) = (201, 3);
        let pixels: Vec<f32> = (0..rows * cols).map(|i| (i / cols) as f32).collect();
        let mut out = Vec::new();
        stretch_rows(&view(&pixels, rows, cols), 1.015, &mut out).expect("stretches");
        for r in 0..rows {
            let src = r as f64 * 1.015;
            let want = if src <= (rows - 1) as f64 { src as f32 } else { 0.0 };
            for c in 0..cols {
                assert!(
                    (out[r * cols + c] - want).abs() < 1e-3,
                    "row {r}: {} vs {want}",
                    out[r * cols + c]
                );
            }
        }
        stretch_rows(&view(&pixels, rows, cols), 0.985, &mut out).expect("stretches");
        assert!((out[100 * cols] - 98.5).abs() < 1e-4);
        assert_eq!(out[(rows - 1) * cols], 197.0);
    }

    #[test]
    fn bad_factors_and_shapes_are_refused() {
        let pixels = vec![0.0f32; 12];
        let mut out = Vec::new();
        for f in [f64::NAN, 0.5, 1.3, f64::INFINITY] {
            assert!(matches!(
                stretch_rows(&view(&pixels, 3, 4), f, &mut out),
                Err(crate::Error::Param(_))
            ));
        }
        assert!(matches!(
            stretch_rows(&view(&pixels, 5, 4), 1.0, &mut out),
            Err(crate::Error::Shape(_))
        ));
    }
}
