//! The spatial correlation (SPEC "Spatial correlation", §4.5.3) of reference and query features:
//! per channel the Pearson correlation of the shared block for every integer column shift, its
//! argmax refined by a parabola, giving the vector `v = [tau_1 .. tau_K, m_1 .. m_K]`
//! ([`CorrVector`]).

use super::encoder::Features;
use crate::{Error, Result};

/// A block whose variance is at most this fraction of its sum of squares counts as flat (its
/// norm as 0): the one-pass sums leave rounding noise where a constant block has none.
const FLAT_VARIANCE_FRACTION: f64 = 1e-12;

/// Parameters of the spatial correlation (SPEC "Spatial correlation").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrelationParams {
    /// Along-track size of a feature column, m (`resolution_m * column_stride`).
    pub column_m: f64,
    /// Largest shift tried either way, m.
    pub max_shift_m: f64,
    /// Smallest shared region, as a fraction of the feature columns, in (0, 1].
    pub min_overlap: f64,
}

impl CorrelationParams {
    fn check(&self) -> gprflow_params::Result {
        gprflow_params::positive("column_m", self.column_m)?;
        crate::check_shift_search(self.max_shift_m, self.min_overlap)
    }

    /// The largest shift tried, in columns, for `cols` feature columns: `floor(max_shift_m /
    /// column_m)`, and no more than leaves `ceil(min_overlap * cols)` columns shared.
    pub fn max_shift_cols(&self, cols: usize) -> usize {
        let min_shared = ((self.min_overlap * cols as f64).ceil() as usize).clamp(1, cols.max(1));
        let by_distance = (self.max_shift_m / self.column_m).floor();
        // `as` saturates: a huge ratio is bounded by the overlap below
        (by_distance as usize).min(cols.saturating_sub(min_shared))
    }
}

/// The correlation vector `v = [tau_1 .. tau_K, m_1 .. m_K]` (SPEC "corr-feat").
#[derive(Debug, Clone, PartialEq)]
pub struct CorrVector {
    /// `2K` values: the per-channel shifts `tau_k` (m), then the peak correlations `m_k`.
    pub values: Vec<f64>,
    /// Largest shift tried either way, columns (the shifts tried are `-T..=T`).
    pub max_shift_cols: usize,
}

impl CorrVector {
    /// Channels, `K`.
    pub fn channels(&self) -> usize {
        self.values.len() / 2
    }

    /// `tau_k`, m: where channel `k` correlates best.
    pub fn tau_m(&self) -> &[f64] {
        &self.values[..self.channels()]
    }

    /// `m_k`: the best correlation of channel `k`.
    pub fn peaks(&self) -> &[f64] {
        &self.values[self.channels()..]
    }

    /// `mean_k m_k`: "do these two share features" (§4.5.2).
    pub fn share_score(&self) -> f64 {
        let peaks = self.peaks();
        if peaks.is_empty() {
            return 0.0;
        }
        peaks.iter().sum::<f64>() / peaks.len() as f64
    }
}

/// The spatial correlation with its work buffers, reused from call to call.
///
/// Per channel, with `R` and `Q` the reference's and the query's `h x w` images, the shared
/// block of a shift `T` is the reference's columns `c + T` and the query's columns `c` for `c`
/// in `[max(0, -T), min(w, w - T))`. Its Pearson correlation needs `Σ AB`, `Σ A`, `Σ A²`,
/// `Σ B`, `Σ B²` over the block. The four single sums are differences of column prefix sums.
/// `Σ AB` is the `T`-th diagonal sum of the column cross-product matrix
/// `D[i][j] = Σ_rows R[row][i] Q[row][j]` (`i - j = T`), computed in `4 x 8` tiles (only those
/// that touch a shift tried) and added into the diagonals tile by tile, never stored whole. Then
/// `r = (Σ AB - Σ A Σ B / N) / sqrt((Σ A² - (Σ A)² / N) (Σ B² - (Σ B)² / N))`, in f64 (f32
/// products are exact in f64; the sums round as in any f64 order).
#[derive(Debug, Clone, Default)]
pub struct Correlator {
    /// One channel of the reference as f64 in panels of [`TILE_I`] columns (see
    /// [`prepare_channel`]).
    reference: Vec<f64>,
    /// One channel of the query as f64 in panels of [`TILE_J`] columns.
    query: Vec<f64>,
    /// Column prefix sums of one channel: reference `Σ`, reference `Σ x²`, query `Σ`, query
    /// `Σ x²`, `w + 1` each.
    prefix: Vec<f64>,
    /// `Σ AB` of one channel per shift tried, in increasing shift.
    products: Vec<f64>,
    /// `r(T)` of one channel for the shifts tried, in increasing shift.
    curve: Vec<f64>,
}

