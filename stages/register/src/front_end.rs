//! The encoder's weight-free front end (`tools/train/SPEC.md`, "Front end"), run in Rust before
//! the ONNX graph: the model file names it in its metadata ([`FRONT_END_KEY`],
//! [`FRONT_END_ITERATIONS_KEY`]), training computes the same in PyTorch.
//!
//! `band`: the standardised submap minus its largest singular component, found by power
//! iteration from a flat column vector, then standardised again. A horizontal band whose
//! strength varies along the track (uneven ground contact) is such a component.

use crate::{Error, Result};

/// Model metadata key naming the front end: `none` (or absent) or `band`.
pub const FRONT_END_KEY: &str = "gprflow.front_end";

/// Model metadata key with the `band` front end's number of power iterations.
pub const FRONT_END_ITERATIONS_KEY: &str = "gprflow.front_end.iterations";

/// Added to a power-iteration vector's norm before dividing (as in training).
const NORM_FLOOR: f64 = 1e-12;

/// Added to the standard deviation before dividing (as in training).
const STD_EPSILON: f64 = 1e-6;

/// What runs before the ONNX graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrontEnd {
    /// Nothing: the standardised submap goes straight to the graph.
    None,
    /// The largest singular component taken out (`iterations` power iterations), then
    /// standardised again.
    Band {
        /// Power iterations, at least 1.
        iterations: usize,
    },
}

impl FrontEnd {
    /// The front end named by a model's metadata values (`None` when a key is absent).
    ///
    /// # Errors
    /// A message naming the key and the value when the name is unknown or the iteration count
    /// is not a whole number from 1 to 1000.
    pub fn from_metadata(name: Option<&str>, iterations: Option<&str>) -> std::result::Result<FrontEnd, String> {
        match name.map(str::trim) {
            None | Some("none") => Ok(FrontEnd::None),
            Some("band") => {
                let Some(text) = iterations else {
                    return Err(format!(
                        "metadata `{FRONT_END_KEY}` is `band` but `{FRONT_END_ITERATIONS_KEY}` is missing"
                    ));
                };
                match text.trim().parse::<usize>() {
                    Ok(n @ 1..=1000) => Ok(FrontEnd::Band { iterations: n }),
                    _ => Err(format!(
                        "metadata `{FRONT_END_ITERATIONS_KEY}` is `{text}`, expected a whole number from 1 to 1000"
                    )),
                }
            }
            Some(other) => Err(format!(
                "metadata `{FRONT_END_KEY}` is `{other}`, expected `none` or `band`"
            )),
        }
    }
}

/// Scratch buffers of [`FrontEndScratch::apply`], reused from submap to submap.
#[derive(Debug, Default)]
pub struct FrontEndScratch {
    u: Vec<f32>,
    v: Vec<f32>,
    next: Vec<f32>,
}

impl FrontEndScratch {
    /// Applies `front_end` in place to `image` (`rows x cols`, row-major, finite). Computed in
    /// f32 (as the graph it was trained in did), with the norm, mean and variance summed in f64.
    ///
    /// # Errors
    /// [`Error::Shape`] when `image` does not hold `rows x cols` values (it is left as it was).
    pub fn apply(&mut self, front_end: FrontEnd, image: &mut [f32], rows: usize, cols: usize) -> Result<()> {
        if rows.checked_mul(cols) != Some(image.len()) {
            return Err(Error::Shape(format!(
                "front end: {} values are not a {rows} x {cols} image",
                image.len()
            )));
        }
        match front_end {
            FrontEnd::None => {}
            FrontEnd::Band { iterations } => {
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has AVX2 and FMA, checked just above.
                    unsafe { self.remove_band_avx2(image, rows, cols, iterations) };
                    return Ok(());
                }
                self.remove_band::<false>(image, rows, cols, iterations);
            }
        }
        Ok(())
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn remove_band_avx2(&mut self, image: &mut [f32], rows: usize, cols: usize, iterations: usize) {
        self.remove_band::<true>(image, rows, cols, iterations);
    }

