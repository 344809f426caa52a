//! Hyperbola detection in a GPR submap by diffraction stacking (seed 000 §2.2.3, §5.2.3).
//!
//! A point or line reflector at along-track position `x0` and two-way time `t0` appears in a
//! B-scan on the hyperbola `t(x) = sqrt(t0^2 + (2 (x - x0) / v)^2)`, `v` the wave velocity in
//! the ground (for a line crossed at angle `phi`, `v / sin(phi)`). For every trial velocity
//! and every apex the image is summed along that curve over `half_aperture_m` each side of
//! the apex (samples linearly interpolated in time), and the mean divided by the image's
//! robust noise level (1.4826 x the median absolute value) is the apex's *score*: the mean
//! amplitude along the hyperbola in noise standard deviations. Apexes whose aperture does not
//! fit in the image are not searched, so a hyperbola is only reported once it is whole.
//! Local maxima of the best score over the velocities, at least `min_score`, are the
//! detections, strongest first; one whose apex lies on a stronger one's curve (within
//! `separation_ns`, along track within twice the half aperture plus `separation_m`) is that
//! hyperbola's flank, matched by a slower curve tangent to it, and is dropped.

use gprflow_params::positive;

use crate::{Error, ParamError, Result};

/// A submap image: `rows` samples (time, `sample_interval_ns` apart, row 0 at time zero) by
/// `cols` along-track columns (`resolution_m` apart), row-major.
#[derive(Debug, Clone, Copy)]
pub struct Image<'a> {
    /// `rows * cols` values, row-major.
    pub pixels: &'a [f32],
    /// Samples per column.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Along-track size of one column, m.
    pub resolution_m: f64,
    /// Time between two samples, ns.
    pub sample_interval_ns: f64,
}

/// Parameters of [`detect`].
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct DetectParams {
    /// Slowest trial velocity, m/ns (default 0.06: wet soil, eps_r 25).
    pub min_velocity_m_per_ns: f64,
    /// Fastest trial velocity, m/ns (default 0.3: a line crossed at 25 degrees in dry soil).
    pub max_velocity_m_per_ns: f64,
    /// Number of trial velocities, geometrically spaced (default 10).
    pub velocities: usize,
    /// Along-track half width of the summed hyperbola, m (default 0.45).
    pub half_aperture_m: f64,
    /// Earliest apex searched, ns (default 4: below the direct wave and the surface).
    pub min_apex_time_ns: f64,
    /// Smallest score reported: mean amplitude along the hyperbola in noise sigmas (default
    /// 20; on the simulator's pipe fields pipes score 50-65 and the soil's own scatterers at
    /// most 17).
    pub min_score: f64,
    /// A weaker apex within this much beyond twice the half aperture of a stronger one ...
    pub separation_m: f64,
    /// ... and this close in time to that one's curve is its flank and dropped; also how
    /// close two submaps' apexes are to be one hyperbola. Defaults 0.3 m, 3 ns.
    pub separation_ns: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        Self {
            min_velocity_m_per_ns: 0.06,
            max_velocity_m_per_ns: 0.3,
            velocities: 10,
            half_aperture_m: 0.45,
            min_apex_time_ns: 4.0,
            min_score: 20.0,
            separation_m: 0.3,
            separation_ns: 3.0,
        }
    }
}

impl DetectParams {
    /// Checks every value; the error names the key.
    ///
    /// # Errors
    /// A value out of range.
    pub fn check(&self) -> gprflow_params::Result {
        positive("detect.min_velocity_m_per_ns", self.min_velocity_m_per_ns)?;
        positive("detect.max_velocity_m_per_ns", self.max_velocity_m_per_ns)?;
        if self.max_velocity_m_per_ns < self.min_velocity_m_per_ns {
            return Err(ParamError::new(
                "detect.max_velocity_m_per_ns",
                format!(
                    "must be at least min_velocity_m_per_ns ({}), got {}",
                    self.min_velocity_m_per_ns, self.max_velocity_m_per_ns
                ),
            ));
        }
        if !(1..=64).contains(&self.velocities) {
            return Err(ParamError::new(
                "detect.velocities",
                format!("must be 1..=64, got {}", self.velocities),
            ));
        }
        positive("detect.half_aperture_m", self.half_aperture_m)?;
        positive("detect.min_score", self.min_score)?;
        positive("detect.separation_m", self.separation_m)?;
        positive("detect.separation_ns", self.separation_ns)?;
        if !(self.min_apex_time_ns.is_finite() && self.min_apex_time_ns >= 0.0) {
            return Err(ParamError::new(
                "detect.min_apex_time_ns",
                format!("must be a number >= 0, got {}", self.min_apex_time_ns),
            ));
        }
        Ok(())
    }

