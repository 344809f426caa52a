//! Gaussian noise models (as square-root information) and robust kernels.

use nalgebra::{DMatrix, DVector};

use crate::{Error, Result};

/// An M-estimator applied to the whitened residual norm, as GTSAM's `noiseModel::Robust`:
/// the factor's error is `loss(||r_w||)` instead of `0.5 ||r_w||^2`, and linearisation
/// reweights the whitened system by `sqrt(weight(||r_w||))` (iteratively reweighted least squares).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RobustKernel {
    /// Quadratic inside `k`, linear outside.
    Huber {
        /// Threshold on the whitened norm.
        k: f64,
    },
    /// `0.5 k^2 ln(1 + x^2 / k^2)`.
    Cauchy {
        /// Scale on the whitened norm.
        k: f64,
    },
}

impl RobustKernel {
    /// The loss of a whitened residual with norm `x`.
    #[must_use]
    pub fn loss(&self, x: f64) -> f64 {
        match *self {
            Self::Huber { k } => {
                let a = x.abs();
                if a <= k { 0.5 * a * a } else { k * (a - 0.5 * k) }
            }
            Self::Cauchy { k } => 0.5 * k * k * (1.0 + x * x / (k * k)).ln(),
        }
    }

    /// The IRLS weight at norm `x`.
    #[must_use]
    pub fn weight(&self, x: f64) -> f64 {
        match *self {
            Self::Huber { k } => {
                let a = x.abs();
                if a <= k { 1.0 } else { k / a }
            }
            Self::Cauchy { k } => k * k / (k * k + x * x),
        }
    }
}

/// Gaussian measurement noise stored as an upper-triangular square-root information matrix
/// `R` (`R^T R = Sigma^-1`), with an optional robust kernel.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseModel {
    sqrt_info: DMatrix<f64>,
    diagonal: bool,
    kernel: Option<RobustKernel>,
}

