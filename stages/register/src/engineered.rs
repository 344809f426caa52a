//! The engineered registration baseline (seed 000 §4.5, eq. 4.2-4.3): the along-track shift
//! between two submaps that maximises the Pearson correlation of their shared region.
//!
//! For a shift of `T` columns the query's column `c` lies over the reference's column `c + T`;
//! the shared region is the columns both cover. With `A` and `B` the two shared regions minus
//! their own means,
//!
//! `r(T) = Σ A B / (sqrt(Σ A²) sqrt(Σ B²))`   (eq. 4.2),
//!
//! and the measurement is `z = K argmax_T r(T)` (eq. 4.3), `K` the column size in metres.
//! Shifts whose shared region is narrower than `min_overlap` of a submap are not considered
//! (small overlaps correlate by chance). The argmax is refined below a column by the vertex of
//! the parabola through the best score and its two neighbours (an addition to the thesis,
//! which stops at the column; `subpixel: false` gives its result).

use crate::learned::Correlator;
use crate::{Error, Result, SubmapView};

/// Parameters of [`register`].
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct EngineeredParams {
    /// Largest shift tried either way, m (default 1.5: half a 3 m submap).
    pub max_shift_m: f64,
    /// Smallest shared region, as a fraction of the submap's columns (default 0.5).
    pub min_overlap: f64,
    /// Refine the argmax below a column (default true).
    pub subpixel: bool,
}

impl Default for EngineeredParams {
    fn default() -> Self {
        Self {
            max_shift_m: 1.5,
            min_overlap: 0.5,
            subpixel: true,
        }
    }
}

/// The result of [`register`].
#[derive(Debug, Clone, PartialEq)]
pub struct AlongTrackMatch {
    /// Along-track position of the query's column 0 over the reference, m (`K argmax r`).
    pub shift_m: f64,
    /// The best correlation, in -1..=1.
    pub score: f64,
    /// `(shift in columns, r)` for every shift tried, in increasing shift.
    pub curve: Vec<(i64, f64)>,
}

