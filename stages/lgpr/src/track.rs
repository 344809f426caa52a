//! Tracking against the prior map (seed 001 §2.2.2): for every sweep, the 5-DOF pose that
//! maximises the correlation of eq. 8 with the local grid, found by particle swarm
//! ([`pso`]) in a box around the expectation: the previous solution moved on by the GPS/INS
//! velocity and heading change.
//!
//! The box, the particles and the iterations follow the correlation reached: after a lock the
//! box shrinks (halves, down to `search_min`), after a miss it widens (doubles, up to
//! `search_max`), and particles and iterations scale between their minimum and maximum with
//! the box's size. The tracker is locked when the correlation exceeds `lock_correlation`
//! (0.9), at least `min_overlap` (2) channels are over mapped data, and the solution lies
//! within `gate_m + gate_m_per_s t` of the expectation (`t` since the last lock); otherwise
//! the pose is dead-reckoned on the GPS/INS velocity. Acquiring (before the first lock, and
//! once the pose has fallen back to the GPS/INS) also needs `acquire_overlap` (4) channels
//! over the map: with only the search box as a gate, a box as wide as the GPS/INS error lets
//! the swarm slide the array sideways until a channel or two match by chance.

pub mod correlate;
pub mod pso;

use serde::Deserialize;

pub use self::correlate::{C_M_PER_NS, Correlation, Correlator, Pose5, PreparedSweep};
pub use self::pso::{SplitMix, Swarm, SwarmParams, SwarmResult};
use crate::array::ArrayGeometry;
use crate::error::{Error, param};
use crate::map::LocalGrid;

/// Half widths of a search box.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields)]
pub struct SearchBox {
    /// Along x and y, m.
    pub xy_m: f64,
    /// Height, m.
    pub height_m: f64,
    /// Heading, degrees.
    pub heading_deg: f64,
    /// Roll, degrees.
    pub roll_deg: f64,
}

impl SearchBox {
    fn half_width(&self) -> Pose5 {
        [
            self.xy_m,
            self.xy_m,
            self.height_m,
            self.heading_deg.to_radians(),
            self.roll_deg.to_radians(),
        ]
    }

