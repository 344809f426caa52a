//! The local grid (seed 001 §2.2.1): map data interpolated onto a square of `size_m` (50 m)
//! around the vehicle at `spacing_m` (5 cm) in both horizontal directions, each grid point
//! the inverse-distance weighted mean of the map columns within `radius_m` (12 cm), at the
//! columns' native depth samples. Most of a grid is empty (a single-track map is 1.5 m wide):
//! only the points with data hold samples, the rest are marked empty in a dense index.

use serde::Deserialize;

use super::store::{Columns, MapReader, StoreError};
use crate::error::{Error, param};

/// Index value of a grid point without map data.
const EMPTY: u32 = u32::MAX;
/// Smallest distance in the inverse-distance weight, m: a column exactly on a grid point
/// weighs as if 1 mm away.
const MIN_WEIGHT_DISTANCE_M: f64 = 1e-3;

/// Size and resolution of a local grid.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct GridSpec {
    /// Side of the square grid, m. Default 50 (seed 001).
    pub size_m: f64,
    /// Grid spacing, m. Default 0.05 (seed 001).
    pub spacing_m: f64,
    /// Map columns within this distance of a grid point contribute to it, m. Default 0.12
    /// (seed 001).
    pub radius_m: f64,
}

impl Default for GridSpec {
    fn default() -> Self {
        Self {
            size_m: 50.0,
            spacing_m: 0.05,
            radius_m: 0.12,
        }
    }
}

impl GridSpec {
    /// Checks the values; `prefix` is the key of this block in the graph file.
    ///
    /// # Errors
    /// `Param`: a non-positive or non-finite value, more than 8192 points a side, a radius
    /// below half the spacing (points between columns would stay empty).
    pub fn check(&self, prefix: &str) -> Result<(), Error> {
        for (key, v) in [
            ("size_m", self.size_m),
            ("spacing_m", self.spacing_m),
            ("radius_m", self.radius_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(param(
                    &format!("{prefix}.{key}"),
                    format!("must be positive and finite, got {v}"),
                ));
            }
        }
        if self.size_m / self.spacing_m > 8192.0 {
            return Err(param(
                &format!("{prefix}.spacing_m"),
                format!(
                    "{} m points over {} m is more than 8192 a side",
                    self.spacing_m, self.size_m
                ),
            ));
        }
        if self.radius_m < 0.5 * self.spacing_m {
            return Err(param(
                &format!("{prefix}.radius_m"),
                format!(
                    "{} m is less than half the spacing ({} m)",
                    self.radius_m, self.spacing_m
                ),
            ));
        }
        Ok(())
    }

    /// Points per side.
    pub fn points(&self) -> usize {
        (self.size_m / self.spacing_m).round().max(1.0) as usize
    }
}

/// A local grid: `n x n` points `spacing` apart, point `(i, j)` at `origin + (i, j) spacing`.
#[derive(Debug, Clone)]
pub struct LocalGrid {
    centre: [f64; 2],
    origin: [f64; 2],
    n: usize,
    spacing: f64,
    samples: usize,
    /// Slot of each point (`j * n + i`), [`EMPTY`] without data.
    index: Vec<u32>,
    /// Samples of slot `s` at `values[s * samples..]`.
    values: Vec<f32>,
    /// With [`LocalGrid::prepare_window`]: the window length and, per slot, the energy
    /// (sum of squares) of the window at every start, `energies[s * starts + b0]`.
    window: Option<(usize, Vec<f32>)>,
}