/// `r(T)` of eq. 4.2 for the query shifted `shift` columns over the reference; `None` when the
/// shared region is empty or flat in either image.
pub fn correlation_at(reference: &SubmapView<'_>, query: &SubmapView<'_>, shift: i64) -> Option<f64> {
    let cols = reference.cols as i64;
    // query column c over reference column c + shift
    let q0 = (-shift).max(0);
    let q1 = (cols - shift).min(query.cols as i64);
    if q1 <= q0 {
        return None;
    }
    let (q0, q1) = (q0 as usize, q1 as usize);
    let width = q1 - q0;
    let r0 = (q0 as i64 + shift) as usize;
    let rows = reference.rows.min(query.rows);
    let n = (rows * width) as f64;
    let (mut sa, mut sb) = (0.0f64, 0.0f64);
    for r in 0..rows {
        let a = &reference.pixels[r * reference.cols + r0..r * reference.cols + r0 + width];
        let b = &query.pixels[r * query.cols + q0..r * query.cols + q1];
        sa += a.iter().map(|&v| f64::from(v)).sum::<f64>();
        sb += b.iter().map(|&v| f64::from(v)).sum::<f64>();
    }
    let (ma, mb) = (sa / n, sb / n);
    let (mut ab, mut aa, mut bb) = (0.0f64, 0.0f64, 0.0f64);
    for r in 0..rows {
        let a = &reference.pixels[r * reference.cols + r0..r * reference.cols + r0 + width];
        let b = &query.pixels[r * query.cols + q0..r * query.cols + q1];
        for (&x, &y) in a.iter().zip(b) {
            let (x, y) = (f64::from(x) - ma, f64::from(y) - mb);
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
    }
    (aa > 0.0 && bb > 0.0).then(|| ab / (aa.sqrt() * bb.sqrt()))
}

/// The shift of `query` over `reference` that maximises eq. 4.2, in metres (eq. 4.3); `None`
/// when no shift has a shared region with structure in both images.
///
/// # Errors
/// Parameters out of range, or submaps of different shape or resolution.
pub fn register(
    reference: &SubmapView<'_>,
    query: &SubmapView<'_>,
    params: &EngineeredParams,
) -> Result<Option<AlongTrackMatch>> {
    register_with(&mut Correlator::default(), reference, query, params)
}

/// [`register`] with `correlator`'s buffers, reused from call to call (a loop closer matches
/// every query with several references).
///
/// # Errors
/// As [`register`].
pub fn register_with(
    correlator: &mut Correlator,
    reference: &SubmapView<'_>,
    query: &SubmapView<'_>,
    params: &EngineeredParams,
) -> Result<Option<AlongTrackMatch>> {
    reference.check("reference")?;
    query.check("query")?;
    if (reference.rows, reference.cols) != (query.rows, query.cols)
        || (reference.resolution_m - query.resolution_m).abs() > 1e-9 * reference.resolution_m
    {
        return Err(Error::Shape(format!(
            "reference {} x {} at {} m, query {} x {} at {} m",
            reference.rows, reference.cols, reference.resolution_m, query.rows, query.cols, query.resolution_m
        )));
    }
    crate::check_shift_search(params.max_shift_m, params.min_overlap)?;
    let cols = reference.cols as i64;
    let min_width = ((params.min_overlap * cols as f64).ceil() as i64).max(1);
    let max_shift = ((params.max_shift_m / reference.resolution_m).round() as i64).min(cols - min_width);
    // every shift at once: the column sums and the diagonal sums of the column cross products
    // (`Correlator`), equal to `correlation_at` but for rounding
    let curve: Vec<(i64, f64)> = correlator
        .shift_curve(
            reference.pixels,
            query.pixels,
            reference.rows,
            reference.cols,
            max_shift as usize,
        )?
        .iter()
        .zip(-max_shift..=max_shift)
        .filter(|(r, _)| !r.is_nan())
        .map(|(&r, t)| (t, r))
        .collect();
    let Some(best) = (0..curve.len()).max_by(|&i, &j| curve[i].1.total_cmp(&curve[j].1)) else {
        return Ok(None);
    };
    let (t, score) = curve[best];
    let mut shift = t as f64;
    if params.subpixel && best > 0 && best + 1 < curve.len() && curve[best - 1].0 == t - 1 && curve[best + 1].0 == t + 1
    {
        let (l, c, r) = (curve[best - 1].1, score, curve[best + 1].1);
        let denom = l - 2.0 * c + r;
        if denom < 0.0 {
            shift += (0.5 * (l - r) / denom).clamp(-0.5, 0.5);
        }
    }
    Ok(Some(AlongTrackMatch {
        shift_m: shift * reference.resolution_m,
        score,
        curve,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    const RES: f64 = 0.015;

    /// A 40 x 200 submap of the ground `g(x, row)` with column 0 at `x0` m.
    fn submap(x0: f64, noise: f32, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        let mut px = vec![0.0f32; 40 * 200];
        for r in 0..40 {
            for c in 0..200 {
                let x = x0 + c as f64 * RES;
                // a few buried reflectors of different widths and depths, and a layer
                let g = (-(x - 1.3).powi(2) / 0.01).exp() * ((r as f64 - 12.0) / 3.0).cos()
                    + 0.7 * (-(x - 2.2).powi(2) / 0.04).exp() * ((r as f64 - 25.0) / 2.0).sin()
                    + 0.5 * (-(x - 3.1).powi(2) / 0.02).exp()
                    + 0.3 * (x * 4.0 + r as f64 * 0.5).sin();
                px[r * 200 + c] = g as f32 + noise * next();
            }
        }
        px
    }

    fn view(px: &[f32]) -> SubmapView<'_> {
        SubmapView {
            pixels: px,
            rows: 40,
            cols: 200,
            resolution_m: RES,
        }
    }

    #[test]
    fn a_shifted_submap_is_found_at_its_shift() {
        let reference = submap(0.5, 0.0, 1);
        for shift_cols in [-60i64, -7, 0, 13, 45] {
            let query = submap(0.5 + shift_cols as f64 * RES, 0.1, 2);
            let m = register(&view(&reference), &view(&query), &EngineeredParams::default())
                .expect("valid inputs")
                .expect("a match");
            let err = m.shift_m - shift_cols as f64 * RES;
            assert!(
                err.abs() < 0.25 * RES,
                "shift {shift_cols}: got {} m, err {err}",
                m.shift_m
            );
            assert!(m.score > 0.9, "{}", m.score);
        }
    }

    #[test]
    fn subpixel_refinement_recovers_a_fraction_of_a_column() {
        let reference = submap(0.5, 0.0, 1);
        let query = submap(0.5 + 10.4 * RES, 0.0, 2);
        let p = EngineeredParams::default();
        let m = register(&view(&reference), &view(&query), &p)
            .expect("valid")
            .expect("match");
        assert!((m.shift_m / RES - 10.4).abs() < 0.2, "{}", m.shift_m / RES);
        let whole = register(
            &view(&reference),
            &view(&query),
            &EngineeredParams { subpixel: false, ..p },
        )
        .expect("valid")
        .expect("match");
        assert_eq!(whole.shift_m / RES, 10.0);
    }

    #[test]
    fn correlation_is_one_for_itself_and_flat_images_do_not_match() {
        let a = submap(0.5, 0.0, 1);
        assert!((correlation_at(&view(&a), &view(&a), 0).expect("structure") - 1.0).abs() < 1e-12);
        let flat = vec![3.0f32; 40 * 200];
        assert!(correlation_at(&view(&a), &view(&flat), 0).is_none());
        assert!(
            register(&view(&flat), &view(&flat), &EngineeredParams::default())
                .expect("valid")
                .is_none()
        );
        // no shared region
        assert!(correlation_at(&view(&a), &view(&a), 200).is_none());
    }

    #[test]
    fn the_curve_is_eq_4_2_at_every_shift_and_leaves_out_the_flat_ones() {
        let reference = submap(0.5, 0.2, 1);
        let mut query = submap(0.9, 0.2, 2);
        // the query flat in its right half: the shifts that share only that half have no
        // structure in it
        for row in query.chunks_exact_mut(200) {
            row[100..].fill(3.0);
        }
        let m = register(&view(&reference), &view(&query), &EngineeredParams::default())
            .expect("valid")
            .expect("a match");
        let direct: Vec<(i64, f64)> = (-100..=100)
            .filter_map(|t| correlation_at(&view(&reference), &view(&query), t).map(|r| (t, r)))
            .collect();
        assert_eq!(direct.len(), 200, "one shift is flat");
        assert_eq!(m.curve.len(), direct.len());
        for (&(t, r), &(t_direct, r_direct)) in m.curve.iter().zip(&direct) {
            assert_eq!(t, t_direct);
            assert!((r - r_direct).abs() < 1e-9, "shift {t}: {r} against {r_direct}");
        }
    }

    #[test]
    fn shapes_and_parameters_are_checked() {
        let a = submap(0.5, 0.0, 1);
        let short = &a[..100];
        let bad = SubmapView {
            pixels: short,
            ..view(&a)
        };
        let e = register(&view(&a), &bad, &EngineeredParams::default()).expect_err("refused");
        assert!(e.to_string().contains("query: 100 pixels for 40 x 200"), "{e}");
        let e = register(
            &view(&a),
            &view(&a),
            &EngineeredParams {
                min_overlap: 0.0,
                ..EngineeredParams::default()
            },
        )
        .expect_err("refused");
        assert!(e.to_string().starts_with("min_overlap:"), "{e}");
    }

    proptest::proptest! {
        #[test]
        fn any_pixels_give_a_result_or_none_never_a_panic(
            px in proptest::collection::vec(-1e6f32..1e6, 40 * 200),
            max_shift_m in 0.0f64..10.0,
        ) {
            let p = EngineeredParams { max_shift_m, ..EngineeredParams::default() };
            let m = register(&view(&px), &view(&px), &p).expect("valid shapes");
            if let Some(m) = m {
                proptest::prop_assert!(m.score <= 1.0 + 1e-9 && m.score >= -1.0 - 1e-9);
            }
        }
    }
}