/// [`Correlator::correlate`] with fresh buffers.
///
/// # Errors
/// See [`Correlator::correlate`].
pub fn correlate(reference: &Features, query: &Features, params: &CorrelationParams) -> Result<CorrVector> {
    Correlator::default().correlate(reference, query, params)
}

impl Correlator {
    /// The correlation vector of `query` over `reference` (SPEC "Spatial correlation").
    ///
    /// # Errors
    /// Parameters out of range, features of inconsistent or different shapes, or a feature that
    /// is NaN or infinite.
    pub fn correlate(
        &mut self,
        reference: &Features,
        query: &Features,
        params: &CorrelationParams,
    ) -> Result<CorrVector> {
        params.check()?;
        reference.check("reference")?;
        query.check("query")?;
        if (reference.channels, reference.rows, reference.cols) != (query.channels, query.rows, query.cols) {
            return Err(Error::Shape(format!(
                "reference features {} x {} x {}, query features {} x {} x {}",
                reference.channels, reference.rows, reference.cols, query.channels, query.rows, query.cols
            )));
        }
        let (channels, h, w) = (reference.channels, reference.rows, reference.cols);
        let shape = ChannelShape {
            h,
            w,
            t_max: params.max_shift_cols(w),
        };
        let mut values = vec![0.0; 2 * channels];
        for k in 0..channels {
            self.channel(reference.channel(k), query.channel(k), shape, 0.0);
            // a NaN or infinite feature makes its channel's sum of squares so (finite f32 values
            // cannot overflow it)
            let (r_squares, q_squares) = (self.prefix[2 * w + 1], self.prefix[4 * w + 3]);
            for (features, what, total) in [(reference, "reference", r_squares), (query, "query", q_squares)] {
                if !total.is_finite() {
                    return Err(non_finite(features, what, k));
                }
            }
            let (tau_cols, peak) = refined_peak(&self.curve, shape.t_max);
            values[k] = tau_cols * params.column_m;
            values[channels + k] = peak;
        }
        Ok(CorrVector {
            values,
            max_shift_cols: shape.t_max,
        })
    }
}

