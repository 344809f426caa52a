//! The subsurface as the radar sees it in one run: layers with undulating interfaces,
//! texture scatterers (generated lazily per cell, so a world is as large as the runs in it),
//! point and linear objects — each with the vertical travel time, RMS velocity and losses
//! for this run's soil moisture.
//!
//! Propagation model: straight rays in a layered medium. A scatterer at depth `d` below a
//! horizontal offset `x` returns after `t(x) = sqrt(t0^2 + (2x / v_rms)^2)` (the RMS-velocity
//! hyperbola, exact for one layer), `t0` the vertical two-way time. Losses: two-way
//! attenuation along the slant path, transmission `1 - R^2` at every interface crossed,
//! geometric spreading `1/r^2` for points, `1/r^1.5` for cylinders, `1/r` for planes.

use std::collections::HashMap;
use std::f64::consts::{LN_10, TAU};

use nalgebra::Vector3;

use crate::rng::Rng;
use crate::scenario::{self, LineKind, LineObject, PointKind, PointObject, Texture};

/// Speed of light, m/ns.
pub const C_M_PER_NS: f64 = 0.299_792_458;
const WATER_SQRT_EPS: f64 = 8.944; // sqrt(80)
/// Extra attenuation per unit volumetric water content, dB/m (seed 001 §4.3: up to
/// 10 dB/m at 30 % saturation).
const MOISTURE_DB_PER_M: f64 = 33.0;
const TEXTURE_CELL_M: f64 = 0.5;

/// A smooth random field: a sum of plane waves (random Fourier features), unit variance.
#[derive(Debug, Clone)]
pub struct SmoothField {
    waves: Vec<([f64; 3], f64)>,
}

impl SmoothField {
    /// A field whose correlation length is about `length_m`.
    pub fn new(rng: &mut Rng, length_m: f64, waves: usize, dims: usize) -> Self {
        let waves = (0..waves)
            .map(|_| {
                let mut k = [0.0; 3];
                for kk in k.iter_mut().take(dims) {
                    *kk = rng.normal() / length_m;
                }
                (k, rng.range(0.0, TAU))
            })
            .collect();
        Self { waves }
    }

    /// The field at `p`.
    pub fn at(&self, p: [f64; 3]) -> f64 {
        let n = self.waves.len() as f64;
        let s: f64 = self
            .waves
            .iter()
            .map(|(k, phase)| (k[0] * p[0] + k[1] * p[1] + k[2] * p[2] + phase).cos())
            .sum();
        s * (2.0 / n).sqrt()
    }
}

/// The vertical path from the surface down to a depth at one place.
#[derive(Debug, Clone, Copy)]
pub struct Column {
    /// Vertical two-way time in the ground, ns.
    pub t0_ns: f64,
    /// RMS velocity over the path, m/ns.
    pub v_rms_m_per_ns: f64,
    /// Natural log of the two-way vertical attenuation factor (<= 0).
    pub ln_attenuation: f64,
    /// Two-way transmission through the interfaces crossed.
    pub transmission: f64,
    /// Refractive index (sqrt eps) of the layer at that depth.
    pub index: f64,
}

/// A texture scatterer, with its column precomputed.
#[derive(Debug, Clone, Copy)]
pub struct Scatterer {
    /// Horizontal position, m.
    pub x: f64,
    /// Horizontal position, m.
    pub y: f64,
    /// Depth, m.
    pub depth_m: f64,
    /// Reflection strength times transmission (signed).
    pub strength: f64,
    /// cos(2 beta), sin(2 beta) of the scatterer's orientation beta.
    pub orientation: [f64; 2],
    /// The vertical column down to it.
    pub column: Column,
}

/// A linear object, ready for the radar.
#[derive(Debug, Clone)]
pub struct Line {
    /// End points (x, y, -depth), m.
    pub a: Vector3<f64>,
    /// Other end.
    pub b: Vector3<f64>,
    /// Radius, m.
    pub radius_m: f64,
    /// Material.
    pub kind: LineKind,
}

/// The world in one run.
#[derive(Debug)]
pub struct World {
    seed: u64,
    tops_m: Vec<f64>,
    undulations: Vec<Option<(SmoothField, f64)>>,
    index: Vec<f64>,
    attenuation_db_per_m: Vec<f64>,
    texture: Option<(Texture, SmoothField)>,
    cells: HashMap<(i64, i64), Vec<Scatterer>>,
    /// Point objects (declared and random).
    pub points: Vec<PointObject>,
    /// Linear objects (declared and rebar).
    pub lines: Vec<Line>,
}