    /// The trial velocities, slowest first.
    pub fn trial_velocities(&self) -> Vec<f64> {
        let n = self.velocities;
        if n == 1 {
            return vec![self.min_velocity_m_per_ns];
        }
        let ratio = self.max_velocity_m_per_ns / self.min_velocity_m_per_ns;
        (0..n)
            .map(|j| self.min_velocity_m_per_ns * ratio.powf(j as f64 / (n - 1) as f64))
            .collect()
    }
}

/// A detected hyperbola.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hyperbola {
    /// Apex column (fractional; column centres at integers).
    pub apex_column: f64,
    /// Two-way time of the apex, ns.
    pub apex_time_ns: f64,
    /// Trial velocity that fits it best, m/ns.
    pub velocity_m_per_ns: f64,
    /// Mean amplitude along the hyperbola in noise standard deviations.
    pub score: f64,
}

impl Hyperbola {
    /// The hyperbola's time at a column, ns.
    pub fn time_at_ns(&self, column: f64, resolution_m: f64) -> f64 {
        let dx_m = (column - self.apex_column) * resolution_m;
        let dt = 2.0 * dx_m / self.velocity_m_per_ns;
        self.apex_time_ns.hypot(dt)
    }
}

/// The image's robust noise level: 1.4826 x the median absolute value of the rows searched.
fn noise_sigma(pixels: &[f32]) -> f64 {
    let mut mags: Vec<f32> = pixels.iter().map(|v| v.abs()).collect();
    if mags.is_empty() {
        return 0.0;
    }
    let mid = mags.len() / 2;
    let median = *mags.select_nth_unstable_by(mid, f32::total_cmp).1;
    1.4826 * f64::from(median)
}