impl Correlator {
    /// `r(T)` of one channel (`r`, `q`: `h x w`, row-major) into `self.curve` (`flat` where the
    /// shared block is flat in either), its column prefix sums left in `self.prefix`. Uses AVX2 and FMA where the CPU has them (fused
    /// multiply-adds: the result may differ from the portable one in the last bit).
    fn channel(&mut self, r: &[f32], q: &[f32], shape: ChannelShape, flat: f64) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA, checked just above.
            unsafe { self.channel_avx2(r, q, shape, flat) };
            return;
        }
        self.channel_with(r, q, shape, flat, |rp, qp, s, out| {
            shifted_products(rp, qp, s, out, |a, b, c| a * b + c)
        });
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn channel_avx2(&mut self, r: &[f32], q: &[f32], shape: ChannelShape, flat: f64) {
        self.channel_with(r, q, shape, flat, |rp, qp, s, out| {
            shifted_products_avx2(rp, qp, s, out)
        });
    }

    /// [`Correlator::channel`] with `products` for [`shifted_products`].
    #[inline(always)]
    fn channel_with(
        &mut self,
        r: &[f32],
        q: &[f32],
        shape: ChannelShape,
        flat: f64,
        products: impl Fn(&[f64], &[f64], ChannelShape, &mut [f64]),
    ) {
        let w = shape.w;
        self.prefix.clear();
        self.prefix.resize(4 * (w + 1), 0.0);
        let (r_sums, rest) = self.prefix.split_at_mut(w + 1);
        let (r_squares, rest) = rest.split_at_mut(w + 1);
        let (q_sums, q_squares) = rest.split_at_mut(w + 1);
        prepare_channel::<TILE_I, false>(r, shape, &mut self.reference, r_sums, r_squares);
        prepare_channel::<TILE_J, true>(q, shape, &mut self.query, q_sums, q_squares);
        let section = DIAGONALS_PAST_W + 2 * w;
        self.products.clear();
        self.products.resize(TILE_I * section, 0.0);
        products(&self.reference, &self.query, shape, &mut self.products);
        // the shifts tried, -t_max..=t_max: diagonal t is at t + w + TILE_J - 1 - a of section a
        let first = w + TILE_J - 1 - shape.t_max;
        for x in first..first + 2 * shape.t_max + 1 {
            let sum: f64 = (1..TILE_I).map(|a| self.products[a * section + x - a]).sum();
            self.products[x] += sum;
        }
        let tried = &self.products[first..first + 2 * shape.t_max + 1];
        channel_curve(shape, tried, &self.prefix, flat, &mut self.curve);
    }

    /// `r(T)` of one pair of `rows x cols` images (row-major; the engineered method's eq. 4.2
    /// on two submaps) for every shift `T` in `-t_max..=t_max`, in increasing shift; NaN where
    /// the shared block is flat in either image. `t_max` is at most `cols - 1`.
    ///
    /// # Errors
    /// Images that are not `rows x cols`, or `t_max` past the last column.
    pub fn shift_curve(
        &mut self,
        reference: &[f32],
        query: &[f32],
        rows: usize,
        cols: usize,
        t_max: usize,
    ) -> Result<&[f64]> {
        if rows == 0 || cols == 0 || reference.len() != rows * cols || query.len() != rows * cols || t_max >= cols {
            return Err(Error::Shape(format!(
                "images of {} and {} pixels for {rows} x {cols}, shifts to {t_max}",
                reference.len(),
                query.len()
            )));
        }
        self.channel(
            reference,
            query,
            ChannelShape {
                h: rows,
                w: cols,
                t_max,
            },
            f64::NAN,
        );
        Ok(&self.curve)
    }
}

/// Rows, columns and largest shift of one channel's images.
#[derive(Debug, Clone, Copy)]
struct ChannelShape {
    h: usize,
    w: usize,
    t_max: usize,
}

/// The error naming the first NaN or infinite value of channel `k`.
fn non_finite(features: &Features, what: &str, k: usize) -> Error {
    let channel = features.channel(k);
    let i = channel.iter().position(|v| !v.is_finite()).unwrap_or(0);
    Error::Shape(format!(
        "{what} features: channel {k}, row {}, col {} is {}",
        i / features.cols,
        i % features.cols,
        channel.get(i).copied().unwrap_or(f32::NAN)
    ))
}