impl World {
    /// The world of `decl` for a run with `soil_moisture` extra water content.
    pub fn new(decl: &scenario::World, seed: u64, soil_moisture: f64) -> Self {
        let mut rng = Rng::derive(seed, "world", 0);
        let undulations = decl
            .layers
            .iter()
            .map(|l| {
                l.undulation
                    .as_ref()
                    .map(|u| (SmoothField::new(&mut rng, u.wavelength_m / TAU, 8, 2), u.amplitude_m))
            })
            .collect();
        let texture = decl.texture.as_ref().map(|t| {
            let field = SmoothField::new(
                &mut Rng::derive(seed, "texture-field", 0),
                t.correlation_length_m,
                48,
                3,
            );
            (t.clone(), field)
        });
        let mut points = decl.points.clone();
        if let Some(r) = &decl.random_points {
            let mut rng = Rng::derive(seed, "random-points", 0);
            let area = (r.area[1][0] - r.area[0][0]).abs() * (r.area[1][1] - r.area[0][1]).abs();
            for _ in 0..rng.poisson(r.per_m2 * area) {
                points.push(PointObject {
                    at: [
                        rng.range(r.area[0][0], r.area[1][0]),
                        rng.range(r.area[0][1], r.area[1][1]),
                    ],
                    depth_m: rng.range(r.depth_m[0], r.depth_m[1]),
                    radius_m: rng.range(r.radius_m[0], r.radius_m[1]),
                    kind: if rng.uniform() < r.void_fraction {
                        PointKind::Void
                    } else {
                        PointKind::Rock
                    },
                });
            }
        }
        let mut lines: Vec<Line> = decl.lines.iter().map(line_of).collect();
        if let Some(g) = &decl.rebar {
            lines.extend(rebar_lines(g).iter().map(line_of));
        }
        Self {
            seed,
            tops_m: decl.layers.iter().map(|l| l.top_depth_m).collect(),
            undulations,
            index: decl
                .layers
                .iter()
                .map(|l| l.eps_r.sqrt() + soil_moisture * (WATER_SQRT_EPS - 1.0))
                .collect(),
            attenuation_db_per_m: decl
                .layers
                .iter()
                .map(|l| l.attenuation_db_per_m + MOISTURE_DB_PER_M * soil_moisture)
                .collect(),
            texture,
            cells: HashMap::new(),
            points,
            lines,
        }
    }

    /// Refractive index of the top layer.
    pub fn surface_index(&self) -> f64 {
        self.index[0]
    }

    /// Depth of the top of layer `i` at (x, y), m.
    pub fn interface_depth(&self, i: usize, x: f64, y: f64) -> f64 {
        if i == 0 {
            return 0.0;
        }
        let base = self.tops_m[i];
        let wobble = self.undulations[i]
            .as_ref()
            .map_or(0.0, |(field, amplitude)| amplitude * field.at([x, y, 0.0]));
        // never above the layer over it
        (base + wobble).max(self.interface_depth(i - 1, x, y) + 0.01)
    }

    /// The number of layers.
    pub fn layer_count(&self) -> usize {
        self.tops_m.len()
    }

    /// Reflection coefficient at the top of layer `i` (i >= 1) for a wave going down.
    pub fn interface_reflection(&self, i: usize) -> f64 {
        let (n1, n2) = (self.index[i - 1], self.index[i]);
        (n1 - n2) / (n1 + n2)
    }

    /// The vertical column from the surface down to `depth_m` at (x, y).
    pub fn column(&self, x: f64, y: f64, depth_m: f64) -> Column {
        let mut t0 = 0.0;
        let mut v2t = 0.0;
        let mut loss_db = 0.0;
        let mut transmission = 1.0;
        let mut index = self.index[0];
        for i in 0..self.tops_m.len() {
            let top = self.interface_depth(i, x, y);
            if top >= depth_m {
                break;
            }
            if i > 0 {
                let r = self.interface_reflection(i);
                transmission *= 1.0 - r * r;
            }
            let bottom = if i + 1 < self.tops_m.len() {
                self.interface_depth(i + 1, x, y).min(depth_m)
            } else {
                depth_m
            };
            let h = (bottom - top).max(0.0);
            let n = self.index[i];
            let dt = 2.0 * h * n / C_M_PER_NS;
            let v = C_M_PER_NS / n;
            t0 += dt;
            v2t += v * v * dt;
            loss_db += self.attenuation_db_per_m[i] * h;
            index = n;
        }
        let v_rms = if t0 > 0.0 {
            (v2t / t0).sqrt()
        } else {
            C_M_PER_NS / index
        };
        Column {
            t0_ns: t0,
            v_rms_m_per_ns: v_rms,
            ln_attenuation: -2.0 * loss_db / 20.0 * LN_10,
            transmission,
            index,
        }
    }