/// Finds the hyperbolas of `image`, strongest first.
///
/// # Errors
/// [`Error::Shape`] for pixels that do not match `rows x cols`, a non-finite value or a
/// non-positive resolution or sample interval; [`Error::Param`] for bad parameters.
pub fn detect(image: &Image<'_>, params: &DetectParams) -> Result<Vec<Hyperbola>> {
    params.check()?;
    let Image {
        pixels,
        rows,
        cols,
        resolution_m: dx,
        sample_interval_ns: dt,
    } = *image;
    if pixels.len() != rows * cols {
        return Err(Error::Shape(format!("{} pixels for {rows} x {cols}", pixels.len())));
    }
    if !(dx.is_finite() && dx > 0.0 && dt.is_finite() && dt > 0.0) {
        return Err(Error::Shape(format!(
            "resolution {dx} m and sample interval {dt} ns must be positive"
        )));
    }
    if let Some(i) = pixels.iter().position(|v| !v.is_finite()) {
        return Err(Error::Shape(format!(
            "pixel {i} (row {}, column {}) is {}",
            i / cols,
            i % cols,
            pixels[i]
        )));
    }
    let half = (params.half_aperture_m / dx).round() as usize;
    let first_row = (params.min_apex_time_ns / dt).ceil() as usize;
    if half == 0 || cols < 2 * half + 1 || rows < 2 || first_row >= rows {
        return Ok(Vec::new());
    }
    let sigma = noise_sigma(&pixels[first_row * cols..]);
    if sigma <= 0.0 {
        return Ok(Vec::new());
    }
    let velocities = params.trial_velocities();
    let width = cols - 2 * half; // apex columns half..cols-half
    // best score and its velocity index per apex (row, column - half)
    let mut best = vec![0.0f64; rows * width];
    let mut best_v = vec![0u8; rows * width];
    let mut acc = vec![0.0f32; width];
    // the curve must stay in the image over at least half the aperture
    let min_reach = half.div_ceil(2);
    let last_row = (rows - 1) as f64;
    for (j, &v) in velocities.iter().enumerate() {
        let slope = 2.0 * dx / (v * dt); // rows per column, squared under the root
        for r0 in first_row..rows {
            let centre = &pixels[r0 * cols + half..r0 * cols + half + width];
            acc.copy_from_slice(centre);
            let mut count = 1usize;
            for k in 1..=half {
                let r = (r0 as f64).hypot(slope * k as f64);
                if r > last_row {
                    break;
                }
                let lo = r.floor() as usize;
                let hi = (lo + 1).min(rows - 1);
                let w = (r - lo as f64) as f32;
                // columns c0 - k and c0 + k for every apex column c0 = half + i
                let (left, right) = (half - k, half + k);
                let span = |row: usize, from: usize| &pixels[row * cols + from..row * cols + from + width];
                let (ll, lh, rl, rh) = (span(lo, left), span(hi, left), span(lo, right), span(hi, right));
                for ((((a, ll), lh), rl), rh) in acc.iter_mut().zip(ll).zip(lh).zip(rl).zip(rh) {
                    *a += (ll + rl) * (1.0 - w) + (lh + rh) * w;
                }
                count = 2 * k + 1;
            }
            if count < 2 * min_reach + 1 {
                continue;
            }
            let norm = 1.0 / (count as f64 * sigma);
            let row_best = &mut best[r0 * width..(r0 + 1) * width];
            let row_v = &mut best_v[r0 * width..(r0 + 1) * width];
            for ((b, bv), a) in row_best.iter_mut().zip(row_v.iter_mut()).zip(&acc) {
                let s = f64::from(a.abs()) * norm;
                if s > *b {
                    *b = s;
                    *bv = j as u8;
                }
            }
        }
    }
    let map = ScoreMap {
        best,
        best_v,
        rows,
        width,
        half,
        first_row,
    };
    Ok(map.peaks(&velocities, image, params))
}

/// The best score over the trial velocities per apex: `rows x width`, column `i` is image
/// column `half + i`; rows before `first_row` are not searched.
struct ScoreMap {
    best: Vec<f64>,
    best_v: Vec<u8>,
    rows: usize,
    width: usize,
    half: usize,
    first_row: usize,
}