/// One channel's `h x w` image (row-major) as f64 in panels of `W` columns into `panels`: per
/// panel `p`, per row, the columns `p W .. (p + 1) W` (zeros past the last column; in
/// decreasing order when `REVERSED`), so that a tile's rows are contiguous; and in the same
/// pass its column prefix sums of values and of squares into `sums` and `squares` (`w + 1`
/// each, entry `c` summing the columns `< c`).
#[inline(always)]
fn prepare_channel<const W: usize, const REVERSED: bool>(
    image: &[f32],
    shape: ChannelShape,
    panels: &mut Vec<f64>,
    sums: &mut [f64],
    squares: &mut [f64],
) {
    let ChannelShape { h, w, .. } = shape;
    panels.clear();
    panels.resize(w.div_ceil(W) * h * W, 0.0);
    let (sums, squares) = (&mut sums[1..], &mut squares[1..]);
    for (row, src) in image.chunks_exact(w).enumerate() {
        let full = src.chunks_exact(W);
        let rest = full.remainder();
        let (sum_full, square_full) = (sums.chunks_exact_mut(W), squares.chunks_exact_mut(W));
        for (p, (chunk, (sum, square))) in full.zip(sum_full.zip(square_full)).enumerate() {
            let dst = panels.get_mut((p * h + row) * W..(p * h + row + 1) * W);
            // fixed-size arrays: the loop below unrolls and vectorises
            let (Ok(chunk), Ok(sum), Ok(square), Some(Ok(dst))) = (
                <&[f32; W]>::try_from(chunk),
                <&mut [f64; W]>::try_from(sum),
                <&mut [f64; W]>::try_from(square),
                dst.map(<&mut [f64; W]>::try_from),
            ) else {
                continue;
            };
            let x: [f64; W] = std::array::from_fn(|o| f64::from(chunk[o]));
            for o in 0..W {
                sum[o] += x[o];
                square[o] += x[o] * x[o];
                dst[if REVERSED { W - 1 - o } else { o }] = x[o];
            }
        }
        if !rest.is_empty() {
            let (p, c0) = (w / W, w - rest.len());
            let Some(dst) = panels.get_mut((p * h + row) * W..(p * h + row + 1) * W) else {
                continue;
            };
            for (o, &v) in rest.iter().enumerate() {
                let x = f64::from(v);
                dst[if REVERSED { W - 1 - o } else { o }] = x;
                sums[c0 + o] += x;
                squares[c0 + o] += x * x;
            }
        }
    }
    for c in 1..w {
        sums[c] += sums[c - 1];
        squares[c] += squares[c - 1];
    }
}

/// `r(T)` for `T` in `-t_max..=t_max` of one channel into `curve`, from `products` (`Σ AB` per
/// shift) and `prefix` (reference sums, reference squares, query sums, query squares, as
/// [`prepare_channel`] leaves them); `flat_value` where either block is flat.
fn channel_curve(shape: ChannelShape, products: &[f64], prefix: &[f64], flat_value: f64, curve: &mut Vec<f64>) {
    let ChannelShape { h, w, t_max } = shape;
    let (pr, rest) = prefix.split_at(w + 1);
    let (prr, rest) = rest.split_at(w + 1);
    let (pq, pqq) = rest.split_at(w + 1);
    curve.clear();
    let t_max = t_max as isize;
    for (t, &sab) in (-t_max..=t_max).zip(products) {
        // query columns [q0, q1) over reference columns [q0 + t, q1 + t)
        let q0 = (-t).max(0) as usize;
        let q1 = (w as isize - t.max(0)) as usize;
        let (r0, r1) = ((q0 as isize + t) as usize, (q1 as isize + t) as usize);
        let count = (h * (q1 - q0)) as f64;
        let (sa, saa) = (pr[r1] - pr[r0], prr[r1] - prr[r0]);
        let (sb, sbb) = (pq[q1] - pq[q0], pqq[q1] - pqq[q0]);
        let var_a = saa - sa * sa / count;
        let var_b = sbb - sb * sb / count;
        let flat = |var: f64, sq: f64| var <= FLAT_VARIANCE_FRACTION * sq;
        let corr = if flat(var_a, saa) || flat(var_b, sbb) {
            flat_value
        } else {
            (sab - sa * sb / count) / (var_a.sqrt() * var_b.sqrt())
        };
        curve.push(corr);
    }
}

/// Reference columns per tile of `D` (and per reference panel).
const TILE_I: usize = 4;

/// Query columns per tile of `D` (and per query panel).
const TILE_J: usize = 8;