    /// Anisotropy of the texture scatterers (0 without texture).
    pub fn texture_polarisation(&self) -> f64 {
        self.texture.as_ref().map_or(0.0, |(t, _)| t.polarisation)
    }

    /// Deepest texture scatterer, m (0 without texture).
    pub fn texture_depth_m(&self) -> f64 {
        self.texture.as_ref().map_or(0.0, |(t, _)| t.max_depth_m)
    }

    /// Calls `visit` for every texture scatterer within `radius_m` of (x, y) horizontally.
    pub fn texture_near(&mut self, x: f64, y: f64, radius_m: f64, mut visit: impl FnMut(&Scatterer)) {
        if self.texture.is_none() {
            return;
        }
        let lo = |v: f64| ((v - radius_m) / TEXTURE_CELL_M).floor() as i64;
        let hi = |v: f64| ((v + radius_m) / TEXTURE_CELL_M).floor() as i64;
        let r2 = radius_m * radius_m;
        for ix in lo(x)..=hi(x) {
            for iy in lo(y)..=hi(y) {
                if !self.cells.contains_key(&(ix, iy)) {
                    let cell = self.make_cell(ix, iy);
                    self.cells.insert((ix, iy), cell);
                }
                if let Some(cell) = self.cells.get(&(ix, iy)) {
                    for s in cell {
                        let (dx, dy) = (s.x - x, s.y - y);
                        if dx * dx + dy * dy <= r2 {
                            visit(s);
                        }
                    }
                }
            }
        }
    }

    fn make_cell(&self, ix: i64, iy: i64) -> Vec<Scatterer> {
        let Some((t, field)) = &self.texture else {
            return Vec::new();
        };
        let mut rng = Rng::derive(
            self.seed,
            "texture-cell",
            ix.wrapping_mul(0x1_0000_0001).wrapping_add(iy),
        );
        let volume = TEXTURE_CELL_M * TEXTURE_CELL_M * t.max_depth_m;
        let count = rng.poisson(t.density_per_m3 * volume);
        let independent = (1.0 - t.correlation * t.correlation).sqrt();
        (0..count)
            .map(|_| {
                let x = (ix as f64 + rng.uniform()) * TEXTURE_CELL_M;
                let y = (iy as f64 + rng.uniform()) * TEXTURE_CELL_M;
                let depth_m = rng.range(0.03, t.max_depth_m);
                let beta = rng.range(0.0, TAU);
                let strength = t.strength * (t.correlation * field.at([x, y, depth_m]) + independent * rng.normal());
                let column = self.column(x, y, depth_m);
                Scatterer {
                    x,
                    y,
                    depth_m,
                    strength: strength * column.transmission,
                    orientation: [(2.0 * beta).cos(), (2.0 * beta).sin()],
                    column,
                }
            })
            .collect()
    }

    /// Reflection coefficient and size factor of a point object in the layer around it.
    pub fn point_response(&self, p: &PointObject) -> f64 {
        let n = self.column(p.at[0], p.at[1], p.depth_m).index;
        let n_obj = match p.kind {
            PointKind::Rock => (n * n + 3.0).sqrt(),
            PointKind::Void => 1.0,
        };
        (n - n_obj) / (n + n_obj) * (p.radius_m / 0.1).min(2.0)
    }

    /// Reflection coefficient and size factor of a linear object at a depth.
    pub fn line_response(&self, line: &Line, x: f64, y: f64, depth_m: f64) -> f64 {
        let n = self.column(x, y, depth_m).index;
        let r = match line.kind {
            LineKind::MetalPipe => -1.0,
            LineKind::PlasticPipe => (n - 1.0) / (n + 1.0),
            LineKind::WaterPipe => (n - WATER_SQRT_EPS) / (n + WATER_SQRT_EPS),
            LineKind::Fracture => (1.0 - 1.5f64.sqrt()) / (1.0 + 1.5f64.sqrt()),
        };
        r * (line.radius_m / 0.05).sqrt().min(1.5)
    }
}