    /// `band`: `y = x - (x v) v^T` for the unit vector `v` after `iterations` steps of
    /// `v <- X^T X v / |X^T X v|` from `v = 1`, then `(y - mean y) / (std y + 1e-6)`. Each
    /// step is one pass over the image, [`BLOCK`] rows at a time (their `x_r . v`, then the
    /// rows times those added to the next `v`, while they are in cache); then one pass for
    /// `x v` and the moments of `y`, one to write `y`. `FMA`: fused multiply-adds.
    #[inline(always)]
    fn remove_band<const FMA: bool>(&mut self, image: &mut [f32], rows: usize, cols: usize, iterations: usize) {
        if rows == 0 || cols == 0 {
            return;
        }
        let FrontEndScratch { u, v, next } = self;
        v.clear();
        v.resize(cols, 1.0);
        for _ in 0..iterations {
            next.clear();
            next.resize(cols, 0.0);
            let next = &mut next[..cols];
            let mut blocks = image.chunks_exact(BLOCK * cols);
            for block in blocks.by_ref() {
                let ub = block_dots::<FMA>(block, v);
                let (r0, r1, r2, r3) = four_rows(block, cols);
                for c in 0..cols {
                    let a = madd::<FMA>(r0[c], ub[0], next[c]);
                    let a = madd::<FMA>(r1[c], ub[1], a);
                    let a = madd::<FMA>(r2[c], ub[2], a);
                    next[c] = madd::<FMA>(r3[c], ub[3], a);
                }
            }
            for row in blocks.remainder().chunks_exact(cols) {
                let ur = row_dot::<FMA>(row, v);
                for (n, &x) in next.iter_mut().zip(row) {
                    *n = madd::<FMA>(x, ur, *n);
                }
            }
            let norm = next.iter().map(|&a| f64::from(a) * f64::from(a)).sum::<f64>().sqrt() + NORM_FLOOR;
            for (a, &b) in v.iter_mut().zip(next.iter()) {
                *a = (f64::from(b) / norm) as f32;
            }
        }
        u.clear();
        let (mut sum, mut squares) = (0.0, 0.0);
        for row in image.chunks_exact(cols) {
            let ur = row_dot::<FMA>(row, v);
            u.push(ur);
            let (s, q) = moments::<FMA>(row, v, ur);
            sum += s;
            squares += q;
        }
        let n = image.len() as f64;
        let mean = sum / n;
        let var = (squares / n - mean * mean).max(0.0);
        let scale = 1.0 / (var.sqrt() + STD_EPSILON);
        let (mean, scale) = (mean as f32, scale as f32);
        for (row, &ur) in image.chunks_exact_mut(cols).zip(u.iter()) {
            for (p, &vc) in row.iter_mut().zip(v.iter()) {
                *p = (madd::<FMA>(-ur, vc, *p) - mean) * scale;
            }
        }
    }
}

/// Rows taken together in a power-iteration step.
const BLOCK: usize = 4;

/// Partial sums per row.
const LANES: usize = 16;

/// `a b + c`, fused when `FMA` (only where the CPU has FMA: elsewhere it is a library call).
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

/// The [`BLOCK`] rows of `block`, each `cols` long.
#[inline(always)]
fn four_rows(block: &[f32], cols: usize) -> (&[f32], &[f32], &[f32], &[f32]) {
    (
        &block[..cols],
        &block[cols..2 * cols],
        &block[2 * cols..3 * cols],
        &block[3 * cols..4 * cols],
    )
}