    fn check(&self, prefix: &str) -> Result<(), Error> {
        for (key, v) in [
            ("xy_m", self.xy_m),
            ("height_m", self.height_m),
            ("heading_deg", self.heading_deg),
            ("roll_deg", self.roll_deg),
        ] {
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

/// The tracker's parameters.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct TrackParams {
    /// First depth bin correlated. Default 4.
    pub window_start: usize,
    /// Depth bins correlated (seed 001: 360 of 369). Default 360.
    pub window_len: usize,
    /// The smallest search box (after locks). Default 0.1 m, 2 cm, 0.5 deg, 1 deg.
    pub search_min: SearchBox,
    /// The largest search box (first acquisition, after misses). Default 2.5 m, 5 cm, 3 deg,
    /// 2 deg.
    pub search_max: SearchBox,
    /// Particles in the smallest box. Default 24.
    pub particles_min: usize,
    /// Particles in the largest box (seed 001 Fig. 11: 200). Default 200.
    pub particles_max: usize,
    /// Iterations in the smallest box. Default 12.
    pub iterations_min: usize,
    /// Iterations in the largest box (seed 001 Fig. 11: 100). Default 100.
    pub iterations_max: usize,
    /// The swarm's constants.
    pub swarm: SwarmParams,
    /// Correlation above which a solution can lock. Default 0.9 (seed 001).
    pub lock_correlation: f64,
    /// Channels over mapped data needed to lock. Default 2 (seed 001).
    pub min_overlap: u32,
    /// Channels over mapped data needed to acquire a lock: before the first lock and once the
    /// dead-reckoned pose is less certain than the GPS/INS (`ins_sigma_m`). Default 4.
    pub acquire_overlap: u32,
    /// Largest distance of a locked solution from the expectation right after a lock, m.
    /// Default 0.25.
    pub gate_m: f64,
    /// Growth of the gate per second without a lock, m/s. Default 0.5.
    pub gate_m_per_s: f64,
    /// Search a sweep that misses the lock on its correlation once more, with the largest
    /// swarm around the best pose found (default true).
    pub retry_misses: bool,
    /// Standard deviation of a locked position, m: what the estimator weighs a map fix by.
    /// Default 0.02, the RMS error of a locked fix per axis on the tuning world `highway`
    /// (0.9-2.2 cm over its passes); 0.05 left the fused estimate leaning on the IMU (1.2 cm
    /// cross-track at 97 km/h against 0.8 cm).
    pub sigma_locked_m: f64,
    /// Growth of the dead-reckoned position's standard deviation, m/s. Default 0.1.
    pub sigma_m_per_s: f64,
    /// Standard deviation of the GPS/INS position, m: once the dead-reckoned position is less
    /// certain than this (and before the first lock), the GPS/INS position is reported and
    /// searched around instead (seed 001's fallback to the GPS/INS solution). Default 0.5.
    pub ins_sigma_m: f64,
    /// The travel-time stretch of wetter or drier soil than the map's.
    pub stretch: StretchParams,
    /// Random seed of the swarm. Default 1.
    pub seed: u64,
}

/// The tracker's estimate of the travel-time stretch between the map and the sweeps: soil
/// wetter than on the mapping pass is slower, so the sweeps' echoes from below the surface
/// come late by a factor (`soil_moisture` 0.02 in the simulator: about 5 %), which
/// decorrelates the deep part of the window (eq. 8 falls below the lock threshold). After each
/// sweep's registration the stretch moves one `step` up or down when that raises the
/// correlation at the registered pose, within `1 +- max`; sweeps are loaded with it
/// ([`PreparedSweep::load_stretched`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct StretchParams {
    /// Largest stretch away from 1 (0: off). Default 0.1.
    pub max: f64,
    /// Step of the search per sweep. Default 0.004.
    pub step: f64,
    /// Time of the ground surface in the sweeps, ns (the stretch applies below it). Default 9
    /// (the 8 ns delay of `lgpr_dsp` and the two-way path through 15 cm of air).
    pub ground_ns: f64,
}

impl Default for StretchParams {
    fn default() -> Self {
        Self {
            max: 0.1,
            step: 0.004,
            ground_ns: 9.0,
        }
    }
}

impl Default for TrackParams {
    fn default() -> Self {
        Self {
            window_start: 4,
            window_len: 360,
            search_min: SearchBox {
                xy_m: 0.1,
                height_m: 0.02,
                heading_deg: 0.5,
                roll_deg: 1.0,
            },
            search_max: SearchBox {
                xy_m: 2.5,
                height_m: 0.05,
                heading_deg: 3.0,
                roll_deg: 2.0,
            },
            particles_min: 24,
            particles_max: 200,
            iterations_min: 12,
            iterations_max: 100,
            swarm: SwarmParams::default(),
            lock_correlation: 0.9,
            min_overlap: 2,
            acquire_overlap: 4,
            gate_m: 0.25,
            gate_m_per_s: 0.5,
            retry_misses: true,
            sigma_locked_m: 0.02,
            sigma_m_per_s: 0.1,
            ins_sigma_m: 0.5,
            stretch: StretchParams::default(),
            seed: 1,
        }
    }
}

impl TrackParams {
    /// Standard deviation of a pose dead-reckoned for `since_lock_s` since the last lock
    /// (infinite before the first lock).
    pub fn dead_reckoned_sigma_m(&self, since_lock_s: Option<f64>) -> f64 {
        since_lock_s.map_or(f64::INFINITY, |t| self.sigma_locked_m.hypot(self.sigma_m_per_s * t))
    }

