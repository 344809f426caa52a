//! The fit criterion of the registration (seed 001 eq. 8): the correlation between the sweep
//! `A` and the slice `B` of the grid under the array at a candidate 5-DOF pose,
//! `sum A B / sqrt(sum A^2 sum B^2)` over every channel over mapped data and the window's depth
//! bins.
//!
//! The pose is `[x, y, dh, yaw, roll]`: the body's world position (m), its height above the
//! mapping pass's (m), heading (rad, from x towards y) and roll (rad, left side up). Channel
//! `k`, at lateral offset `o_k` (body y, mount included) and forward offset `mount_x`, reads
//! the grid point nearest its world position, and its samples are compared with the grid's
//! moved by `round(2 dz_k / c / dt)` samples, `dz_k = dh + o_k sin(roll)`: a higher element hears
//! the same echoes later by the extra two-way path in air.

use crate::array::ArrayGeometry;
use crate::map::LocalGrid;

/// Speed of light, m/ns.
pub const C_M_PER_NS: f64 = 0.299_792_458;

/// A 5-DOF pose: `[x, y, dh, yaw, roll]` (m, m, m, rad, rad).
pub type Pose5 = [f64; 5];

/// The correlation at one pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correlation {
    /// Eq. 8, in `[-1, 1]`; 0 when no channel is over mapped data.
    pub value: f64,
    /// Channels over mapped data.
    pub overlap: u32,
}

/// A sweep ready to be correlated: each channel's window of depth bins and its energy.
#[derive(Debug, Clone, Default)]
pub struct PreparedSweep {
    channels: usize,
    start: usize,
    len: usize,
    /// Channel `k`'s window at `a[k * len..(k + 1) * len]`.
    a: Vec<f32>,
    aa: Vec<f32>,
    offsets: Vec<f64>,
    mount_x: f64,
}

impl PreparedSweep {
    /// An empty sweep for `channels` channels at `geometry`, window `[start, start + len)`.
    pub fn new(geometry: &ArrayGeometry, channels: usize, start: usize, len: usize) -> Self {
        Self {
            channels,
            start,
            len,
            a: vec![0.0; channels * len],
            aa: vec![0.0; channels],
            offsets: geometry.channel_offsets_m(channels),
            mount_x: geometry.mount_m[0],
        }
    }

    /// Channels.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Lateral offset of each channel (mount included), m.
    pub fn offsets(&self) -> &[f64] {
        &self.offsets
    }

    /// Loads a sweep of `channels x samples` values (channel-major). Returns `false` (and
    /// leaves the sweep unusable) when its size does not fit or the window runs past its end.
    pub fn load(&mut self, values: &[f32], samples: usize) -> bool {
        if values.len() != self.channels * samples || self.start + self.len > samples {
            return false;
        }
        for k in 0..self.channels {
            let src = &values[k * samples + self.start..k * samples + self.start + self.len];
            let dst = &mut self.a[k * self.len..(k + 1) * self.len];
            dst.copy_from_slice(src);
            self.aa[k] = dot(src, src);
        }
        true
    }

    /// Loads a sweep as [`PreparedSweep::load`], its travel times below `origin` (a sample
    /// position: the ground surface) scaled by `1 / stretch`: window sample `d` takes the
    /// sweep's value at `origin + stretch (d - origin)`, linearly interpolated. A sweep
    /// through wetter (slower) soil than the map's has its echoes late by a factor
    /// `stretch > 1`; so loaded, it lines up with the map again.
    pub fn load_stretched(&mut self, values: &[f32], samples: usize, stretch: f64, origin: f64) -> bool {
        if stretch == 1.0 {
            return self.load(values, samples);
        }
        if values.len() != self.channels * samples || self.start + self.len > samples {
            return false;
        }
        let last = (samples - 1) as f64;
        for k in 0..self.channels {
            let src = &values[k * samples..(k + 1) * samples];
            let dst = &mut self.a[k * self.len..(k + 1) * self.len];
            for (j, out) in dst.iter_mut().enumerate() {
                let d = (self.start + j) as f64;
                let at = if d <= origin {
                    d
                } else {
                    (origin + stretch * (d - origin)).min(last)
                };
                let i = at.floor() as usize;
                let f = (at - i as f64) as f32;
                let next = src[(i + 1).min(samples - 1)];
                *out = src[i] + f * (next - src[i]);
            }
            self.aa[k] = dot(dst, dst);
        }
        true
    }
}

