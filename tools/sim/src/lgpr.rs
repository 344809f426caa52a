//! The LGPR's stepped-frequency array (seed 001 §2.1.3, Table I): 12 elements across track,
//! 11 transmit/receive pairs, 51 tones, written as complex S-parameters per tone together
//! with the calibration channel.
//!
//! What each channel measures, per tone f:
//! `S_ant = H(f, t) G_k(f) (C_k(f) + P(f) S_scene(f)) + noise` and `S_cal = H(f, t) K(f) + noise`,
//! with `H` the receive chain drifting with temperature, `G_k` the element's gain and phase
//! mismatch, `C_k` its direct coupling, `P` the antennas' band shape, `K` the calibration
//! path. The factory calibration (anechoic chamber, no ground) is `H0 G_k C_k` with
//! `H0 K` on its calibration channel. Self calibration (eq. 2) removes `H`; the factory
//! calibration (eq. 3-4) removes `G_k` and the coupling, leaving `P S_scene / C_k`.

use std::f64::consts::TAU;

use nalgebra::{Complex, Vector3};

use crate::motion::Kinematics;
use crate::rng::Rng;
use crate::scenario::LgprRadar;
use crate::scene::{AntennaPose, Echo, collect_echoes};
use crate::world::World;

type C64 = Complex<f64>;

/// Delay of the calibration loop-back path, ns.
const CAL_PATH_DELAY_NS: f64 = 1.5;
/// Internal reflections (vehicle underbody, connectors): delay ns, relative amplitude.
const INTERNAL_REFLECTIONS: [(f64, f64); 2] = [(0.6, 0.08), (2.4, 0.04)];

/// The array and its hardware state.
#[derive(Debug)]
pub struct LgprArray {
    cfg: LgprRadar,
    frequencies_ghz: Vec<f64>,
    /// Element gain/phase per channel and tone.
    gain: Vec<Vec<C64>>,
    /// Direct coupling per channel and tone.
    coupling: Vec<Vec<C64>>,
    band: Vec<f64>,
    cal_path: Vec<C64>,
    rng: Rng,
    drift_phase: f64,
    echoes: Vec<Echo>,
}

impl LgprArray {
    /// The array (its hardware drawn from `seed`, the same in every run of a world) with
    /// run noise from `rng`.
    pub fn new(cfg: &LgprRadar, seed: u64, rng: Rng) -> Self {
        let tones = cfg.tones as usize;
        let channels = cfg.elements as usize - 1;
        let frequencies_ghz: Vec<f64> = (0..tones)
            .map(|m| (cfg.start_frequency_hz + m as f64 * cfg.frequency_step_hz) * 1e-9)
            .collect();
        let (f_lo, f_hi) = (frequencies_ghz[0], frequencies_ghz[tones - 1]);
        let span = (f_hi - f_lo).max(1e-9);
        let mut hw = Rng::derive(seed, "lgpr-array", 0);
        let mut gain = Vec::with_capacity(channels);
        let mut coupling = Vec::with_capacity(channels);
        for _ in 0..channels {
            let g = 1.0 + cfg.element_mismatch * hw.normal();
            let phase0 = hw.range(-0.5, 0.5);
            let slope = hw.normal() * 0.3; // rad across the band
            let c = 1.0 + cfg.element_mismatch * hw.normal();
            let ripple_ns = hw.range(2.0, 4.0);
            gain.push(
                frequencies_ghz
                    .iter()
                    .map(|f| C64::from_polar(g, phase0 + slope * (f - f_lo) / span))
                    .collect(),
            );
            coupling.push(
                frequencies_ghz
                    .iter()
                    .map(|f| C64::new(c * (1.0 + 0.05 * (TAU * f * ripple_ns).cos()), 0.0))
                    .collect(),
            );
        }
        let band = frequencies_ghz
            .iter()
            .map(|f| 0.3 + 0.7 * (std::f64::consts::PI * (f - f_lo) / span).sin())
            .collect();
        let cal_path = frequencies_ghz
            .iter()
            .map(|f| C64::from_polar(1.0, -TAU * f * CAL_PATH_DELAY_NS))
            .collect();
        Self {
            cfg: cfg.clone(),
            frequencies_ghz,
            gain,
            coupling,
            band,
            cal_path,
            rng,
            drift_phase: 0.0,
            echoes: Vec::new(),
        }
    }