    /// Checks every value; keys are relative to the block (`search_min.xy_m`).
    ///
    /// # Errors
    /// `Param` naming the first bad value.
    pub fn check(&self) -> Result<(), Error> {
        if self.window_len == 0 {
            return Err(param("window_len", "must be at least 1"));
        }
        self.search_min.check("search_min")?;
        self.search_max.check("search_max")?;
        let (lo, hi) = (self.search_min.half_width(), self.search_max.half_width());
        if lo.iter().zip(&hi).any(|(a, b)| a > b) || self.search_min.xy_m <= 0.0 {
            return Err(param(
                "search_min",
                "must be positive in x-y and no larger than search_max in every axis",
            ));
        }
        if self.particles_min == 0 || self.particles_min > self.particles_max {
            return Err(param("particles_min", "must be at least 1 and at most particles_max"));
        }
        if self.iterations_min == 0 || self.iterations_min > self.iterations_max {
            return Err(param("iterations_min", "must be at least 1 and at most iterations_max"));
        }
        self.swarm.check("swarm")?;
        if self.acquire_overlap < self.min_overlap {
            return Err(param(
                "acquire_overlap",
                format!("must be at least min_overlap ({})", self.min_overlap),
            ));
        }
        if !(-1.0..=1.0).contains(&self.lock_correlation) {
            return Err(param(
                "lock_correlation",
                format!("must be in [-1, 1], got {}", self.lock_correlation),
            ));
        }
        for (key, v) in [
            ("gate_m", self.gate_m),
            ("gate_m_per_s", self.gate_m_per_s),
            ("sigma_locked_m", self.sigma_locked_m),
            ("sigma_m_per_s", self.sigma_m_per_s),
            ("ins_sigma_m", self.ins_sigma_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(param(key, format!("must be >= 0 and finite, got {v}")));
            }
        }
        if self.sigma_locked_m <= 0.0 {
            return Err(param("sigma_locked_m", "must be positive"));
        }
        let st = &self.stretch;
        if !(0.0..0.5).contains(&st.max) {
            return Err(param("stretch.max", format!("must be in [0, 0.5), got {}", st.max)));
        }
        if !(st.step.is_finite() && st.step > 0.0) {
            return Err(param("stretch.step", format!("must be positive, got {}", st.step)));
        }
        if !(st.ground_ns.is_finite() && st.ground_ns >= 0.0) {
            return Err(param(
                "stretch.ground_ns",
                format!("must be >= 0 and finite, got {}", st.ground_ns),
            ));
        }
        Ok(())
    }
}

/// The GPS/INS state used to predict between sweeps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InsState {
    /// Position `(x, y)`, m (used only to start).
    pub xy_m: [f64; 2],
    /// Heading, rad.
    pub yaw_rad: f64,
    /// Velocity over the ground in the world frame, m/s.
    pub velocity_mps: [f64; 2],
}

/// Why a solution did not lock (the first criterion that failed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Miss {
    /// Correlation at or below `lock_correlation`.
    Correlation,
    /// Fewer than `min_overlap` channels over mapped data.
    Overlap,
    /// Too far from the velocity-consistent expectation.
    Gate,
}

/// The tracker's answer for one sweep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackOutput {
    /// The pose reported: the registration when locked, else the dead-reckoned expectation.
    pub pose: Pose5,
    /// The best registration found (also when not locked).
    pub registered: Pose5,
    /// The expectation the search started from.
    pub expected: Pose5,
    /// Correlation of the best registration.
    pub correlation: f64,
    /// Channels over mapped data at the best registration.
    pub overlap: u32,
    /// Whether the lock criteria held.
    pub locked: bool,
    /// The failed criterion when not locked.
    pub miss: Option<Miss>,
    /// Standard deviation of the reported position, m.
    pub sigma_m: f64,
    /// Half width of the search box in x-y, m.
    pub search_xy_m: f64,
    /// Correlations evaluated.
    pub evaluations: usize,
    /// The travel-time stretch the sweep was loaded with.
    pub stretch: f64,
}

/// The lock decision of seed 001 §2.2.2, each criterion on its own.
pub fn lock_check(
    params: &TrackParams,
    c: Correlation,
    distance_from_expected_m: f64,
    since_lock_s: Option<f64>,
) -> Option<Miss> {
    if c.value <= params.lock_correlation {
        return Some(Miss::Correlation);
    }
    if c.overlap < params.min_overlap {
        return Some(Miss::Overlap);
    }
    // acquiring: never locked, or dead reckoning already worse than the GPS/INS
    let acquiring = params.dead_reckoned_sigma_m(since_lock_s) > params.ins_sigma_m;
    if acquiring && c.overlap < params.acquire_overlap {
        return Some(Miss::Overlap);
    }
    // before the first lock the search box is the only gate
    if let Some(t) = since_lock_s
        && distance_from_expected_m > params.gate_m + params.gate_m_per_s * t
    {
        return Some(Miss::Gate);
    }
    None
}