/// [`shifted_products`] with fused multiply-adds, compiled on its own (inlined into the rest,
/// the tile loop lost its vector registers).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline(never)]
fn shifted_products_avx2(r_panels: &[f64], q_panels: &[f64], shape: ChannelShape, out: &mut [f64]) {
    shifted_products(r_panels, q_panels, shape, out, f64::mul_add);
}

/// A section of [`shifted_products`]' `out` holds `2 w` and this many diagonals.
const DIAGONALS_PAST_W: usize = TILE_I + TILE_J - 1;

/// `Σ AB` of one channel for every shift added into `out`: the diagonal sums of
/// `D[i][j] = Σ_rows r[row][i] q[row][j]`, split by `a = i mod TILE_I` into `TILE_I` sections
/// of `2 w + DIAGONALS_PAST_W` (section `a` holds diagonal `i - j` at `i - j + w + TILE_J - 1 -
/// a`; apart, a tile's rows never store into overlapping ranges back to back), from the
/// channel's panels ([`prepare_channel`]: the reference in panels of [`TILE_I`]
/// columns, the query in panels of [`TILE_J`] columns in decreasing order, so that a tile's
/// row `a` holds the diagonals `ib - jb - 7 + a ..= ib - jb + a`, in increasing order); only
/// the tiles that touch a shift in `-t_max..=t_max`; `madd(a, b, c) = a b + c`.
#[inline(always)]
fn shifted_products(
    r_panels: &[f64],
    q_panels: &[f64],
    shape: ChannelShape,
    out: &mut [f64],
    madd: impl Fn(f64, f64, f64) -> f64,
) {
    let ChannelShape { h, w, t_max } = shape;
    let t_max = t_max as isize;
    let section_len = 2 * w + DIAGONALS_PAST_W;
    for (pi, r_panel) in r_panels.chunks_exact(h * TILE_I).enumerate() {
        let ib = pi * TILE_I;
        for (pj, q_panel) in q_panels.chunks_exact(h * TILE_J).enumerate() {
            let jb = pj * TILE_J;
            // the tile's shifts i - j span [ib - jb - 7, ib - jb + 3]
            let (lo, hi) = (
                ib as isize - (jb + TILE_J - 1) as isize,
                (ib + TILE_I - 1) as isize - jb as isize,
            );
            if hi < -t_max || lo > t_max {
                continue;
            }
            let mut acc = [[0.0f64; TILE_J]; TILE_I];
            for (ri, qj) in r_panel.chunks_exact(TILE_I).zip(q_panel.chunks_exact(TILE_J)) {
                for (acc_a, &ra) in acc.iter_mut().zip(ri) {
                    for (s, &qb) in acc_a.iter_mut().zip(qj) {
                        *s = madd(ra, qb, *s);
                    }
                }
            }
            // row a, lane l: i = ib + a, j = jb + 7 - l, at ib - jb + l + w of section a
            let base = ib + w - jb;
            for (section, acc_a) in out.chunks_exact_mut(section_len).zip(&acc) {
                let Some(dst) = section.get_mut(base..base + TILE_J) else {
                    continue;
                };
                for (d, &s) in dst.iter_mut().zip(acc_a) {
                    *d += s;
                }
            }
        }
    }
}