impl ScoreMap {
    /// Local maxima at or above `min_score`, refined to a fraction of a pixel and thinned.
    fn peaks(&self, velocities: &[f64], image: &Image<'_>, params: &DetectParams) -> Vec<Hyperbola> {
        let Self {
            best,
            best_v,
            rows,
            width,
            half,
            first_row,
        } = self;
        let (rows, width, half, first_row) = (*rows, *width, *half, *first_row);
        let at = |r: usize, i: usize| best[r * width + i];
        let mut found = Vec::new();
        for r in first_row..rows {
            for i in 0..width {
                let s = at(r, i);
                if s < params.min_score {
                    continue;
                }
                let mut is_max = true;
                for (dr, di) in [
                    (-1i64, -1i64),
                    (-1, 0),
                    (-1, 1),
                    (0, -1),
                    (0, 1),
                    (1, -1),
                    (1, 0),
                    (1, 1),
                ] {
                    let (rr, ii) = (r as i64 + dr, i as i64 + di);
                    if rr < first_row as i64 || rr >= rows as i64 || ii < 0 || ii >= width as i64 {
                        continue;
                    }
                    let n = at(rr as usize, ii as usize);
                    // ties go to the earlier neighbour, so a plateau gives one maximum
                    if n > s || (n == s && (dr, di) < (0, 0)) {
                        is_max = false;
                        break;
                    }
                }
                if !is_max {
                    continue;
                }
                let refine = |m: f64, c: f64, p: f64| {
                    let den = m - 2.0 * c + p;
                    if den < 0.0 {
                        (0.5 * (m - p) / den).clamp(-0.5, 0.5)
                    } else {
                        0.0
                    }
                };
                let di = if i > 0 && i + 1 < width {
                    refine(at(r, i - 1), s, at(r, i + 1))
                } else {
                    0.0
                };
                let dr = if r > first_row && r + 1 < rows {
                    refine(at(r - 1, i), s, at(r + 1, i))
                } else {
                    0.0
                };
                found.push(Hyperbola {
                    apex_column: (half + i) as f64 + di,
                    apex_time_ns: (r as f64 + dr) * image.sample_interval_ns,
                    velocity_m_per_ns: velocities[usize::from(best_v[r * width + i])],
                    score: s,
                });
            }
        }
        found.sort_by(|a, b| b.score.total_cmp(&a.score));
        let mut kept: Vec<Hyperbola> = Vec::new();
        for h in found {
            // on a stronger one's curve near it: its flank, not a hyperbola of its own
            let near = kept.iter().any(|k| {
                ((k.apex_column - h.apex_column) * image.resolution_m).abs()
                    < 2.0 * params.half_aperture_m + params.separation_m
                    && (k.time_at_ns(h.apex_column, image.resolution_m) - h.apex_time_ns).abs() < params.separation_ns
            });
            if !near {
                kept.push(h);
            }
        }
        kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Ricker-like wavelet of `width_ns` centred on `t_ns`, at time `at_ns`.
    fn wavelet(at_ns: f64, t_ns: f64, width_ns: f64) -> f64 {
        let u = (at_ns - t_ns) / width_ns;
        (1.0 - 2.0 * u * u) * (-u * u).exp()
    }

    struct Scene {
        rows: usize,
        cols: usize,
        dx: f64,
        dt: f64,
    }

    impl Scene {
        /// Hyperbolas `(apex column, apex time, velocity, amplitude)` plus seeded noise of `noise` std.
        fn image(&self, hyperbolas: &[(f64, f64, f64, f64)], noise: f64, seed: u64) -> Vec<f32> {
            let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let mut gauss = || {
                // sum of 12 uniforms: close enough to a gaussian for a test image
                let mut s = 0.0;
                for _ in 0..12 {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    s += (state >> 11) as f64 / (1u64 << 53) as f64;
                }
                s - 6.0
            };
            let mut px = vec![0.0f32; self.rows * self.cols];
            for r in 0..self.rows {
                for c in 0..self.cols {
                    let t = r as f64 * self.dt;
                    let mut v = noise * gauss();
                    for &(c0, t0, vel, amp) in hyperbolas {
                        let h = Hyperbola {
                            apex_column: c0,
                            apex_time_ns: t0,
                            velocity_m_per_ns: vel,
                            score: 0.0,
                        };
                        // spherical spreading and a beam of about 0.5 m, as in real B-scans
                        let th = h.time_at_ns(c as f64, self.dx);
                        let off_m = (c as f64 - c0) * self.dx;
                        let fade = (t0 / th).powi(2) * (-(off_m / 0.5).powi(2)).exp();
                        v += amp * fade * wavelet(t, th, 0.6);
                    }
                    px[r * self.cols + c] = v as f32;
                }
            }
            px
        }

        fn view<'a>(&self, px: &'a [f32]) -> Image<'a> {
            Image {
                pixels: px,
                rows: self.rows,
                cols: self.cols,
                resolution_m: self.dx,
                sample_interval_ns: self.dt,
            }
        }
    }

    /// The defaults with a threshold for the clean synthetic images below.
    fn params() -> DetectParams {
        DetectParams {
            min_score: 3.0,
            ..DetectParams::default()
        }
    }

    const SCENE: Scene = Scene {
        rows: 201,
        cols: 200,
        dx: 0.015,
        dt: 0.2,
    };

    #[test]
    fn finds_a_hyperbola_in_noise_at_its_apex() {
        let px = SCENE.image(&[(117.3, 10.0, 0.12, 1.0)], 0.05, 1);
        let found = detect(&SCENE.view(&px), &params()).expect("detect");
        assert_eq!(found.len(), 1, "{found:?}");
        let h = found[0];
        assert!((h.apex_column - 117.3).abs() < 1.0, "{h:?}");
        // the stack peaks on the wavelet's main lobe
        assert!((h.apex_time_ns - 10.0).abs() < 0.4, "{h:?}");
        assert!((h.velocity_m_per_ns - 0.12).abs() < 0.03, "{h:?}");
        assert!(h.score > 3.0, "{h:?}");
    }

    #[test]
    fn oblique_crossings_fit_faster_velocities() {
        let px = SCENE.image(&[(90.0, 12.0, 0.24, 1.0)], 0.1, 2);
        let found = detect(&SCENE.view(&px), &params()).expect("detect");
        assert_eq!(found.len(), 1, "{found:?}");
        assert!((found[0].velocity_m_per_ns - 0.24).abs() < 0.05, "{found:?}");
        assert!((found[0].apex_column - 90.0).abs() < 1.0, "{found:?}");
    }

    #[test]
    fn two_hyperbolas_are_two_detections() {
        let px = SCENE.image(&[(60.0, 8.0, 0.12, 1.0), (140.0, 20.0, 0.12, 0.8)], 0.05, 3);
        let mut found = detect(&SCENE.view(&px), &params()).expect("detect");
        found.sort_by(|a, b| a.apex_column.total_cmp(&b.apex_column));
        assert_eq!(found.len(), 2, "{found:?}");
        assert!((found[0].apex_column - 60.0).abs() < 1.0 && (found[0].apex_time_ns - 8.0).abs() < 0.4);
        // the apex time is that of the stack's strongest lobe: for the deeper, fainter one a
        // side lobe of the wavelet, 0.73 ns from its centre
        assert!(
            (found[1].apex_column - 140.0).abs() < 1.0 && (found[1].apex_time_ns - 20.0).abs() < 0.8,
            "{found:?}"
        );
    }

    #[test]
    fn noise_alone_and_cut_hyperbolas_are_not_detections() {
        let px = SCENE.image(&[], 1.0, 4);
        assert!(detect(&SCENE.view(&px), &params()).expect("detect").is_empty());
        // apex 0.1 m from the edge: its aperture does not fit, it is reported by a later submap
        let px = SCENE.image(&[(6.0, 10.0, 0.12, 1.0)], 0.05, 5);
        let found = detect(&SCENE.view(&px), &params()).expect("detect");
        assert!(found.iter().all(|h| h.apex_column > 25.0), "{found:?}");
    }

    #[test]
    fn bad_images_and_params_are_errors_naming_what() {
        let px = vec![0.0f32; 10];
        let img = Image {
            pixels: &px,
            rows: 3,
            cols: 4,
            resolution_m: 0.01,
            sample_interval_ns: 0.1,
        };
        let e = detect(&img, &DetectParams::default()).expect_err("size");
        assert!(e.to_string().contains("10 pixels for 3 x 4"), "{e}");
        let mut px = vec![0.0f32; 12];
        px[5] = f32::NAN;
        let e = detect(&Image { pixels: &px, ..img }, &DetectParams::default()).expect_err("nan");
        assert!(e.to_string().contains("row 1, column 1"), "{e}");
        let p = DetectParams {
            max_velocity_m_per_ns: 0.01,
            ..DetectParams::default()
        };
        let e = p.check().expect_err("order");
        assert!(e.to_string().starts_with("detect.max_velocity_m_per_ns"), "{e}");
    }

    #[test]
    fn empty_and_tiny_images_have_no_hyperbolas() {
        for (rows, cols) in [(0, 0), (0, 50), (50, 0), (1, 1), (201, 10)] {
            let px = vec![1.0f32; rows * cols];
            let img = Image {
                pixels: &px,
                rows,
                cols,
                resolution_m: 0.015,
                sample_interval_ns: 0.2,
            };
            assert!(detect(&img, &DetectParams::default()).expect("detect").is_empty());
        }
    }
}