/// The tracker's state from sweep to sweep.
#[derive(Debug, Clone)]
pub struct Tracker {
    params: TrackParams,
    swarm: Swarm,
    sweep: PreparedSweep,
    trial: PreparedSweep,
    stretch: f64,
    /// The last reported pose, its stamp and the INS heading then.
    last: Option<(Pose5, i64, f64)>,
    last_lock_ns: Option<i64>,
    /// Size of the box, 0 (smallest) to 1 (largest), on a log scale.
    level: f64,
}

impl Tracker {
    /// A tracker for sweeps of `channels` channels at `geometry`; the parameters must have
    /// passed [`TrackParams::check`].
    pub fn new(params: TrackParams, geometry: &ArrayGeometry, channels: usize) -> Self {
        let swarm = Swarm::new(params.swarm.clone(), params.seed);
        let sweep = PreparedSweep::new(geometry, channels, params.window_start, params.window_len);
        Self {
            trial: sweep.clone(),
            sweep,
            stretch: 1.0,
            params,
            swarm,
            last: None,
            last_lock_ns: None,
            level: 1.0,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &TrackParams {
        &self.params
    }

    /// Whether a lock has ever been reached.
    pub fn ever_locked(&self) -> bool {
        self.last_lock_ns.is_some()
    }

    /// The expectation at `stamp_ns`: the last pose moved on by the INS velocity and heading
    /// change (the INS pose itself at the start).
    pub fn expect(&self, stamp_ns: i64, ins: &InsState) -> Pose5 {
        match self.last {
            None => [ins.xy_m[0], ins.xy_m[1], 0.0, ins.yaw_rad, 0.0],
            Some((p, t, ins_yaw)) => {
                let dt = ((stamp_ns - t) as f64 * 1e-9).max(0.0);
                [
                    p[0] + ins.velocity_mps[0] * dt,
                    p[1] + ins.velocity_mps[1] * dt,
                    p[2],
                    p[3] + wrap(ins.yaw_rad - ins_yaw),
                    p[4],
                ]
            }
        }
    }

    fn half_width(&self) -> Pose5 {
        let (lo, hi) = (self.params.search_min.half_width(), self.params.search_max.half_width());
        std::array::from_fn(|d| {
            if lo[d] > 0.0 {
                lo[d] * (hi[d] / lo[d]).powf(self.level)
            } else {
                hi[d] * self.level
            }
        })
    }

    fn scaled(&self, min: usize, max: usize) -> usize {
        (min as f64 + (max - min) as f64 * self.level).round() as usize
    }

    /// Channels of the sweeps this tracker takes.
    pub fn channels(&self) -> usize {
        self.sweep.channels()
    }

    /// The current travel-time stretch estimate.
    pub fn stretch(&self) -> f64 {
        self.stretch
    }

    /// Registers one sweep (`channels x samples` values, channel-major, samples
    /// `sample_interval_ns` apart) on `grid`; `None` when its size does not fit.
    pub fn track(
        &mut self,
        grid: &LocalGrid,
        sample_interval_ns: f64,
        values: &[f32],
        samples: usize,
        stamp_ns: i64,
        ins: &InsState,
    ) -> Option<TrackOutput> {
        let origin = self.params.stretch.ground_ns / sample_interval_ns;
        if !self.sweep.load_stretched(values, samples, self.stretch, origin) {
            return None;
        }
        let stretch_used = self.stretch;
        let sweep = &self.sweep;
        let expected = self.expect(stamp_ns, ins);
        let half_width = self.half_width();
        let particles = self.scaled(self.params.particles_min, self.params.particles_max);
        let iterations = self.scaled(self.params.iterations_min, self.params.iterations_max);
        let correlator = Correlator::new(grid, sample_interval_ns);
        let mut found = self.swarm.search(&expected, &half_width, particles, iterations, |p| {
            correlator.correlate(sweep, p).value
        });
        let mut c = correlator.correlate(sweep, &found.best);
        let mut evaluations = found.evaluations;
        if self.params.retry_misses && c.value <= self.params.lock_correlation && c.overlap >= self.params.min_overlap {
            // a near miss: once more around the best found, with the largest swarm, in the
            // same box (a swarm of the smallest box can stop short of the peak)
            let again = self.swarm.search(
                &found.best,
                &half_width,
                self.params.particles_max,
                self.params.iterations_max,
                |p| correlator.correlate(sweep, p).value,
            );
            evaluations += again.evaluations;
            let c2 = correlator.correlate(sweep, &again.best);
            if c2.value > c.value {
                found = again;
                c = c2;
            }
        }
        // the stretch: one step either way when it correlates better at this pose
        let st = &self.params.stretch;
        if st.max > 0.0 && c.overlap >= self.params.min_overlap {
            let mut best = c.value;
            let mut best_stretch = self.stretch;
            for cand in [self.stretch - st.step, self.stretch + st.step] {
                if (cand - 1.0).abs() > st.max || !self.trial.load_stretched(values, samples, cand, origin) {
                    continue;
                }
                let v = correlator.correlate(&self.trial, &found.best).value;
                if v > best {
                    best = v;
                    best_stretch = cand;
                }
            }
            self.stretch = best_stretch;
        }
        let distance = (found.best[0] - expected[0]).hypot(found.best[1] - expected[1]);
        let since_lock = self.last_lock_ns.map(|t| ((stamp_ns - t) as f64 * 1e-9).max(0.0));
        let miss = lock_check(&self.params, c, distance, since_lock);
        // the ladder of box sizes: 8 steps from the smallest to the largest, one down per lock
        // and one up per miss
        let step = 1.0 / 8.0;
        let (pose, sigma) = if miss.is_none() {
            self.last_lock_ns = Some(stamp_ns);
            self.level = (self.level - step).max(0.0);
            (found.best, self.params.sigma_locked_m)
        } else {
            self.level = (self.level + step).min(1.0);
            let sigma = self.params.dead_reckoned_sigma_m(since_lock);
            if sigma > self.params.ins_sigma_m {
                // dead reckoning is now worse than the GPS/INS itself
                let mut at = expected;
                at[0] = ins.xy_m[0];
                at[1] = ins.xy_m[1];
                (at, self.params.ins_sigma_m)
            } else {
                (expected, sigma)
            }
        };
        self.last = Some((pose, stamp_ns, ins.yaw_rad));
        Some(TrackOutput {
            pose,
            registered: found.best,
            expected,
            correlation: c.value,
            overlap: c.overlap,
            locked: miss.is_none(),
            miss,
            sigma_m: sigma,
            search_xy_m: half_width[0],
            evaluations,
            stretch: stretch_used,
        })
    }
}

/// `a` wrapped to `(-pi, pi]`.
fn wrap(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let w = a.rem_euclid(t);
    if w > std::f64::consts::PI { w - t } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::array::ArrayGeometry;
    use crate::map::{Columns, GridSpec};

    /// A 6 m square map of smooth random texture, 40 samples deep, and a sweep read from it at
    /// a pose (nearest point, shifted by the height as the correlation models it).
    struct World {
        grid: LocalGrid,
        geometry: ArrayGeometry,
    }

    const SAMPLES: usize = 40;
    const DT_NS: f64 = 0.163;

    fn texture(x: f64, y: f64, d: usize) -> f32 {
        let t = d as f64 * 0.35;
        ((x * 3.1 + t).sin() * (y * 2.3 - 0.5 * t).cos() + (x * 1.3 - y * 4.1 + 0.8 * t).sin()) as f32
    }

    fn world() -> World {
        let spec = GridSpec {
            size_m: 6.0,
            spacing_m: 0.05,
            radius_m: 0.12,
        };
        let mut c = Columns::new(SAMPLES);
        let mut y = -3.0;
        while y <= 3.0 {
            let mut x = -3.0;
            while x <= 3.0 {
                c.positions.push([x, y]);
                c.stamps_ns.push(0);
                c.channels.push(0);
                c.values.extend((0..SAMPLES).map(|d| texture(x, y, d)));
                x += 0.035;
            }
            y += 0.1;
        }
        World {
            grid: LocalGrid::build(&spec, [0.0, 0.0], SAMPLES, &[&c]),
            geometry: ArrayGeometry::default(),
        }
    }

    fn sweep_at(w: &World, pose: &Pose5) -> Vec<f32> {
        let mut out = Vec::new();
        for k in 0..11 {
            let o = w.geometry.channel_y_m(k, 11);
            let (x, y) = ArrayGeometry::to_world(pose[0], pose[1], pose[3], 0.0, o);
            let shift = ((pose[2] + o * pose[4].sin()) * 2.0 / C_M_PER_NS / DT_NS).round() as i64;
            out.extend((0..SAMPLES as i64).map(|d| texture(x, y, (d - shift).clamp(0, 39) as usize)));
        }
        out
    }

    fn params() -> TrackParams {
        TrackParams {
            window_start: 4,
            window_len: 32,
            ..TrackParams::default()
        }
    }

    #[test]
    fn pso_finds_a_planted_5_dof_offset() {
        let w = world();
        let truth = [0.43, -0.61, 0.012, 0.02, 0.015];
        let sweep = sweep_at(&w, &truth);
        let mut t = Tracker::new(params(), &w.geometry, 11);
        // the INS is 0.9 m and 1.5 degrees off
        let ins = InsState {
            xy_m: [truth[0] - 0.6, truth[1] + 0.7],
            yaw_rad: truth[3] - 0.026,
            velocity_mps: [0.0, 0.0],
        };
        let out = t.track(&w.grid, DT_NS, &sweep, SAMPLES, 0, &ins).expect("fits");
        let err = (out.registered[0] - truth[0]).hypot(out.registered[1] - truth[1]);
        assert!(out.locked, "{out:?}");
        assert!(err < 0.04, "position error {err} m: {out:?}");
        assert!((out.registered[2] - truth[2]).abs() < 0.006, "{out:?}");
        assert!(out.correlation > 0.95);
        // locked: the box shrinks
        let next = t
            .track(&w.grid, DT_NS, &sweep, SAMPLES, 10_000_000, &ins)
            .expect("fits");
        assert!(next.search_xy_m < out.search_xy_m);
    }

    /// A swarm too small for its box (2 particles, 2 iterations) stops short of the peak; the
    /// retry with the largest swarm reaches it, and only a miss costs the second search.
    #[test]
    fn a_near_miss_is_searched_once_more_with_the_largest_swarm() {
        let w = world();
        let truth = [0.43, -0.61, 0.012, 0.02, 0.015];
        let sweep = sweep_at(&w, &truth);
        // inside the smallest box (0.1 m, 2 cm, 0.5 and 1 degree) but far from its centre
        let ins = InsState {
            xy_m: [truth[0] - 0.08, truth[1] + 0.07],
            yaw_rad: truth[3] - 0.006,
            velocity_mps: [0.0, 0.0],
        };
        let run = |retry_misses: bool| {
            let p = TrackParams {
                particles_min: 2,
                particles_max: 2,
                iterations_min: 2,
                iterations_max: 2,
                // 10 cm off the peak this texture still correlates 0.96
                lock_correlation: 0.99,
                retry_misses,
                ..params()
            };
            let mut t = Tracker::new(p, &w.geometry, 11);
            t.params.particles_max = 200;
            t.params.iterations_max = 100;
            t.level = 0.0;
            t.track(&w.grid, DT_NS, &sweep, SAMPLES, 0, &ins).expect("fits")
        };
        let (once, again) = (run(false), run(true));
        assert!(!once.locked && once.evaluations <= 6, "{once:?}");
        assert!(again.locked && again.evaluations > 1000, "{again:?}");
        let err = (again.registered[0] - truth[0]).hypot(again.registered[1] - truth[1]);
        assert!(err < 0.04, "position error {err} m: {again:?}");
    }

    #[test]
    fn each_lock_criterion_fails_on_its_own() {
        let p = TrackParams::default();
        let good = Correlation {
            value: 0.95,
            overlap: 11,
        };
        assert_eq!(lock_check(&p, good, 0.1, Some(0.0)), None);
        assert_eq!(lock_check(&p, good, 5.0, None), None);
        let low = Correlation {
            value: 0.89,
            overlap: 11,
        };
        assert_eq!(lock_check(&p, low, 0.1, Some(0.0)), Some(Miss::Correlation));
        let few = Correlation {
            value: 0.99,
            overlap: 1,
        };
        assert_eq!(lock_check(&p, few, 0.1, Some(0.0)), Some(Miss::Overlap));
        // two channels keep a lock but do not acquire one
        let two = Correlation {
            value: 0.99,
            overlap: 2,
        };
        assert_eq!(lock_check(&p, two, 0.1, Some(0.0)), None);
        assert_eq!(lock_check(&p, two, 0.1, None), Some(Miss::Overlap));
        assert_eq!(lock_check(&p, two, 0.1, Some(10.0)), Some(Miss::Overlap));
        assert_eq!(lock_check(&p, good, 0.3, Some(0.0)), Some(Miss::Gate));
        // the gate widens with the time since the last lock
        assert_eq!(lock_check(&p, good, 0.3, Some(1.0)), None);
    }

    #[test]
    fn off_the_map_it_dead_reckons_and_widens() {
        let w = world();
        let mut t = Tracker::new(params(), &w.geometry, 11);
        let truth = [0.0, 0.0, 0.0, 0.0, 0.0];
        let sweep = sweep_at(&w, &truth);
        let ins = InsState {
            xy_m: [0.0, 0.0],
            yaw_rad: 0.0,
            velocity_mps: [2.0, 0.0],
        };
        let first = t.track(&w.grid, DT_NS, &sweep, SAMPLES, 0, &ins).expect("fits");
        assert!(first.locked);
        // a sweep of noise: no lock, the pose moves on at the INS velocity, the box grows
        let noise: Vec<f32> = (0..11 * SAMPLES).map(|i| ((i * 7919) % 101) as f32 - 50.0).collect();
        let out = t
            .track(&w.grid, DT_NS, &noise, SAMPLES, 500_000_000, &ins)
            .expect("fits");
        assert!(!out.locked && out.miss.is_some(), "{out:?}");
        assert!((out.pose[0] - (first.pose[0] + 1.0)).abs() < 1e-9);
        assert!(out.sigma_m > first.sigma_m);
        // once dead reckoning is less certain than the GPS/INS, the GPS/INS position
        let late = t
            .track(&w.grid, DT_NS, &noise, SAMPLES, 9_000_000_000, &ins)
            .expect("fits");
        assert!(
            !late.locked && late.pose[0] == ins.xy_m[0] && late.sigma_m == 0.5,
            "{late:?}"
        );
        let again = t
            .track(&w.grid, DT_NS, &noise, SAMPLES, 600_000_000, &ins)
            .expect("fits");
        // a sweep of the wrong size is refused
        assert!(
            t.track(&w.grid, DT_NS, &noise[1..], SAMPLES, 700_000_000, &ins)
                .is_none()
        );
        assert!(!again.locked && again.search_xy_m > out.search_xy_m, "{again:?}");
    }

    #[test]
    fn parameter_checks_name_the_key() {
        let mut p = TrackParams::default();
        p.search_min.xy_m = 5.0;
        assert!(p.check().expect_err("must fail").to_string().contains("search_min"));
        let mut p = TrackParams::default();
        p.swarm.inertia_start = 1.5;
        assert!(
            p.check()
                .expect_err("must fail")
                .to_string()
                .contains("swarm.inertia_start")
        );
        let p = TrackParams {
            lock_correlation: f64::NAN,
            ..TrackParams::default()
        };
        assert!(
            p.check()
                .expect_err("must fail")
                .to_string()
                .contains("lock_correlation")
        );
        assert!(TrackParams::default().check().is_ok());
    }
}