/// The argmax of `curve` (shifts `-t_max..=t_max`; the smallest shift on ties) refined by the
/// parabola through it and its neighbours: `(T* + delta, r(T*))`, in columns.
fn refined_peak(curve: &[f64], t_max: usize) -> (f64, f64) {
    let mut best = 0;
    for (i, &r) in curve.iter().enumerate() {
        if r > curve[best] {
            best = i;
        }
    }
    let Some(&peak) = curve.get(best) else {
        return (0.0, 0.0);
    };
    let mut delta = 0.0;
    if best > 0 && best + 1 < curve.len() {
        let (a, b, c) = (curve[best - 1], peak, curve[best + 1]);
        let denom = a - 2.0 * b + c;
        if denom < 0.0 {
            delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
        }
    }
    (best as f64 - t_max as f64 + delta, peak)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Agreement of the fast correlation with the direct one.
    const EXACT: f64 = 1e-9;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect()
    }

    fn features(k: usize, h: usize, w: usize, seed: u64) -> Features {
        Features {
            channels: k,
            rows: h,
            cols: w,
            data: random(k * h * w, seed),
        }
    }

    /// Pearson correlation of the shared block, two passes, straight from the definition.
    fn direct_r(r: &[f32], q: &[f32], h: usize, w: usize, t: i64) -> f64 {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for row in 0..h {
            for c in 0..w as i64 {
                let rc = c + t;
                if (0..w as i64).contains(&rc) {
                    a.push(f64::from(r[row * w + rc as usize]));
                    b.push(f64::from(q[row * w + c as usize]));
                }
            }
        }
        let n = a.len() as f64;
        let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
        let ab: f64 = a.iter().zip(&b).map(|(x, y)| (x - ma) * (y - mb)).sum();
        let aa: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
        let bb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
        if aa == 0.0 || bb == 0.0 {
            0.0
        } else {
            ab / (aa.sqrt() * bb.sqrt())
        }
    }

    /// The correlation vector straight from SPEC.
    fn direct(reference: &Features, query: &Features, p: &CorrelationParams) -> Vec<f64> {
        let (k, h, w) = (reference.channels, reference.rows, reference.cols);
        let t_max = (p.max_shift_m / p.column_m).floor() as i64;
        let min_shared = (p.min_overlap * w as f64).ceil() as i64;
        let shifts: Vec<i64> = (-t_max..=t_max).filter(|t| w as i64 - t.abs() >= min_shared).collect();
        let mut v = vec![0.0; 2 * k];
        for ch in 0..k {
            let curve: Vec<f64> = shifts
                .iter()
                .map(|&t| direct_r(reference.channel(ch), query.channel(ch), h, w, t))
                .collect();
            let mut best = 0;
            for i in 0..curve.len() {
                if curve[i] > curve[best] {
                    best = i;
                }
            }
            let mut delta = 0.0;
            if best > 0 && best + 1 < curve.len() {
                let (a, b, c) = (curve[best - 1], curve[best], curve[best + 1]);
                if a - 2.0 * b + c < 0.0 {
                    delta = (0.5 * (a - c) / (a - 2.0 * b + c)).clamp(-0.5, 0.5);
                }
            }
            v[ch] = (shifts[best] as f64 + delta) * p.column_m;
            v[k + ch] = curve[best];
        }
        v
    }

    const PARAMS: CorrelationParams = CorrelationParams {
        column_m: 0.06,
        max_shift_m: 1.5,
        min_overlap: 0.5,
    };

    #[test]
    fn fast_correlation_matches_the_direct_one_on_random_features() {
        let mut corr = Correlator::default();
        for (seed, (k, h, w)) in [(3, 7, 11), (2, 1, 1), (4, 13, 50), (1, 5, 8), (2, 9, 33)]
            .into_iter()
            .enumerate()
        {
            for params in [
                PARAMS,
                CorrelationParams {
                    max_shift_m: 0.2,
                    ..PARAMS
                },
                CorrelationParams {
                    min_overlap: 1.0,
                    ..PARAMS
                },
                CorrelationParams {
                    min_overlap: 0.1,
                    max_shift_m: 100.0,
                    ..PARAMS
                },
            ] {
                let r = features(k, h, w, 2 * seed as u64 + 1);
                let mut q = features(k, h, w, 2 * seed as u64 + 2);
                // a correlated query: the reference moved by 3 columns plus noise
                for ch in 0..k {
                    for row in 0..h {
                        for c in 0..w.saturating_sub(3) {
                            let i = (ch * h + row) * w + c;
                            q.data[i] = r.data[(ch * h + row) * w + c + 3] + 0.3 * q.data[i];
                        }
                    }
                }
                let fast = corr.correlate(&r, &q, &params).expect("valid");
                let slow = direct(&r, &q, &params);
                for (i, (a, b)) in fast.values.iter().zip(&slow).enumerate() {
                    assert!((a - b).abs() <= EXACT, "{k}x{h}x{w} {params:?}: v[{i}] {a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn the_portable_arithmetic_matches_the_dispatched_one() {
        let (h, w) = (9, 37);
        let (r, q) = (features(1, h, w, 11), features(1, h, w, 12));
        let shape = ChannelShape { h, w, t_max: 17 };
        let mut corr = Correlator::default();
        corr.channel(&r.data, &q.data, shape, 0.0);
        let dispatched = corr.curve.clone();
        corr.channel_with(&r.data, &q.data, shape, 0.0, |rp, qp, s, out| {
            shifted_products(rp, qp, s, out, |a, b, c| a * b + c)
        });
        assert_eq!(dispatched.len(), 2 * 17 + 1);
        for (t, (a, b)) in dispatched.iter().zip(&corr.curve).enumerate() {
            assert!((a - b).abs() <= 1e-12, "shift {}: {a} vs {b}", t as i64 - 17);
        }
    }

    #[test]
    fn a_shifted_feature_image_peaks_at_its_shift() {
        let (k, h, w) = (2, 10, 40);
        let wide = features(k, h, w + 10, 7);
        let crop = |c0: usize| Features {
            channels: k,
            rows: h,
            cols: w,
            data: (0..k * h)
                .flat_map(|kr| wide.data[kr * (w + 10) + c0..kr * (w + 10) + c0 + w].to_vec())
                .collect(),
        };
        // query column c is the wide image's column c + 6, the reference's column c + 4
        let (reference, query) = (crop(2), crop(6));
        let v = correlate(&reference, &query, &PARAMS).expect("valid");
        for ch in 0..k {
            // the parabola through noise-level neighbours moves it a little
            assert!(
                (v.tau_m()[ch] - 4.0 * PARAMS.column_m).abs() < 0.1 * PARAMS.column_m,
                "{:?}",
                v.tau_m()
            );
            assert!((v.peaks()[ch] - 1.0).abs() < 1e-9);
        }
        assert!((v.share_score() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn flat_channels_correlate_as_zero_and_bad_features_are_refused() {
        let mut a = features(2, 4, 10, 1);
        let mut b = features(2, 4, 10, 2);
        a.data[..40].fill(0.0);
        b.data[..40].fill(2.5);
        let v = correlate(&a, &b, &PARAMS).expect("valid");
        assert_eq!(v.peaks()[0], 0.0);
        assert_eq!(v.tau_m()[0], -(PARAMS.max_shift_cols(10) as f64) * PARAMS.column_m);
        b.data[45] = f32::NAN;
        let e = correlate(&a, &b, &PARAMS).expect_err("NaN");
        assert!(
            e.to_string().contains("query features: channel 1, row 0, col 5 is NaN"),
            "{e}"
        );
        let e = correlate(&a, &features(2, 4, 9, 3), &PARAMS).expect_err("shape");
        assert!(e.to_string().contains("4 x 9"), "{e}");
        let e = correlate(
            &a,
            &a,
            &CorrelationParams {
                column_m: 0.0,
                ..PARAMS
            },
        )
        .expect_err("column");
        assert!(e.to_string().starts_with("column_m:"), "{e}");
    }

    proptest::proptest! {
        #[test]
        fn correlation_of_any_features_is_bounded(
            data in proptest::collection::vec(-1e3f32..1e3, 2 * 3 * 12),
            max_shift_m in 0.0f64..5.0,
        ) {
            let r = Features { channels: 2, rows: 3, cols: 12, data: data[..72].to_vec() };
            let q = Features { channels: 2, rows: 3, cols: 12, data: data.iter().rev().copied().collect() };
            let v = correlate(&r, &q, &CorrelationParams { max_shift_m, ..PARAMS }).expect("valid");
            for &m in v.peaks() {
                proptest::prop_assert!((-1.0 - 1e-9..=1.0 + 1e-9).contains(&m));
            }
        }
    }
}
