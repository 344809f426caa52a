//! Particle swarm optimisation (seed 001 §2.2.2, eq. 9-10; Kennedy & Eberhart 1995): particles
//! move through the 5-DOF box, each pulled towards its own best position (cognitive constant)
//! and the swarm's best (social constant), with an inertia that falls linearly over the
//! iterations (wide exploration first, convergence last).
//!
//! The schedule, shared with the numpy reference `tools/peer/bench_track.py`: particle 0 at the
//! box centre, the others uniform in the box, velocities uniform within a fifth of the box;
//! each iteration evaluates every particle, updates the bests (strictly better only), then
//! (but after the last) moves: `v = w v + c_a r_a (p_best - p) + c_b r_b (g_best - p)`,
//! clamped to the box's half widths, and `p += v`, clamped to the box.

use serde::Deserialize;

use super::correlate::Pose5;
use crate::error::{Error, param};

/// A small deterministic generator (SplitMix64): the swarm's random numbers.
#[derive(Debug, Clone)]
pub struct SplitMix(u64);

impl SplitMix {
    /// A generator from `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[-1, 1)`.
    pub fn signed(&mut self) -> f64 {
        2.0 * self.unit() - 1.0
    }
}

/// The swarm's constants.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct SwarmParams {
    /// Inertia `w` at the first iteration. Default 0.9.
    pub inertia_start: f64,
    /// Inertia at the last iteration. Default 0.4.
    pub inertia_end: f64,
    /// Cognitive constant `C_a`. Default 1.5.
    pub cognitive: f64,
    /// Social constant `C_b`. Default 1.5.
    pub social: f64,
}

impl Default for SwarmParams {
    fn default() -> Self {
        Self {
            inertia_start: 0.9,
            inertia_end: 0.4,
            cognitive: 1.5,
            social: 1.5,
        }
    }
}