/// `x_r . v` of each of the [`BLOCK`] rows of `block` (rows of `v.len()`), together.
#[inline(always)]
fn block_dots<const FMA: bool>(block: &[f32], v: &[f32]) -> [f32; BLOCK] {
    let cols = v.len();
    let (vc, vt) = v.as_chunks::<LANES>();
    let (r0, r1, r2, r3) = four_rows(block, cols);
    let mut acc = [[0.0f32; LANES]; BLOCK];
    let chunks = vc
        .iter()
        .zip(r0.as_chunks::<LANES>().0)
        .zip(r1.as_chunks::<LANES>().0)
        .zip(r2.as_chunks::<LANES>().0)
        .zip(r3.as_chunks::<LANES>().0);
    for ((((vs, x0), x1), x2), x3) in chunks {
        for l in 0..LANES {
            acc[0][l] = madd::<FMA>(x0[l], vs[l], acc[0][l]);
            acc[1][l] = madd::<FMA>(x1[l], vs[l], acc[1][l]);
            acc[2][l] = madd::<FMA>(x2[l], vs[l], acc[2][l]);
            acc[3][l] = madd::<FMA>(x3[l], vs[l], acc[3][l]);
        }
    }
    let tail = cols - vt.len();
    let mut out = [0.0; BLOCK];
    for (b, (acc, row)) in acc.iter_mut().zip([r0, r1, r2, r3]).enumerate() {
        for (l, (&x, &vv)) in row[tail..].iter().zip(vt).enumerate() {
            acc[l] = madd::<FMA>(x, vv, acc[l]);
        }
        out[b] = acc.iter().sum();
    }
    out
}

/// `x . v` of one row, in [`LANES`] interleaved partial sums.
#[inline(always)]
fn row_dot<const FMA: bool>(row: &[f32], v: &[f32]) -> f32 {
    let ((xc, xt), (vc, vt)) = (row.as_chunks::<LANES>(), v.as_chunks::<LANES>());
    let mut acc = [0.0f32; LANES];
    for (x, vs) in xc.iter().zip(vc) {
        for l in 0..LANES {
            acc[l] = madd::<FMA>(x[l], vs[l], acc[l]);
        }
    }
    for (l, (&x, &vv)) in xt.iter().zip(vt).enumerate() {
        acc[l] = madd::<FMA>(x, vv, acc[l]);
    }
    acc.iter().sum()
}