impl NoiseModel {
    /// Independent components with the given standard deviations.
    ///
    /// # Errors
    /// [`Error::BadNoise`] for a sigma that is not positive and finite.
    pub fn diagonal(sigmas: &[f64]) -> Result<Self> {
        if sigmas.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::BadNoise(format!("sigmas must be positive: {sigmas:?}")));
        }
        let d = DVector::from_iterator(sigmas.len(), sigmas.iter().map(|s| 1.0 / s));
        Ok(Self {
            sqrt_info: DMatrix::from_diagonal(&d),
            diagonal: true,
            kernel: None,
        })
    }

    /// `dim` independent components with one standard deviation.
    ///
    /// # Errors
    /// [`Error::BadNoise`] for a sigma that is not positive and finite.
    pub fn isotropic(dim: usize, sigma: f64) -> Result<Self> {
        Self::diagonal(&vec![sigma; dim])
    }

    /// From a full covariance matrix.
    ///
    /// # Errors
    /// [`Error::BadNoise`] when the covariance is not symmetric positive definite.
    pub fn from_covariance(cov: &DMatrix<f64>) -> Result<Self> {
        let info = cov
            .clone()
            .cholesky()
            .ok_or_else(|| Error::BadNoise("covariance is not positive definite".into()))?
            .inverse();
        let info = 0.5 * (&info + info.transpose());
        let l = info
            .cholesky()
            .ok_or_else(|| Error::BadNoise("information is not positive definite".into()))?;
        Ok(Self {
            sqrt_info: l.l().transpose(),
            diagonal: false,
            kernel: None,
        })
    }

    /// The same model under a robust kernel.
    #[must_use]
    pub fn robust(mut self, kernel: RobustKernel) -> Self {
        self.kernel = Some(kernel);
        self
    }

    /// Residual dimension.
    #[must_use]
    pub fn dim(&self) -> usize {
        self.sqrt_info.nrows()
    }

    /// The robust kernel, if any.
    #[must_use]
    pub fn kernel(&self) -> Option<RobustKernel> {
        self.kernel
    }

    /// `R r`.
    #[must_use]
    pub fn whiten(&self, r: &DVector<f64>) -> DVector<f64> {
        let mut out = DVector::zeros(r.len());
        self.whiten_into(r.as_slice(), out.as_mut_slice());
        out
    }

    /// `R r` into `out` (the same length as `r`).
    pub(crate) fn whiten_into(&self, r: &[f64], out: &mut [f64]) {
        out.copy_from_slice(r);
        if self.diagonal {
            for (o, s) in out.iter_mut().zip(self.sqrt_info.diagonal().iter()) {
                *o *= s;
            }
        } else {
            upper_mul_in_place(self.sqrt_info.as_slice(), out);
        }
    }

    /// `R J` in place.
    pub fn whiten_jacobian(&self, j: &mut DMatrix<f64>) {
        if self.diagonal {
            for (row, s) in self.sqrt_info.diagonal().iter().enumerate() {
                j.row_mut(row).scale_mut(*s);
            }
        } else {
            let m = j.nrows();
            for col in j.as_mut_slice().chunks_exact_mut(m.max(1)) {
                upper_mul_in_place(self.sqrt_info.as_slice(), col);
            }
        }
    }

    /// `R J` for a Jacobian stored by rows: `rows` holds the `dim()` rows of `J`, each `width`
    /// long (a multiple of 4), one after the other; `out` (the same size) receives those of
    /// `R J`. Each row of the result is a sum of whole rows of `J` (contiguous, so the adds
    /// vectorise), accumulated in the same order as [`NoiseModel::whiten_jacobian`].
    pub(crate) fn whiten_rows(&self, rows: &[f64], width: usize, out: &mut [f64]) {
        let m = self.dim();
        debug_assert!(width.is_multiple_of(4) && rows.len() == m * width && out.len() == m * width);
        if self.diagonal {
            for ((o, x), s) in out
                .chunks_exact_mut(width)
                .zip(rows.chunks_exact(width))
                .zip(self.sqrt_info.diagonal().iter())
            {
                for (oi, xi) in o.iter_mut().zip(x) {
                    *oi = xi * s;
                }
            }
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { upper_mul_rows_avx2(self.sqrt_info.as_slice(), m, rows, width, out) };
            return;
        }
        upper_mul_rows(self.sqrt_info.as_slice(), m, rows, width, out);
    }

    /// The factor error of an unwhitened residual: `0.5 ||R r||^2`, or the kernel's loss.
    #[must_use]
    pub fn error(&self, r: &DVector<f64>) -> f64 {
        // Whitened on the stack (every factor's error is taken at every candidate step).
        let mut small = [0.0f64; 32];
        let d2 = match small.get_mut(..r.len()) {
            Some(w) => {
                self.whiten_into(r.as_slice(), w);
                w.iter().map(|x| x * x).sum()
            }
            None => self.whiten(r).norm_squared(),
        };
        match self.kernel {
            Some(k) => k.loss(d2.sqrt()),
            None => 0.5 * d2,
        }
    }

    /// The IRLS scale `sqrt(weight)` for a whitened residual.
    #[must_use]
    pub fn robust_scale(&self, whitened: &DVector<f64>) -> f64 {
        self.robust_scale_at(whitened.norm())
    }

    /// The IRLS scale for a whitened residual of norm `norm`.
    pub(crate) fn robust_scale_at(&self, norm: f64) -> f64 {
        self.kernel.map_or(1.0, |k| k.weight(norm).sqrt())
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn upper_mul_rows_avx2(r: &[f64], m: usize, rows: &[f64], width: usize, out: &mut [f64]) {
    upper_mul_rows(r, m, rows, width, out);
}

/// Row `i` of `R J` is the sum over `k >= i` of `R[i, k]` times row `k` of `J`, added in
/// increasing `k` (`R` upper-triangular `m x m`, column-major; rows `width` long, a multiple of
/// 4), 16 columns at a time held in registers across the sum.
#[inline(always)]
fn upper_mul_rows(r: &[f64], m: usize, rows: &[f64], width: usize, out: &mut [f64]) {
    for (i, o) in out.chunks_exact_mut(width).enumerate() {
        let (wide, rest) = o.as_chunks_mut::<16>();
        let mut c0 = 0;
        for chunk in wide {
            upper_mul_row_chunk(r, m, i, rows, width, c0, chunk);
            c0 += 16;
        }
        for chunk in rest.as_chunks_mut::<4>().0 {
            upper_mul_row_chunk(r, m, i, rows, width, c0, chunk);
            c0 += 4;
        }
    }
}

/// Columns `c0..c0 + N` of row `i` of `R J` (see [`upper_mul_rows`]).
#[inline(always)]
fn upper_mul_row_chunk<const N: usize>(
    r: &[f64],
    m: usize,
    i: usize,
    rows: &[f64],
    width: usize,
    c0: usize,
    out: &mut [f64; N],
) {
    let mut acc = [0.0f64; N];
    for k in i..m {
        let rik = r[k * m + i];
        let x = &rows[k * width + c0..][..N];
        for (a, xv) in acc.iter_mut().zip(x) {
            *a += rik * xv;
        }
    }
    *out = acc;
}

/// `x <- R x` for an upper-triangular `m x m` matrix `R` stored column-major, `m = x.len()`:
/// the columns of `R` scaled and added (contiguous, so the adds vectorise).
#[inline(always)]
fn upper_mul_in_place(r: &[f64], x: &mut [f64]) {
    let m = x.len();
    let mut small = [0.0f64; 32];
    let mut large = Vec::new();
    let y: &mut [f64] = if m <= small.len() {
        &mut small[..m]
    } else {
        large.resize(m, 0.0);
        &mut large
    };
    for (k, xk) in x.iter().enumerate() {
        if *xk == 0.0 {
            continue;
        }
        for (yi, rik) in y[..=k].iter_mut().zip(&r[k * m..=k * m + k]) {
            *yi += rik * xk;
        }
    }
    x.copy_from_slice(y);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_covariance_whitens_to_unit() {
        let cov = DMatrix::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 2.0]);
        let n = NoiseModel::from_covariance(&cov).expect("spd");
        let r = DVector::from_vec(vec![1.0, -2.0]);
        let expected = 0.5 * (r.transpose() * cov.clone().try_inverse().expect("inv") * &r)[0];
        assert!((n.error(&r) - expected).abs() < 1e-12);
    }

    #[test]
    fn in_place_whitening_matches_the_dense_product() {
        let cov = DMatrix::from_row_slice(3, 3, &[4.0, 1.0, 0.5, 1.0, 2.0, 0.3, 0.5, 0.3, 1.5]);
        let n = NoiseModel::from_covariance(&cov).expect("spd");
        let j = DMatrix::from_fn(3, 5, |r, c| (r * 5 + c) as f64 - 6.0);
        let mut w = j.clone();
        n.whiten_jacobian(&mut w);
        assert!((w - &n.sqrt_info * &j).norm() < 1e-12);
        let r = DVector::from_vec(vec![0.3, -1.0, 2.0]);
        assert!((n.whiten(&r) - &n.sqrt_info * &r).norm() < 1e-12);
    }

    #[test]
    fn huber_is_continuous_and_linear_outside() {
        let h = RobustKernel::Huber { k: 1.345 };
        assert!((h.loss(1.345 - 1e-9) - h.loss(1.345 + 1e-9)).abs() < 1e-8);
        assert!((h.loss(10.0) - h.loss(9.0) - 1.345).abs() < 1e-12);
        let c = RobustKernel::Cauchy { k: 1.0 };
        assert!(c.loss(100.0) < 5.0);
    }
}