impl SwarmParams {
    /// Checks the values; `prefix` is the key of this block in the graph file.
    ///
    /// # Errors
    /// `Param`: a constant that is not finite, an inertia outside `[0, 1]`, a negative
    /// cognitive or social constant.
    pub fn check(&self, prefix: &str) -> Result<(), Error> {
        for (key, v) in [("inertia_start", self.inertia_start), ("inertia_end", self.inertia_end)] {
            if !(0.0..=1.0).contains(&v) {
                return Err(param(&format!("{prefix}.{key}"), format!("must be in [0, 1], got {v}")));
            }
        }
        for (key, v) in [("cognitive", self.cognitive), ("social", self.social)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(param(
                    &format!("{prefix}.{key}"),
                    format!("must be >= 0 and finite, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// What a search found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwarmResult {
    /// The best pose.
    pub best: Pose5,
    /// Its fitness.
    pub value: f64,
    /// Fitness evaluations made.
    pub evaluations: usize,
}

/// A swarm with its buffers (reused from search to search).
#[derive(Debug, Clone)]
pub struct Swarm {
    params: SwarmParams,
    rng: SplitMix,
    position: Vec<Pose5>,
    velocity: Vec<Pose5>,
    best: Vec<Pose5>,
    best_value: Vec<f64>,
}

impl Swarm {
    /// A swarm with these constants and random seed.
    pub fn new(params: SwarmParams, seed: u64) -> Self {
        Self {
            params,
            rng: SplitMix::new(seed),
            position: Vec::new(),
            velocity: Vec::new(),
            best: Vec::new(),
            best_value: Vec::new(),
        }
    }

    /// Maximises `fitness` over the box `centre +- half_width` with `particles` particles over
    /// `iterations` iterations (each at least 1).
    pub fn search(
        &mut self,
        centre: &Pose5,
        half_width: &Pose5,
        particles: usize,
        iterations: usize,
        mut fitness: impl FnMut(&Pose5) -> f64,
    ) -> SwarmResult {
        let (particles, iterations) = (particles.max(1), iterations.max(1));
        let lo: Pose5 = std::array::from_fn(|d| centre[d] - half_width[d]);
        let hi: Pose5 = std::array::from_fn(|d| centre[d] + half_width[d]);
        self.position.clear();
        self.velocity.clear();
        for p in 0..particles {
            let pos = if p == 0 {
                *centre
            } else {
                std::array::from_fn(|d| centre[d] + half_width[d] * self.rng.signed())
            };
            self.position.push(pos);
        }
        for _ in 0..particles {
            let v = std::array::from_fn(|d| 0.2 * half_width[d] * self.rng.signed());
            self.velocity.push(v);
        }
        self.best.clear();
        self.best.extend_from_slice(&self.position);
        self.best_value.clear();
        self.best_value.resize(particles, f64::NEG_INFINITY);
        let (mut g_best, mut g_value) = (*centre, f64::NEG_INFINITY);
        let SwarmParams {
            inertia_start,
            inertia_end,
            cognitive,
            social,
        } = self.params;
        for it in 0..iterations {
            for p in 0..particles {
                let v = fitness(&self.position[p]);
                if v > self.best_value[p] {
                    self.best_value[p] = v;
                    self.best[p] = self.position[p];
                }
                if v > g_value {
                    g_value = v;
                    g_best = self.position[p];
                }
            }
            if it + 1 == iterations {
                break;
            }
            let w = inertia_start + (inertia_end - inertia_start) * it as f64 / (iterations - 1).max(1) as f64;
            for p in 0..particles {
                for d in 0..5 {
                    let (ra, rb) = (self.rng.unit(), self.rng.unit());
                    let x = self.position[p][d];
                    let v = w * self.velocity[p][d]
                        + cognitive * ra * (self.best[p][d] - x)
                        + social * rb * (g_best[d] - x);
                    let v = v.clamp(-half_width[d], half_width[d]);
                    self.velocity[p][d] = v;
                    self.position[p][d] = (x + v).clamp(lo[d], hi[d]);
                }
            }
        }
        SwarmResult {
            best: g_best,
            value: g_value,
            evaluations: particles * iterations,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_peak_of_a_smooth_function_off_centre() {
        let peak = [0.7, -1.1, 0.02, 0.01, -0.015];
        let f = |p: &Pose5| {
            let s = [1.0, 1.0, 0.05, 0.02, 0.03];
            -(0..5).map(|d| ((p[d] - peak[d]) / s[d]).powi(2)).sum::<f64>()
        };
        let mut swarm = Swarm::new(SwarmParams::default(), 7);
        let r = swarm.search(&[0.0; 5], &[2.0, 2.0, 0.05, 0.035, 0.035], 60, 60, f);
        assert_eq!(r.evaluations, 3600);
        for d in 0..5 {
            assert!(
                (r.best[d] - peak[d]).abs() < 0.05 * [1.0, 1.0, 0.05, 0.02, 0.03][d] + 1e-3,
                "{:?}",
                r.best
            );
        }
    }

    #[test]
    fn stays_inside_the_box_and_counts_evaluations() {
        let mut swarm = Swarm::new(SwarmParams::default(), 1);
        let mut n = 0;
        let r = swarm.search(&[1.0; 5], &[0.5, 0.5, 0.0, 0.1, 0.1], 7, 3, |p| {
            n += 1;
            assert!((0.5..=1.5).contains(&p[0]) && p[2] == 1.0);
            p[0] // wants the upper edge
        });
        assert_eq!((n, r.evaluations), (21, 21));
        assert!(r.best[0] > 1.2);
        // the same seed gives the same search
        let again = Swarm::new(SwarmParams::default(), 1).search(&[1.0; 5], &[0.5, 0.5, 0.0, 0.1, 0.1], 7, 3, |p| p[0]);
        assert_eq!(again, r);
    }

    #[test]
    fn unit_draws_are_in_range_and_spread() {
        let mut r = SplitMix::new(3);
        let v: Vec<f64> = (0..10_000).map(|_| r.unit()).collect();
        assert!(v.iter().all(|x| (0.0..1.0).contains(x)));
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        assert!((mean - 0.5).abs() < 0.02);
    }
}
