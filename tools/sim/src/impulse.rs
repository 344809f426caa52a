//! Single-channel impulse GPR: each trace sums the pulse returned by every scatterer in the
//! antenna footprint at its two-way travel time, plus the radar's own artefacts (direct
//! coupling, repetitive ringing, wow, DC offset, time-zero jitter, noise, int16 counts).

use std::f64::consts::PI;

use crate::rng::Rng;
use crate::scenario::{GroundContact, ImpulseRadar};
use crate::scene::{AntennaPose, Echo};
use crate::world::World;

const OVERSAMPLE: usize = 32;
/// Pulse support, in periods of the centre frequency on each side.
const PULSE_PERIODS: f64 = 1.6;

/// The radar's transmitted wavelet: a negated Ricker, so the direct coupling's main lobe is
/// negative and zero time is the first negative peak.
pub fn wavelet(t_ns: f64, center_frequency_hz: f64) -> f64 {
    let a = (PI * center_frequency_hz * 1e-9 * t_ns).powi(2);
    -(1.0 - 2.0 * a) * (-a).exp()
}

/// Synthesises traces.
#[derive(Debug)]
pub struct ImpulseGpr {
    cfg: ImpulseRadar,
    table: Vec<f64>,
    half_width_ns: f64,
    rng: Rng,
    dc_offset: f64,
    ringing_gain: f64,
    /// Sample buffer reused between traces.
    buffer: Vec<f64>,
    echoes: Vec<Echo>,
    contact: Option<Contact>,
}

/// The antenna's uneven contact with the ground ([`GroundContact`]): a unit Gauss-Markov
/// process in time whose exponential scales the ringing, drawn from a stream of its own so
/// that a run without it draws the same numbers as before.
#[derive(Debug)]
struct Contact {
    cfg: GroundContact,
    x: f64,
    rng: Rng,
}

impl Contact {
    /// The ringing's strength factor `dt_s` seconds after the previous trace.
    fn step(&mut self, dt_s: f64) -> f64 {
        let a = (-dt_s / self.cfg.correlation_s).exp();
        self.x = a * self.x + (1.0 - a * a).sqrt() * self.rng.normal();
        (self.cfg.ringing_sigma * self.x).exp()
    }
}

impl ImpulseGpr {
    /// A radar with configuration `cfg` drawing its noise from `rng`.
    pub fn new(cfg: &ImpulseRadar, rng: Rng) -> Self {
        let half_width_ns = PULSE_PERIODS * 1e9 / cfg.center_frequency_hz;
        let step = cfg.sample_interval_ns / OVERSAMPLE as f64;
        let n = (2.0 * half_width_ns / step).ceil() as usize + 1;
        let table = (0..n)
            .map(|i| wavelet(i as f64 * step - half_width_ns, cfg.center_frequency_hz))
            .collect();
        Self {
            table,
            half_width_ns,
            dc_offset: cfg.dc_offset_counts,
            ringing_gain: 1.0,
            buffer: vec![0.0; cfg.samples as usize],
            echoes: Vec::new(),
            contact: None,
            rng,
            cfg: cfg.clone(),
        }
    }

    /// Lets the antenna's contact with the ground vary ([`GroundContact`]), with random
    /// numbers from `rng`.
    #[must_use]
    pub fn with_ground_contact(mut self, cfg: &GroundContact, mut rng: Rng) -> Self {
        let x = rng.normal();
        self.contact = Some(Contact {
            cfg: cfg.clone(),
            x,
            rng,
        });
        self
    }

    /// Adds `amplitude` times the wavelet arriving at `tau_ns` (relative to the transmit
    /// instant) to the buffer whose sample 0 is at `t_first_ns`.
    fn add_pulse(&mut self, t_first_ns: f64, tau_ns: f64, amplitude: f64) {
        let dt = self.cfg.sample_interval_ns;
        let n = self.buffer.len() as isize;
        let k_lo = (((tau_ns - self.half_width_ns - t_first_ns) / dt).ceil() as isize).max(0);
        let k_hi = (((tau_ns + self.half_width_ns - t_first_ns) / dt).floor() as isize).min(n - 1);
        if k_hi < k_lo {
            return;
        }
        // table index of sample k_lo; each later sample is OVERSAMPLE entries further on
        let t0 = t_first_ns + k_lo as f64 * dt - tau_ns + self.half_width_ns;
        let first = (t0 * OVERSAMPLE as f64 / dt + 0.5).max(0.0) as usize;
        let samples = &mut self.buffer[k_lo as usize..=k_hi as usize];
        let taps = self.table.get(first..).unwrap_or(&[]).iter().step_by(OVERSAMPLE);
        for (b, w) in samples.iter_mut().zip(taps) {
            *b += amplitude * w;
        }
    }

    /// One trace at `pose`, `dt_s` seconds after the previous one, as int16 counts.
    pub fn trace(&mut self, world: &mut World, pose: AntennaPose, dt_s: f64) -> Vec<i16> {
        let cfg = self.cfg.clone();
        self.buffer.iter_mut().for_each(|b| *b = 0.0);
        let jitter = cfg.time_zero_jitter_ns * self.rng.normal();
        // sample k is at t = (k - time_zero_sample) * dt - jitter after the transmit instant
        let t_first = -cfg.time_zero_sample * cfg.sample_interval_ns - jitter;
        let window_end = t_first + cfg.samples as f64 * cfg.sample_interval_ns;

        // the radar: direct coupling and repetitive ringing (the same everywhere)
        self.ringing_gain *= 1.0 + cfg.ringing.drift_per_s * dt_s.sqrt() * self.rng.normal();
        self.add_pulse(t_first, 0.0, cfg.direct_coupling_counts);
        let contact = self.contact.as_mut().map_or(1.0, |c| c.step(dt_s));
        let mut copy = cfg.direct_coupling_counts * cfg.ringing.first * self.ringing_gain * contact;
        let mut tau = cfg.ringing.period_ns;
        while cfg.ringing.period_ns > 0.0 && tau < window_end + self.half_width_ns && copy.abs() > 1e-3 {
            self.add_pulse(t_first, tau, copy);
            copy *= -cfg.ringing.decay;
            tau += cfg.ringing.period_ns;
        }

        // the ground
        crate::scene::collect_echoes(world, pose, cfg.beam_half_angle_deg.to_radians(), &mut self.echoes);
        for k in 0..self.echoes.len() {
            let e = self.echoes[k];
            self.add_pulse(t_first, e.delay_ns, cfg.reflection_counts * e.amplitude);
        }

        // wow, DC, noise, quantisation
        self.dc_offset += cfg.dc_walk_counts * self.rng.normal();
        let dt = cfg.sample_interval_ns;
        let mut out = Vec::with_capacity(self.buffer.len());
        for k in 0..self.buffer.len() {
            let t = t_first + k as f64 * dt;
            let wow = if t > 0.0 && cfg.wow_time_ns > 0.0 {
                let u = t / cfg.wow_time_ns;
                cfg.wow_counts * u * (1.0 - u).exp()
            } else {
                0.0
            };
            let v = self.buffer[k] + wow + self.dc_offset + cfg.noise_counts * self.rng.normal();
            out.push(v.round().clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wavelet_main_lobe_is_negative_at_zero() {
        assert_eq!(wavelet(0.0, 500e6), -1.0);
        // side lobes positive, about 0.45 of the main lobe at t = +-sqrt(3/2)/(pi f)
        let t = (1.5f64).sqrt() / (PI * 0.5);
        assert!((wavelet(t, 500e6) - 2.0 * (-1.5f64).exp()).abs() < 1e-12);
    }
}