/// `sum a b` with eight independent partial sums (vectorises).
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0_f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// `(sum a b, sum b b)` in one pass.
#[inline]
fn dot_and_energy(a: &[f32], b: &[f32]) -> (f32, f32) {
    let mut ab = [0.0_f32; 8];
    let mut bb = [0.0_f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            ab[l] += x[l] * y[l];
            bb[l] += y[l] * y[l];
        }
    }
    let (mut s_ab, mut s_bb): (f32, f32) = (ab.iter().sum(), bb.iter().sum());
    for (x, y) in ra.iter().zip(rb) {
        s_ab += x * y;
        s_bb += y * y;
    }
    (s_ab, s_bb)
}

/// Evaluates eq. 8 against one grid.
#[derive(Debug, Clone, Copy)]
pub struct Correlator<'g> {
    grid: &'g LocalGrid,
    /// Samples of shift per metre of height.
    samples_per_m: f64,
}

impl<'g> Correlator<'g> {
    /// A correlator on `grid`, whose samples are `sample_interval_ns` apart.
    pub fn new(grid: &'g LocalGrid, sample_interval_ns: f64) -> Self {
        Self {
            grid,
            samples_per_m: 2.0 / C_M_PER_NS / sample_interval_ns,
        }
    }

    /// Eq. 8 for `sweep` at `pose`.
    pub fn correlate(&self, sweep: &PreparedSweep, pose: &Pose5) -> Correlation {
        let [x, y, dh, yaw, roll] = *pose;
        let (sy, cy) = yaw.sin_cos();
        let sin_roll = roll.sin();
        let samples = self.grid.samples();
        let max_start = samples.saturating_sub(sweep.len) as i64;
        let (mut ab, mut aa, mut bb) = (0.0_f64, 0.0_f64, 0.0_f64);
        let mut overlap = 0;
        for (k, &o) in sweep.offsets.iter().enumerate() {
            let wx = x + cy * sweep.mount_x - sy * o;
            let wy = y + sy * sweep.mount_x + cy * o;
            let Some(slot) = self.grid.slot_at(wx, wy) else {
                continue;
            };
            let dz = dh + o * sin_roll;
            let shift = (dz * self.samples_per_m + 0.5).floor() as i64;
            let b0 = (sweep.start as i64 - shift).clamp(0, max_start) as usize;
            let b = &self.grid.column(slot)[b0..b0 + sweep.len];
            let a = &sweep.a[k * sweep.len..(k + 1) * sweep.len];
            let (s_ab, s_bb) = match self.grid.window_energy(slot, b0, sweep.len) {
                Some(e) => (dot(a, b), e),
                None => dot_and_energy(a, b),
            };
            ab += f64::from(s_ab);
            bb += f64::from(s_bb);
            aa += f64::from(sweep.aa[k]);
            overlap += 1;
        }
        let den = aa * bb;
        Correlation {
            value: if den > 0.0 { ab / den.sqrt() } else { 0.0 },
            overlap,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{Columns, GridSpec};

    /// A grid whose every point has a distinct column, and the exact formula of eq. 8.
    fn grid(samples: usize) -> LocalGrid {
        let spec = GridSpec {
            size_m: 2.0,
            spacing_m: 0.05,
            radius_m: 0.03,
        };
        let g0 = LocalGrid::build(&spec, [0.0, 0.0], samples, &[]);
        let (n, s, origin) = g0.layout();
        let mut c = Columns::new(samples);
        for j in 0..n {
            for i in 0..n {
                c.positions.push([origin[0] + i as f64 * s, origin[1] + j as f64 * s]);
                c.stamps_ns.push(0);
                c.channels.push(0);
                c.values
                    .extend((0..samples).map(|d| ((i * 31 + j * 17 + d * 7) as f32 * 0.11).sin()));
            }
        }
        LocalGrid::build(&spec, [0.0, 0.0], samples, &[&c])
    }

    #[test]
    fn matches_the_direct_formula() {
        let samples = 40;
        let g = grid(samples);
        let geo = ArrayGeometry {
            element_spacing_m: 0.127,
            mount_m: [0.1, 0.02],
        };
        let mut sweep = PreparedSweep::new(&geo, 5, 4, 32);
        let values: Vec<f32> = (0..5 * samples).map(|v| ((v * 13) as f32 * 0.07).cos()).collect();
        assert!(sweep.load(&values, samples));
        let dt = 0.163;
        let c = Correlator::new(&g, dt);
        for pose in [
            [0.1, -0.2, 0.0, 0.3, 0.0],
            [0.0, 0.0, 0.04, -0.5, 0.02],
            [0.8, 0.75, -0.01, 0.0, -0.03],
        ] {
            // the direct formula, one term at a time in f64
            let (mut ab, mut aa, mut bb, mut n) = (0.0, 0.0, 0.0, 0);
            for k in 0..5 {
                let o = geo.channel_y_m(k, 5);
                let (wx, wy) = ArrayGeometry::to_world(pose[0], pose[1], pose[3], 0.1, o);
                let Some(slot) = g.slot_at(wx, wy) else { continue };
                let shift = ((pose[2] + o * pose[4].sin()) * 2.0 / C_M_PER_NS / dt).round() as i64;
                let b0 = (4 - shift).clamp(0, 8) as usize;
                for d in 0..32 {
                    let a = f64::from(values[k * samples + 4 + d]);
                    let b = f64::from(g.column(slot)[b0 + d]);
                    ab += a * b;
                    aa += a * a;
                    bb += b * b;
                }
                n += 1;
            }
            let want = ab / (aa * bb).sqrt();
            let got = c.correlate(&sweep, &pose);
            assert_eq!(got.overlap, n);
            assert!((got.value - want).abs() < 1e-5, "{pose:?}: {} vs {want}", got.value);
        }
        // with the window energies tabulated, the same values
        let mut tabulated = g.clone();
        tabulated.prepare_window(32);
        let t = Correlator::new(&tabulated, dt);
        for pose in [[0.1, -0.2, 0.0, 0.3, 0.0], [0.0, 0.0, 0.04, -0.5, 0.02]] {
            let (a, b) = (c.correlate(&sweep, &pose), t.correlate(&sweep, &pose));
            assert!(
                (a.value - b.value).abs() < 1e-6 && a.overlap == b.overlap,
                "{a:?} vs {b:?}"
            );
        }
        // off the grid: nothing overlaps, correlation 0
        let off = c.correlate(&sweep, &[10.0, 10.0, 0.0, 0.0, 0.0]);
        assert_eq!((off.value, off.overlap), (0.0, 0));
    }

    #[test]
    fn a_sweep_cut_from_the_grid_correlates_to_one_and_its_negative_to_minus_one() {
        let samples = 40;
        let g = grid(samples);
        let geo = ArrayGeometry::default();
        let pose = [0.2, 0.3, 0.0, 0.4, 0.0];
        let mut values = Vec::new();
        for k in 0..3 {
            let (wx, wy) = ArrayGeometry::to_world(pose[0], pose[1], pose[3], 0.0, geo.channel_y_m(k, 3));
            values.extend_from_slice(g.column(g.slot_at(wx, wy).expect("must succeed")));
        }
        let mut sweep = PreparedSweep::new(&geo, 3, 4, 32);
        assert!(sweep.load(&values, samples));
        let c = Correlator::new(&g, 0.163);
        assert!((c.correlate(&sweep, &pose).value - 1.0).abs() < 1e-6);
        let neg: Vec<f32> = values.iter().map(|v| -v).collect();
        assert!(sweep.load(&neg, samples));
        assert!((c.correlate(&sweep, &pose).value + 1.0).abs() < 1e-6);
        // wrong sizes are refused
        assert!(!sweep.load(&values[1..], samples));
        assert!(!sweep.load_stretched(&values[1..], samples, 1.05, 10.0));
        // a stretch of 1 is the plain load; stretching by 2 about sample 10 reads sample
        // 10 + 2 (d - 10) for window sample d
        let ramp: Vec<f32> = (0..3).flat_map(|_| (0..samples).map(|d| d as f32)).collect();
        assert!(sweep.load_stretched(&ramp, samples, 2.0, 10.0));
        let mut plain = PreparedSweep::new(&geo, 3, 4, 32);
        assert!(plain.load(&ramp, samples));
        assert_eq!(&sweep.a[..6], &[4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
        assert_eq!(sweep.a[7], 12.0);
        assert_eq!(sweep.a[20], 38.0); // d = 24: 10 + 2 x 14
        assert_eq!(sweep.a[31], 39.0); // d = 35: 60, past the end, the last sample
        assert_eq!(plain.a[20], 24.0);
    }
}