impl LocalGrid {
    /// Grids `sources` (map columns of `samples` samples) around `centre`.
    pub fn build(spec: &GridSpec, centre: [f64; 2], samples: usize, sources: &[&Columns]) -> Self {
        let n = spec.points();
        let half = (n as f64 - 1.0) / 2.0 * spec.spacing_m;
        let origin = [centre[0] - half, centre[1] - half];
        let mut grid = Self {
            centre,
            origin,
            n,
            spacing: spec.spacing_m,
            samples,
            index: vec![EMPTY; n * n],
            values: Vec::new(),
            window: None,
        };
        let mut weights: Vec<f32> = Vec::new();
        let r = spec.radius_m;
        let reach = (r / spec.spacing_m).ceil() as i64;
        for cols in sources {
            debug_assert_eq!(cols.samples, samples);
            for (c, &[x, y]) in cols.positions.iter().enumerate() {
                let fi = (x - origin[0]) / spec.spacing_m;
                let fj = (y - origin[1]) / spec.spacing_m;
                let (ci, cj) = (fi.round() as i64, fj.round() as i64);
                if ci + reach < 0 || cj + reach < 0 || ci - reach >= n as i64 || cj - reach >= n as i64 {
                    continue;
                }
                let column = cols.column(c);
                for j in (cj - reach).max(0)..=(cj + reach).min(n as i64 - 1) {
                    for i in (ci - reach).max(0)..=(ci + reach).min(n as i64 - 1) {
                        let dx = origin[0] + i as f64 * spec.spacing_m - x;
                        let dy = origin[1] + j as f64 * spec.spacing_m - y;
                        let d = dx.hypot(dy);
                        if d > r {
                            continue;
                        }
                        let w = (1.0 / d.max(MIN_WEIGHT_DISTANCE_M)) as f32;
                        let at = j as usize * n + i as usize;
                        let slot = if grid.index[at] == EMPTY {
                            let s = weights.len();
                            grid.index[at] = s as u32;
                            weights.push(0.0);
                            grid.values.resize((s + 1) * samples, 0.0);
                            s
                        } else {
                            grid.index[at] as usize
                        };
                        weights[slot] += w;
                        let dst = &mut grid.values[slot * samples..(slot + 1) * samples];
                        for (d, v) in dst.iter_mut().zip(column) {
                            *d += w * v;
                        }
                    }
                }
            }
        }
        for (slot, w) in weights.iter().enumerate() {
            let inv = 1.0 / w;
            grid.values[slot * samples..(slot + 1) * samples]
                .iter_mut()
                .for_each(|v| *v *= inv);
        }
        grid
    }

    /// Reads the map's columns within reach of a grid around `centre` and grids them. Damaged
    /// tiles give what they hold; their damage is returned with the grid.
    ///
    /// # Errors
    /// `Io` reading a tile.
    pub fn from_map(map: &MapReader, spec: &GridSpec, centre: [f64; 2]) -> Result<(Self, Vec<StoreError>), StoreError> {
        Self::from_map_with_window(map, spec, centre, 0)
    }

    /// As [`LocalGrid::from_map`], with the window energies of `window_len` tabulated
    /// ([`LocalGrid::prepare_window`]; 0: none).
    ///
    /// # Errors
    /// `Io` reading a tile.
    pub fn from_map_with_window(
        map: &MapReader,
        spec: &GridSpec,
        centre: [f64; 2],
        window_len: usize,
    ) -> Result<(Self, Vec<StoreError>), StoreError> {
        let reach = spec.size_m / 2.0 + spec.spacing_m + spec.radius_m;
        let window = [
            centre[0] - reach,
            centre[1] - reach,
            centre[0] + reach,
            centre[1] + reach,
        ];
        let mut sources = Vec::new();
        let mut damage = Vec::new();
        for key in map.tiles_over(window[0], window[1], window[2], window[3]) {
            let t = map.read_tile(key, Some(window))?;
            if let Some(d) = t.damage {
                damage.push(d);
            }
            sources.push(t.columns);
        }
        let refs: Vec<&Columns> = sources.iter().collect();
        let mut grid = Self::build(spec, centre, map.info().samples as usize, &refs);
        grid.prepare_window(window_len);
        Ok((grid, damage))
    }

    /// Tabulates the energy of every window of `len` samples of every slot, so that a
    /// correlation needs only the products (`len` beyond the samples: nothing to tabulate).
    pub fn prepare_window(&mut self, len: usize) {
        if len == 0 || len > self.samples {
            self.window = None;
            return;
        }
        let starts = self.samples - len + 1;
        let slots = self.occupied();
        let mut energies = Vec::with_capacity(slots * starts);
        for s in 0..slots {
            let col = &self.values[s * self.samples..(s + 1) * self.samples];
            // a running sum in f64 over the window as it slides
            let mut e: f64 = col[..len].iter().map(|v| f64::from(*v) * f64::from(*v)).sum();
            energies.push(e as f32);
            for b0 in 1..starts {
                let (out, inn) = (f64::from(col[b0 - 1]), f64::from(col[b0 + len - 1]));
                e += inn * inn - out * out;
                energies.push(e.max(0.0) as f32);
            }
        }
        self.window = Some((len, energies));
    }

    /// The energy of slot `slot`'s window of `len` samples from `start`, when tabulated.
    #[inline]
    pub fn window_energy(&self, slot: usize, start: usize, len: usize) -> Option<f32> {
        let (l, e) = self.window.as_ref()?;
        if *l != len {
            return None;
        }
        e.get(slot * (self.samples - len + 1) + start).copied()
    }

    /// The world position the grid was built around.
    pub fn centre(&self) -> [f64; 2] {
        self.centre
    }

    /// Samples per point.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// Points with data.
    pub fn occupied(&self) -> usize {
        self.values.len() / self.samples.max(1)
    }

    /// Bytes held by the grid.
    pub fn bytes(&self) -> usize {
        self.index.len() * 4 + self.values.len() * 4 + self.window.as_ref().map_or(0, |w| w.1.len() * 4)
    }