fn line_of(l: &LineObject) -> Line {
    Line {
        a: Vector3::new(l.from[0], l.from[1], -l.from[2]),
        b: Vector3::new(l.to[0], l.to[1], -l.to[2]),
        radius_m: l.radius_m,
        kind: l.kind,
    }
}

/// The bars of a rebar grid as linear objects.
pub fn rebar_lines(g: &scenario::RebarGrid) -> Vec<LineObject> {
    let (s, c) = g.angle_deg.to_radians().sin_cos();
    let along = [c, s];
    let across = [-s, c];
    let at = |u: f64, v: f64| {
        [
            g.origin[0] + u * along[0] + v * across[0],
            g.origin[1] + u * along[1] + v * across[1],
        ]
    };
    let mut out = Vec::new();
    let bar = |p: [f64; 2], q: [f64; 2]| LineObject {
        from: [p[0], p[1], g.depth_m],
        to: [q[0], q[1], g.depth_m],
        radius_m: g.radius_m,
        kind: LineKind::MetalPipe,
    };
    let n_across = (g.size_m[1] / g.spacing_m[1]).floor() as usize;
    for k in 0..=n_across {
        let v = k as f64 * g.spacing_m[1];
        out.push(bar(at(0.0, v), at(g.size_m[0], v)));
    }
    let n_along = (g.size_m[0] / g.spacing_m[0]).floor() as usize;
    for k in 0..=n_along {
        let u = k as f64 * g.spacing_m[0];
        // the cross bars sit just on top of the long ones
        let mut b = bar(at(u, 0.0), at(u, g.size_m[1]));
        b.from[2] -= 2.0 * g.radius_m;
        b.to[2] -= 2.0 * g.radius_m;
        out.push(b);
    }
    out
}

/// The closest point of segment `a`-`b` to `p`.
pub fn closest_on_segment(a: &Vector3<f64>, b: &Vector3<f64>, p: &Vector3<f64>) -> Vector3<f64> {
    let ab = b - a;
    let len2 = ab.norm_squared();
    if len2 <= 0.0 {
        return *a;
    }
    let t = ((p - a).dot(&ab) / len2).clamp(0.0, 1.0);
    a + t * ab
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Layer;

    fn decl(layers: Vec<Layer>) -> scenario::World {
        scenario::World {
            layers,
            texture: None,
            points: vec![],
            random_points: None,
            lines: vec![],
            rebar: None,
            clutter: vec![],
        }
    }

    #[test]
    fn one_layer_column_is_exact() {
        let w = World::new(
            &decl(vec![Layer {
                top_depth_m: 0.0,
                eps_r: 9.0,
                attenuation_db_per_m: 10.0,
                undulation: None,
            }]),
            1,
            0.0,
        );
        let c = w.column(0.0, 0.0, 1.5);
        let v = C_M_PER_NS / 3.0;
        assert!((c.t0_ns - 2.0 * 1.5 / v).abs() < 1e-12);
        assert!((c.v_rms_m_per_ns - v).abs() < 1e-12);
        // 10 dB/m, 1.5 m, two way: -30 dB in amplitude
        assert!((c.ln_attenuation.exp() - 10f64.powf(-1.5)).abs() < 1e-12);
        assert_eq!(c.transmission, 1.0);
    }

    #[test]
    fn moisture_slows_and_attenuates() {
        let layers = vec![Layer {
            top_depth_m: 0.0,
            eps_r: 6.0,
            attenuation_db_per_m: 3.0,
            undulation: None,
        }];
        let dry = World::new(&decl(layers.clone()), 1, 0.0).column(0.0, 0.0, 1.0);
        let wet = World::new(&decl(layers), 1, 0.1).column(0.0, 0.0, 1.0);
        assert!(wet.t0_ns > dry.t0_ns * 1.1);
        assert!(wet.ln_attenuation < dry.ln_attenuation);
    }

    #[test]
    fn smooth_field_has_unit_variance_and_correlation() {
        let f = SmoothField::new(&mut Rng::new(5), 0.5, 64, 3);
        let (mut s2, mut near, n) = (0.0, 0.0, 4000);
        let mut r = Rng::new(9);
        for _ in 0..n {
            let p = [r.range(-50.0, 50.0), r.range(-50.0, 50.0), r.range(0.0, 2.0)];
            let a = f.at(p);
            s2 += a * a;
            near += a * f.at([p[0] + 0.05, p[1], p[2]]);
        }
        let var = s2 / f64::from(n);
        assert!((var - 1.0).abs() < 0.25, "variance {var}");
        assert!(near / f64::from(n) > 0.8 * var, "neighbours must be correlated");
    }
}