/// `(Σ y_i, Σ y_i^2)` for `y = x - ur v`, in [`LANES`] interleaved partial sums (f64 totals).
#[inline(always)]
fn moments<const FMA: bool>(row: &[f32], v: &[f32], ur: f32) -> (f64, f64) {
    let ((xc, xt), (vc, vt)) = (row.as_chunks::<LANES>(), v.as_chunks::<LANES>());
    let mut sum = [0.0f32; LANES];
    let mut squares = [0.0f32; LANES];
    for (x, vs) in xc.iter().zip(vc) {
        for l in 0..LANES {
            let y = madd::<FMA>(-ur, vs[l], x[l]);
            sum[l] += y;
            squares[l] = madd::<FMA>(y, y, squares[l]);
        }
    }
    for (l, (&x, &vv)) in xt.iter().zip(vt).enumerate() {
        let y = madd::<FMA>(-ur, vv, x);
        sum[l] += y;
        squares[l] = madd::<FMA>(y, y, squares[l]);
    }
    let total = |a: [f32; LANES]| a.iter().map(|&x| f64::from(x)).sum::<f64>();
    (total(sum), total(squares))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(rows: usize, cols: usize) -> Vec<f32> {
        // a random-ish texture plus a horizontal band whose strength varies along the columns
        (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                let texture = ((i as f64 * 12.9898).sin() * 43758.5453).fract() - 0.5;
                let band = if (20..24).contains(&r) {
                    3.0 * (1.0 + (c as f64 * 0.05).sin())
                } else {
                    0.0
                };
                (texture + band) as f32
            })
            .collect()
    }

    /// The largest singular component by a dense eigen-decomposition of `X^T X`.
    fn leading_component(x: &[f32], rows: usize, cols: usize) -> Vec<f64> {
        let m = nalgebra::DMatrix::from_fn(rows, cols, |r, c| f64::from(x[r * cols + c]));
        let gram = m.transpose() * &m;
        let eig = gram.symmetric_eigen();
        let top = eig.eigenvalues.imax();
        eig.eigenvectors.column(top).iter().copied().collect()
    }

    #[test]
    fn the_band_is_taken_out_and_the_result_standardised() {
        let (rows, cols) = (60, 40);
        let mut x = image(rows, cols);
        let v = leading_component(&x, rows, cols);
        let mut scratch = FrontEndScratch::default();
        scratch
            .apply(FrontEnd::Band { iterations: 60 }, &mut x, rows, cols)
            .expect("shape");
        let n = x.len() as f64;
        let mean = x.iter().map(|&p| f64::from(p)).sum::<f64>() / n;
        let var = x.iter().map(|&p| (f64::from(p) - mean).powi(2)).sum::<f64>() / n;
        assert!(mean.abs() < 1e-6, "mean {mean}");
        assert!((var - 1.0).abs() < 1e-5, "variance {var}");
        // what is left has (almost) nothing along the removed direction, up to the constant
        // the re-standardisation subtracted
        let along: f64 = x
            .chunks_exact(cols)
            .map(|row| {
                row.iter()
                    .zip(&v)
                    .map(|(&p, &b)| (f64::from(p) - mean) * b)
                    .sum::<f64>()
                    .powi(2)
            })
            .sum::<f64>()
            / n;
        let mean_part = (v.iter().sum::<f64>() * mean).powi(2);
        assert!(along < 1e-3 + mean_part, "energy along the band direction {along}");
        // the band rows no longer stand out
        let row_energy = |r: usize| {
            x[r * cols..(r + 1) * cols]
                .iter()
                .map(|&p| f64::from(p).powi(2))
                .sum::<f64>()
        };
        let band: f64 = (20..24).map(row_energy).sum::<f64>() / 4.0;
        let rest: f64 = (0..rows).filter(|r| !(20..24).contains(r)).map(row_energy).sum::<f64>() / (rows - 4) as f64;
        assert!(band < 3.0 * rest, "band rows {band} vs the rest {rest}");
    }

    #[test]
    fn the_portable_arithmetic_matches_the_dispatched_one() {
        let (rows, cols) = (37, 53); // blocks of four rows and chunks of sixteen columns, with rests
        let mut fused = image(rows, cols);
        let mut portable = fused.clone();
        let mut scratch = FrontEndScratch::default();
        scratch
            .apply(FrontEnd::Band { iterations: 6 }, &mut fused, rows, cols)
            .expect("shape");
        scratch.remove_band::<false>(&mut portable, rows, cols, 6);
        let worst = fused
            .iter()
            .zip(&portable)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "max difference {worst}");
    }

    #[test]
    fn none_leaves_the_image_alone_and_wrong_shapes_are_refused() {
        let mut x = image(5, 7);
        let before = x.clone();
        let mut scratch = FrontEndScratch::default();
        scratch.apply(FrontEnd::None, &mut x, 5, 7).expect("shape");
        assert_eq!(x, before);
        scratch
            .apply(FrontEnd::Band { iterations: 3 }, &mut [], 0, 0)
            .expect("empty");
        let e = scratch
            .apply(FrontEnd::Band { iterations: 3 }, &mut x, 6, 7)
            .expect_err("wrong shape");
        assert!(e.to_string().contains("35 values are not a 6 x 7 image"), "{e}");
        assert_eq!(x, before);
    }

    #[test]
    fn metadata_names_are_checked() {
        assert_eq!(FrontEnd::from_metadata(None, None), Ok(FrontEnd::None));
        assert_eq!(FrontEnd::from_metadata(Some("none"), Some("9")), Ok(FrontEnd::None));
        assert_eq!(
            FrontEnd::from_metadata(Some("band"), Some("6")),
            Ok(FrontEnd::Band { iterations: 6 })
        );
        for (name, iterations, needle) in [
            (Some("band"), None, "missing"),
            (Some("band"), Some("0"), "whole number"),
            (Some("band"), Some("six"), "whole number"),
            (Some("wavelet"), Some("6"), "`wavelet`"),
        ] {
            let e = FrontEnd::from_metadata(name, iterations).expect_err("refused");
            assert!(e.contains(needle), "{e}");
        }
    }
}