    /// Number of channels (element pairs).
    pub fn channels(&self) -> usize {
        self.gain.len()
    }

    /// Lateral offset of channel `k`'s midpoint in the body frame (left positive), m.
    pub fn channel_offset_m(&self, k: usize) -> f64 {
        let e = f64::from(self.cfg.elements);
        (k as f64 + 1.0 - (e - 1.0) / 2.0 - 0.5) * self.cfg.element_spacing_m
    }

    fn push(out: &mut Vec<f32>, z: C64) {
        out.push(z.re as f32);
        out.push(z.im as f32);
    }

    /// The factory calibration: (`values`, `calibration`) as a sweep would carry them.
    pub fn factory_calibration(&self) -> (Vec<f32>, Vec<f32>) {
        let mut values = Vec::new();
        for (g, c) in self.gain.iter().zip(&self.coupling) {
            for (gm, cm) in g.iter().zip(c) {
                Self::push(&mut values, gm * cm);
            }
        }
        let mut cal = Vec::new();
        for k in &self.cal_path {
            Self::push(&mut cal, *k);
        }
        (values, cal)
    }

    /// One sweep with the body at `body`, `t_s` seconds into the run.
    pub fn sweep(&mut self, world: &mut World, body: &Kinematics, t_s: f64) -> (Vec<f32>, Vec<f32>) {
        let tones = self.frequencies_ghz.len();
        let f_mid = 0.5 * (self.frequencies_ghz[0] + self.frequencies_ghz[tones - 1]);
        // thermal drift of the receive chain: a slowly growing delay-like phase and gain
        self.drift_phase = self.cfg.thermal_phase_drift_deg_per_min.to_radians() * t_s / 60.0;
        let chain_gain = 1.0 + 0.02 * (TAU * t_s / 300.0).sin();
        let chain: Vec<C64> = self
            .frequencies_ghz
            .iter()
            .map(|f| C64::from_polar(chain_gain, self.drift_phase * f / f_mid))
            .collect();

        let mut values = Vec::with_capacity(2 * tones * self.channels());
        let mut scene = vec![C64::new(0.0, 0.0); tones];
        for k in 0..self.channels() {
            let in_body = Vector3::new(self.cfg.mount_m[0], self.cfg.mount_m[1] + self.channel_offset_m(k), 0.0);
            let p = body.position_m + body.world_from_body * in_body;
            let pose = AntennaPose {
                x: p.x,
                y: p.y,
                height_m: self.cfg.height_m + p.z,
                yaw_rad: body.yaw_rad,
            };
            collect_echoes(world, pose, self.cfg.beam_half_angle_deg.to_radians(), &mut self.echoes);
            scene.iter_mut().for_each(|s| *s = C64::new(0.0, 0.0));
            let level = self.cfg.reflection_level;
            let internal = INTERNAL_REFLECTIONS.iter().map(|&(d, a)| Echo {
                delay_ns: d,
                amplitude: a / level,
            });
            for e in self.echoes.iter().copied().chain(internal) {
                // exp(-j 2 pi f tau) by recurrence over the evenly spaced tones
                let mut phasor = C64::from_polar(level * e.amplitude, -TAU * self.frequencies_ghz[0] * e.delay_ns);
                let step = C64::from_polar(1.0, -TAU * self.cfg.frequency_step_hz * 1e-9 * e.delay_ns);
                for s in scene.iter_mut() {
                    *s += phasor;
                    phasor *= step;
                }
            }
            for m in 0..tones {
                let noise = C64::new(self.rng.normal(), self.rng.normal()) * self.cfg.noise;
                let s = chain[m] * self.gain[k][m] * (self.coupling[k][m] + self.band[m] * scene[m]) + noise;
                Self::push(&mut values, s);
            }
        }
        let mut cal = Vec::with_capacity(2 * tones);
        for (h, k) in chain.iter().zip(&self.cal_path) {
            let noise = C64::new(self.rng.normal(), self.rng.normal()) * self.cfg.noise;
            Self::push(&mut cal, h * k + noise);
        }
        (values, cal)
    }
}