    /// The slot of the grid point nearest `(x, y)`, if it has data.
    #[inline]
    pub fn slot_at(&self, x: f64, y: f64) -> Option<usize> {
        let fi = ((x - self.origin[0]) / self.spacing + 0.5).floor();
        let fj = ((y - self.origin[1]) / self.spacing + 0.5).floor();
        if fi < 0.0 || fj < 0.0 || fi >= self.n as f64 || fj >= self.n as f64 {
            return None;
        }
        let s = self.index[fj as usize * self.n + fi as usize];
        (s != EMPTY).then_some(s as usize)
    }

    /// The samples of `slot`.
    #[inline]
    pub fn column(&self, slot: usize) -> &[f32] {
        &self.values[slot * self.samples..(slot + 1) * self.samples]
    }

    /// The grid's Chebyshev distance from `(x, y)` to its centre, m.
    pub fn distance_from_centre(&self, x: f64, y: f64) -> f64 {
        (x - self.centre[0]).abs().max((y - self.centre[1]).abs())
    }

    /// Points per side, spacing (m) and the world position of point (0, 0): what a dump of
    /// the grid needs.
    pub fn layout(&self) -> (usize, f64, [f64; 2]) {
        (self.n, self.spacing, self.origin)
    }

    /// The dense index (`j * n + i`; `u32::MAX` without data) and the slots' samples.
    pub fn raw(&self) -> (&[u32], &[f32]) {
        (&self.index, &self.values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn columns(points: &[([f64; 2], f32)], samples: usize) -> Columns {
        let mut c = Columns::new(samples);
        for &(p, v) in points {
            c.positions.push(p);
            c.stamps_ns.push(0);
            c.channels.push(0);
            c.values.extend(std::iter::repeat_n(v, samples));
        }
        c
    }

    #[test]
    fn idw_on_known_points() {
        let spec = GridSpec {
            size_m: 1.0,
            spacing_m: 0.05,
            radius_m: 0.12,
        };
        // two columns 0.1 m apart around the point nearest the centre
        let g0 = LocalGrid::build(&spec, [0.0, 0.0], 3, &[]);
        let (_, _, origin) = g0.layout();
        let p = [origin[0] + 10.0 * 0.05, origin[1] + 10.0 * 0.05];
        let cols = columns(&[([p[0] - 0.03, p[1]], 1.0), ([p[0] + 0.07, p[1]], 4.0)], 3);
        let g = LocalGrid::build(&spec, [0.0, 0.0], 3, &[&cols]);
        let s = g.slot_at(p[0], p[1]).expect("must succeed");
        let (w1, w2) = (1.0 / 0.03, 1.0 / 0.07);
        let want = (w1 * 1.0 + w2 * 4.0) / (w1 + w2);
        assert!(
            (f64::from(g.column(s)[0]) - want).abs() < 1e-5,
            "{} vs {want}",
            g.column(s)[0]
        );
        // a point 0.17 m from the nearest is empty; one 0.07 m from only the first has its value
        assert!(g.slot_at(p[0] - 0.2, p[1]).is_none());
        let s = g.slot_at(p[0] - 0.1, p[1]).expect("must succeed");
        assert!((g.column(s)[2] - 1.0).abs() < 1e-6);
        // outside the grid
        assert!(g.slot_at(5.0, 0.0).is_none());
    }

    #[test]
    fn a_column_on_a_point_dominates_but_does_not_divide_by_zero() {
        let spec = GridSpec {
            size_m: 1.0,
            ..GridSpec::default()
        };
        let (_, _, origin) = LocalGrid::build(&spec, [3.0, 4.0], 1, &[]).layout();
        let on = [origin[0] + 0.5, origin[1] + 0.5];
        let cols = columns(&[(on, 2.0), ([on[0] + 0.1, on[1]], -8.0)], 1);
        let g = LocalGrid::build(&spec, [3.0, 4.0], 1, &[&cols]);
        let v = g.column(g.slot_at(on[0], on[1]).expect("must succeed"))[0];
        assert!(v.is_finite() && (v - 2.0).abs() < 0.11, "{v}");
    }

    #[test]
    fn spec_checks_name_the_key() {
        let bad = GridSpec {
            radius_m: 0.01,
            ..GridSpec::default()
        };
        assert!(
            bad.check("grid")
                .expect_err("must fail")
                .to_string()
                .contains("grid.radius_m")
        );
        let bad = GridSpec {
            spacing_m: f64::NAN,
            ..GridSpec::default()
        };
        assert!(
            bad.check("grid")
                .expect_err("must fail")
                .to_string()
                .contains("grid.spacing_m")
        );
    }
}
