//! What the ground sends back to an antenna: a list of echoes (two-way delay, amplitude),
//! shared by the impulse radar and the SFCW array. Amplitudes are relative to a perfect flat
//! reflector 1 m below the antenna with no losses.

use std::f64::consts::PI;

use nalgebra::Vector3;

use crate::world::{C_M_PER_NS, World, closest_on_segment};

/// Beam response below which a scatterer is left out.
const BEAM_CUTOFF: f64 = 0.03;
/// Squared range inside which spreading stops growing (the antenna's near field), m^2.
const NEAR_FIELD_M2: f64 = 0.04;
/// How strongly a pipe's echo depends on its angle to the antenna's polarisation.
const LINE_POLARISATION: f64 = 0.5;

/// Where an antenna is and how it faces.
#[derive(Debug, Clone, Copy)]
pub struct AntennaPose {
    /// Ground position of the antenna centre, m.
    pub x: f64,
    /// Ground position, m.
    pub y: f64,
    /// Height above the ground, m.
    pub height_m: f64,
    /// Heading of the body, rad (the dipoles lie across it).
    pub yaw_rad: f64,
}

/// One echo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Echo {
    /// Two-way delay after the transmit instant, ns.
    pub delay_ns: f64,
    /// Amplitude relative to a lossless perfect flat reflector at 1 m.
    pub amplitude: f64,
}

/// Replaces `out` with the echoes of the ground, interfaces, texture and objects seen from
/// `pose` by an antenna whose two-way beam is `exp(-(angle / beam)^2)`.
pub fn collect_echoes(world: &mut World, pose: AntennaPose, beam_half_angle_rad: f64, out: &mut Vec<Echo>) {
    out.clear();
    let h = pose.height_m.max(0.0);
    let t_air = 2.0 * h / C_M_PER_NS;
    let beam = beam_half_angle_rad;

    if h > 0.005 {
        let n0 = world.surface_index();
        out.push(Echo {
            delay_ns: t_air,
            amplitude: (1.0 - n0) / (1.0 + n0) / (2.0 * h).max(0.1),
        });
    }
    for i in 1..world.layer_count() {
        let depth = world.interface_depth(i, pose.x, pose.y);
        let col = world.column(pose.x, pose.y, depth);
        let r = world.interface_reflection(i);
        out.push(Echo {
            delay_ns: t_air + col.t0_ns,
            amplitude: r * col.transmission * col.ln_attenuation.exp() / (depth + h).max(0.1),
        });
    }

    // the dipoles lie across the heading: their polarisation angle, doubled
    let pol_angle = 2.0 * (pose.yaw_rad + PI / 2.0);
    let (c2, s2) = (pol_angle.cos(), pol_angle.sin());
    let polarisation = world.texture_polarisation();
    let tan_cut = (beam * (-BEAM_CUTOFF.ln()).sqrt()).min(1.45).tan();
    let radius = (world.texture_depth_m() + h) * tan_cut;
    let inv_beam2 = 1.0 / (beam * beam);
    world.texture_near(pose.x, pose.y, radius, |s| {
        let (dx, dy) = (s.x - pose.x, s.y - pose.y);
        let r_h2 = dx * dx + dy * dy;
        let vertical = s.depth_m + h;
        // outside the cone: skip before any transcendental function
        if r_h2 > vertical * vertical * tan_cut * tan_cut {
            return;
        }
        let theta = (r_h2.sqrt() / vertical).atan();
        let g = (-theta * theta * inv_beam2).exp();
        let col = s.column;
        let slant = (col.t0_ns * col.t0_ns + 4.0 * r_h2 / (col.v_rms_m_per_ns * col.v_rms_m_per_ns)).sqrt();
        let pol = 1.0 + polarisation * (s.orientation[0] * c2 + s.orientation[1] * s2);
        let att = (col.ln_attenuation * slant / col.t0_ns.max(1e-9)).exp();
        out.push(Echo {
            delay_ns: t_air + slant,
            amplitude: s.strength * att * g * pol / (r_h2 + vertical * vertical).max(NEAR_FIELD_M2),
        });
    });

    let world: &World = world;
    for p in &world.points {
        let (dx, dy) = (p.at[0] - pose.x, p.at[1] - pose.y);
        let top = (p.depth_m - p.radius_m).max(0.01);
        if dx * dx + dy * dy > (top + h) * (top + h) * tan_cut * tan_cut {
            continue;
        }
        if let Some((slant, loss)) = path(world, dx, dy, top, h, beam, [p.at[0], p.at[1]]) {
            out.push(Echo {
                delay_ns: t_air + slant,
                amplitude: world.point_response(p) * loss / range2(dx, dy, top, h),
            });
        }
    }

    // a linear object echoes from its point closest to the antenna
    let antenna = Vector3::new(pose.x, pose.y, h);
    for line in &world.lines {
        let c = closest_on_segment(&line.a, &line.b, &antenna);
        let (dx, dy) = (c.x - pose.x, c.y - pose.y);
        let top = (-c.z - line.radius_m).max(0.01);
        if let Some((slant, loss)) = path(world, dx, dy, top, h, beam, [c.x, c.y]) {
            let dir = line.b - line.a;
            let axis = 2.0 * dir.y.atan2(dir.x);
            let pol = 1.0 + LINE_POLARISATION * (axis.cos() * c2 + axis.sin() * s2);
            out.push(Echo {
                delay_ns: t_air + slant,
                amplitude: world.line_response(line, c.x, c.y, top) * loss * pol / range2(dx, dy, top, h).powf(0.75),
            });
        }
    }
}

fn range2(dx: f64, dy: f64, depth: f64, h: f64) -> f64 {
    (dx * dx + dy * dy + (depth + h) * (depth + h)).max(NEAR_FIELD_M2)
}

/// Two-way ground travel time and loss factor (attenuation, transmission, beam) of an echo
/// from `depth` below horizontal offset (dx, dy); `None` outside the beam.
fn path(world: &World, dx: f64, dy: f64, depth: f64, h: f64, beam: f64, at: [f64; 2]) -> Option<(f64, f64)> {
    let r_h2 = dx * dx + dy * dy;
    let theta = (r_h2.sqrt() / (depth + h)).atan();
    let g = (-(theta / beam).powi(2)).exp();
    if g < BEAM_CUTOFF {
        return None;
    }
    let col = world.column(at[0], at[1], depth);
    let slant = (col.t0_ns * col.t0_ns + 4.0 * r_h2 / (col.v_rms_m_per_ns * col.v_rms_m_per_ns)).sqrt();
    let att = (col.ln_attenuation * slant / col.t0_ns.max(1e-9)).exp();
    Some((slant, att * col.transmission * g))
}
