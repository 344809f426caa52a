//! Motion on the ground: paths of straight lines and circular arcs, driven with a
//! trapezoidal speed profile per leg (stopping at the ends of legs), turns in place, a
//! small roll/pitch/height wobble and (optionally) a smooth sideways wander off the planned
//! path. Everything is analytic in time, so positions, velocities, accelerations and angular
//! rates agree exactly — the IMU sees the derivatives of the pose that the radar and the
//! ground truth see. Only the odometer of a wandering leg is integrated numerically (a table
//! at 5 mm of planned path).

use std::f64::consts::{FRAC_PI_2, PI, TAU};

use nalgebra::{Rotation3, UnitQuaternion, Vector2, Vector3};

use gprflow::geometry::wrap_angle;

use crate::rng::Rng;
use crate::scenario::{Run, Trajectory, Vibration, Wander};

/// Standard gravity, m/s^2.
pub const GRAVITY_MPS2: f64 = 9.80665;

type V2 = Vector2<f64>;

/// A piece of path.
#[derive(Debug, Clone, Copy)]
enum Piece {
    Line {
        start: V2,
        heading_rad: f64,
        length_m: f64,
    },
    Arc {
        center: V2,
        radius_m: f64,
        start_angle_rad: f64,
        sweep_rad: f64,
    },
}

/// A point of a path: position, tangent heading, signed curvature (left turns positive).
#[derive(Debug, Clone, Copy)]
struct PathPoint {
    position: V2,
    heading_rad: f64,
    curvature_per_m: f64,
}

impl Piece {
    fn length(&self) -> f64 {
        match *self {
            Piece::Line { length_m, .. } => length_m,
            Piece::Arc {
                radius_m, sweep_rad, ..
            } => radius_m * sweep_rad.abs(),
        }
    }

    fn at(&self, s: f64) -> PathPoint {
        match *self {
            Piece::Line { start, heading_rad, .. } => PathPoint {
                position: start + s * V2::new(heading_rad.cos(), heading_rad.sin()),
                heading_rad,
                curvature_per_m: 0.0,
            },
            Piece::Arc {
                center,
                radius_m,
                start_angle_rad,
                sweep_rad,
            } => {
                let dir = sweep_rad.signum();
                let angle = start_angle_rad + dir * s / radius_m;
                PathPoint {
                    position: center + radius_m * V2::new(angle.cos(), angle.sin()),
                    heading_rad: angle + dir * FRAC_PI_2,
                    curvature_per_m: dir / radius_m,
                }
            }
        }
    }

    fn end(&self) -> PathPoint {
        self.at(self.length())
    }
}

/// Pieces driven without stopping.
#[derive(Debug, Clone)]
struct Leg {
    pieces: Vec<Piece>,
    /// Arc length at the start of each piece.
    starts: Vec<f64>,
    length_m: f64,
    /// Driven backwards: the body faces against the path.
    reverse: bool,
    speed_mps: f64,
    accel_mps2: f64,
    /// The sideways deviation while driving this leg, if the run wanders (boxed: most legs
    /// have none).
    lateral: Option<Box<Lateral>>,
}

/// Number of sinusoids in a wander field.
const WANDER_TERMS: usize = 6;

/// The largest possible deviation of a wander field, in units of its RMS (every term at
/// its peak: `sqrt(2 * WANDER_TERMS)`).
pub const WANDER_PEAK_PER_SIGMA: f64 = 3.464_101_615_137_754_6;

/// Planned arc length between the entries of a wandering leg's odometer table, m.
const DRIVEN_TABLE_STEP_M: f64 = 0.005;

/// A smooth random function of the distance driven: a sum of sinusoids, RMS `sigma_m`.
#[derive(Debug, Clone)]
struct WanderField {
    terms: [(f64, f64, f64); WANDER_TERMS], // amplitude, wavenumber (rad/m), phase
    ramp_m: f64,
}

impl WanderField {
    fn new(w: &Wander, rng: &mut Rng) -> Self {
        let amplitude = w.sigma_m * (2.0 / WANDER_TERMS as f64).sqrt();
        let mut terms = [(0.0, 0.0, 0.0); WANDER_TERMS];
        for term in &mut terms {
            let wavelength = w.wavelength_m * rng.range(0.5, 1.5);
            *term = (amplitude, TAU / wavelength, rng.range(0.0, TAU));
        }
        Self {
            terms,
            ramp_m: w.ramp_m,
        }
    }

    /// Value and first two derivatives at `d` metres driven.
    fn eval(&self, d: f64) -> (f64, f64, f64) {
        sum_of_sines(&self.terms, d)
    }
}

/// `sum a sin(w x + p)` over `terms` (amplitude, angular frequency, phase), with its first
/// and second derivatives in `x`.
fn sum_of_sines(terms: &[(f64, f64, f64)], x: f64) -> (f64, f64, f64) {
    let mut out = (0.0, 0.0, 0.0);
    for &(a, w, p) in terms {
        let (s, c) = (w * x + p).sin_cos();
        out.0 += a * s;
        out.1 += a * w * c;
        out.2 -= a * w * w * s;
    }
    out
}

/// The wander over one leg: the field from where the leg starts, faded in and out, and the
/// distance actually driven along the offset path.
#[derive(Debug, Clone)]
struct Lateral {
    field: WanderField,
    /// Distance driven (all legs, unsigned) when this leg starts, m.
    distance_at_start_m: f64,
    /// Distance driven along the offset path at every `DRIVEN_TABLE_STEP_M` of planned arc
    /// length, from the leg's start.
    driven_m: Vec<f64>,
}

/// 0 -> 1 over `ramp` after `s = 0`, 1 -> 0 over `ramp` before `s = length` (sin^2 ramps),
/// with first and second derivatives.
fn taper(s: f64, length: f64, ramp: f64) -> (f64, f64, f64) {
    let c = PI / ramp;
    if s < ramp {
        let x = c * s;
        (0.5 * (1.0 - x.cos()), 0.5 * c * x.sin(), 0.5 * c * c * x.cos())
    } else if s > length - ramp {
        let x = c * (length - s);
        (0.5 * (1.0 - x.cos()), -0.5 * c * x.sin(), 0.5 * c * c * x.cos())
    } else {
        (1.0, 0.0, 0.0)
    }
}

impl Leg {
    fn new(pieces: Vec<Piece>, reverse: bool, speed_mps: f64, accel_mps2: f64) -> Self {
        let mut starts = Vec::with_capacity(pieces.len());
        let mut total = 0.0;
        for p in &pieces {
            starts.push(total);
            total += p.length();
        }
        Self {
            pieces,
            starts,
            length_m: total,
            reverse,
            speed_mps,
            accel_mps2,
            lateral: None,
        }
    }

    /// Lets this leg wander, `distance_at_start_m` metres into the run's driving.
    fn set_wander(&mut self, field: &WanderField, distance_at_start_m: f64) {
        if self.length_m <= 0.0 {
            return;
        }
        self.lateral = Some(Box::new(Lateral {
            field: field.clone(),
            distance_at_start_m,
            driven_m: Vec::new(),
        }));
        let steps = (self.length_m / DRIVEN_TABLE_STEP_M).ceil() as usize;
        let ds = self.length_m / steps as f64;
        let rate = |s: f64| {
            let p = self.at(s);
            let (w, w1, _) = self.offset(s);
            (1.0 - p.curvature_per_m * w).hypot(w1)
        };
        let mut driven = Vec::with_capacity(steps + 1);
        driven.push(0.0);
        let (mut total, mut last) = (0.0, rate(0.0));
        for i in 1..=steps {
            // Simpson's rule over each step
            let s = i as f64 * ds;
            let (mid, end) = (rate(s - 0.5 * ds), rate(s));
            total += ds / 6.0 * (last + 4.0 * mid + end);
            driven.push(total);
            last = end;
        }
        if let Some(l) = &mut self.lateral {
            l.driven_m = driven;
        }
    }

    /// The sideways offset (left of the path positive) `s` metres into the leg, with its
    /// first and second derivatives along the planned path.
    fn offset(&self, s: f64) -> (f64, f64, f64) {
        let Some(l) = &self.lateral else {
            return (0.0, 0.0, 0.0);
        };
        let (w, w1, w2) = l.field.eval(l.distance_at_start_m + s);
        let (g, g1, g2) = taper(s, self.length_m, l.field.ramp_m.min(0.5 * self.length_m));
        (g * w, g1 * w + g * w1, g2 * w + 2.0 * g1 * w1 + g * w2)
    }

    /// Distance driven when `s` metres of the planned path are done, m.
    fn driven(&self, s: f64) -> f64 {
        match &self.lateral {
            Some(l) if l.driven_m.len() > 1 => {
                let steps = l.driven_m.len() - 1;
                let x = (s / self.length_m * steps as f64).clamp(0.0, steps as f64);
                let i = (x.floor() as usize).min(steps - 1);
                let f = x - i as f64;
                l.driven_m[i] + f * (l.driven_m[i + 1] - l.driven_m[i])
            }
            _ => s,
        }
    }

    /// Distance driven over the whole leg, m.
    fn driven_length(&self) -> f64 {
        self.driven(self.length_m)
    }

    fn at(&self, s: f64) -> PathPoint {
        let i = self.starts.partition_point(|&x| x <= s).saturating_sub(1);
        self.pieces[i].at((s - self.starts[i]).min(self.pieces[i].length()))
    }

    /// The peak speed reached and the time to reach it (trapezoid or triangle).
    fn profile(&self) -> (f64, f64, f64) {
        let a = self.accel_mps2;
        let v = self.speed_mps.min((a * self.length_m).sqrt());
        let t_acc = v / a;
        let s_acc = 0.5 * a * t_acc * t_acc;
        let t_cruise = ((self.length_m - 2.0 * s_acc) / v).max(0.0);
        (v, t_acc, t_cruise)
    }

    fn duration(&self) -> f64 {
        if self.length_m <= 0.0 {
            return 0.0;
        }
        let (_, t_acc, t_cruise) = self.profile();
        2.0 * t_acc + t_cruise
    }

    /// Arc length, speed and acceleration along the path at `t` into the leg.
    fn progress(&self, t: f64) -> (f64, f64, f64) {
        let (v, t_acc, t_cruise) = self.profile();
        let a = self.accel_mps2;
        let s_acc = 0.5 * a * t_acc * t_acc;
        if t < t_acc {
            (0.5 * a * t * t, a * t, a)
        } else if t < t_acc + t_cruise {
            (s_acc + v * (t - t_acc), v, 0.0)
        } else {
            let td = (t - t_acc - t_cruise).min(t_acc);
            (s_acc + v * t_cruise + v * td - 0.5 * a * td * td, v - a * td, -a)
        }
    }
}

#[derive(Debug, Clone)]
enum Phase {
    Hold { position: V2, heading_rad: f64 },
    Turn { position: V2, from_rad: f64, by_rad: f64 },
    Drive { leg: Leg, odometer_at_start_m: f64 },
}

/// The body's state at one instant.
#[derive(Debug, Clone, Copy)]
pub struct Kinematics {
    /// Body position in the world, m (z up; 0 = resting height).
    pub position_m: Vector3<f64>,
    /// `world_from_body` rotation (x forward, y left, z up).
    pub world_from_body: UnitQuaternion<f64>,
    /// Heading, rad.
    pub yaw_rad: f64,
    /// Velocity in the world, m/s.
    pub velocity_mps: Vector3<f64>,
    /// Acceleration in the world, m/s^2.
    pub accel_mps2: Vector3<f64>,
    /// Angular rate in the body frame, rad/s.
    pub angular_rate_radps: Vector3<f64>,
    /// Specific force in the body frame (what an accelerometer reads), m/s^2.
    pub specific_force_mps2: Vector3<f64>,
    /// Signed distance travelled along track (decreases when driving backwards), m.
    pub odometer_m: f64,
    /// Signed speed along the body's x axis, m/s.
    pub forward_speed_mps: f64,
    /// Signed acceleration along track, m/s^2.
    pub forward_accel_mps2: f64,
}

impl Kinematics {
    /// The body at rest at the origin, level, facing +x: the accelerometer reads gravity up.
    #[must_use]
    pub fn at_rest() -> Self {
        Self {
            position_m: Vector3::zeros(),
            world_from_body: UnitQuaternion::identity(),
            yaw_rad: 0.0,
            velocity_mps: Vector3::zeros(),
            accel_mps2: Vector3::zeros(),
            angular_rate_radps: Vector3::zeros(),
            specific_force_mps2: Vector3::new(0.0, 0.0, GRAVITY_MPS2),
            odometer_m: 0.0,
            forward_speed_mps: 0.0,
            forward_accel_mps2: 0.0,
        }
    }
}

/// Sums of three sinusoids, with first and second derivatives.
#[derive(Debug, Clone)]
struct Wobble {
    terms: [(f64, f64, f64); 3], // amplitude, angular frequency, phase
}

impl Wobble {
    fn new(peak: f64, frequency_hz: f64, rng: &mut Rng) -> Self {
        let mut terms = [(0.0, 0.0, 0.0); 3];
        for (term, ratio) in terms.iter_mut().zip([0.6, 1.0, 1.7]) {
            let f = frequency_hz * ratio * rng.range(0.8, 1.2);
            *term = (peak / 3.0, TAU * f, rng.range(0.0, TAU));
        }
        Self { terms }
    }

    fn eval(&self, t: f64) -> (f64, f64, f64) {
        sum_of_sines(&self.terms, t)
    }
}

/// A run's motion: phases in time plus the wobble.
#[derive(Debug, Clone)]
pub struct Motion {
    phases: Vec<(f64, f64, Phase)>, // start, duration, phase
    duration_s: f64,
    roll: Wobble,
    pitch: Wobble,
    height: Wobble,
}

const TURN_RATE_RADPS: f64 = 0.8;

impl Motion {
    /// Builds the motion of `run`; the wobble (and the wander, if the run has one) is drawn
    /// from `rng`.
    pub fn new(run: &Run, vibration: &Vibration, rng: &mut Rng) -> Self {
        let plan = Planner::of(&run.trajectory);
        let (first_pos, first_heading) = plan.first.unwrap_or((V2::zeros(), 0.0));
        let mut phases = Vec::new();
        let mut t = 0.0;
        phases.push((
            t,
            run.start_pause_s,
            Phase::Hold {
                position: first_pos,
                heading_rad: first_heading,
            },
        ));
        t += run.start_pause_s;
        for (d, p) in plan.phases {
            phases.push((t, d, p));
            t += d;
        }
        let (pos, heading) = plan.last;
        phases.push((
            t,
            run.end_pause_s,
            Phase::Hold {
                position: pos,
                heading_rad: heading,
            },
        ));
        t += run.end_pause_s;
        let f = vibration.frequency_hz;
        let roll = Wobble::new(vibration.roll_deg.to_radians(), f, rng);
        let pitch = Wobble::new(vibration.pitch_deg.to_radians(), f, rng);
        let height = Wobble::new(vibration.height_m, f, rng);
        if let Some(w) = run.wander.as_ref().filter(|w| w.sigma_m > 0.0) {
            let field = WanderField::new(w, rng);
            let (mut distance, mut odometer) = (0.0, 0.0);
            for (_, _, phase) in &mut phases {
                if let Phase::Drive {
                    leg,
                    odometer_at_start_m,
                } = phase
                {
                    leg.set_wander(&field, distance);
                    distance += leg.length_m;
                    *odometer_at_start_m = odometer;
                    let driven = leg.driven_length();
                    odometer += if leg.reverse { -driven } else { driven };
                }
            }
        }
        Self {
            phases,
            duration_s: t,
            roll,
            pitch,
            height,
        }
    }

    /// Length of the run, s.
    pub fn duration_s(&self) -> f64 {
        self.duration_s
    }

    /// The state at `t` seconds into the run (clamped to the run).
    pub fn at(&self, t: f64) -> Kinematics {
        let t = t.clamp(0.0, self.duration_s);
        let i = self
            .phases
            .partition_point(|(start, _, _)| *start <= t)
            .saturating_sub(1);
        let (start, duration, phase) = &self.phases[i];
        let tau = (t - start).min(*duration);
        // planar part: position, heading, yaw rate, velocity, acceleration, odometer
        let (pos, yaw, yaw_rate, vel, acc, odo, fwd_speed, fwd_acc) = match phase {
            Phase::Hold { position, heading_rad } => {
                (*position, *heading_rad, 0.0, V2::zeros(), V2::zeros(), None, 0.0, 0.0)
            }
            Phase::Turn {
                position,
                from_rad,
                by_rad,
            } => {
                let x = PI * tau / duration;
                let yaw = from_rad + by_rad * 0.5 * (1.0 - x.cos());
                let rate = by_rad * 0.5 * x.sin() * PI / duration;
                (*position, yaw, rate, V2::zeros(), V2::zeros(), None, 0.0, 0.0)
            }
            Phase::Drive {
                leg,
                odometer_at_start_m,
            } => {
                let (s, v, a) = leg.progress(tau);
                let p = leg.at(s);
                let kappa = p.curvature_per_m;
                let tangent = V2::new(p.heading_rad.cos(), p.heading_rad.sin());
                let normal = V2::new(-tangent.y, tangent.x);
                // the offset path p(s) + w(s) n(s) and its derivatives along the plan
                let (w, w1, w2) = leg.offset(s);
                let (q, r) = (1.0 - kappa * w, w1);
                let rate = q.hypot(r); // driven distance per metre of plan
                let dir = q * tangent + r * normal;
                let bend = -2.0 * kappa * r * tangent + (kappa * q + w2) * normal;
                let heading = p.heading_rad + r.atan2(q);
                let turn_per_m = (kappa * (q * q + 2.0 * r * r) + q * w2) / (rate * rate);
                let rate_per_m = r * (w2 - kappa * q) / rate;
                let sign = if leg.reverse { -1.0 } else { 1.0 };
                let yaw = wrap_angle(if leg.reverse { heading + PI } else { heading });
                (
                    p.position + w * normal,
                    yaw,
                    turn_per_m * v,
                    v * dir,
                    a * dir + v * v * bend,
                    Some(odometer_at_start_m + sign * leg.driven(s)),
                    sign * v * rate,
                    sign * (a * rate + v * v * rate_per_m),
                )
            }
        };
        let yaw = wrap_angle(yaw);
        let odometer_m = odo.unwrap_or_else(|| self.odometer_before(i));
        let (roll, roll_rate, _) = self.roll.eval(t);
        let (pitch, pitch_rate, _) = self.pitch.eval(t);
        let (z, z_rate, z_acc) = self.height.eval(t);
        let world_from_body = Rotation3::from_euler_angles(roll, pitch, yaw);
        let (sr, cr) = roll.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        let angular_rate_radps = Vector3::new(
            roll_rate - yaw_rate * sp,
            pitch_rate * cr + yaw_rate * cp * sr,
            -pitch_rate * sr + yaw_rate * cp * cr,
        );
        let accel_mps2 = Vector3::new(acc.x, acc.y, z_acc);
        let specific_force_mps2 = world_from_body.inverse() * (accel_mps2 + Vector3::new(0.0, 0.0, GRAVITY_MPS2));
        Kinematics {
            position_m: Vector3::new(pos.x, pos.y, z),
            world_from_body: UnitQuaternion::from_rotation_matrix(&world_from_body),
            yaw_rad: yaw,
            velocity_mps: Vector3::new(vel.x, vel.y, z_rate),
            accel_mps2,
            angular_rate_radps,
            specific_force_mps2,
            odometer_m,
            forward_speed_mps: fwd_speed,
            forward_accel_mps2: fwd_acc,
        }
    }

    fn odometer_before(&self, phase: usize) -> f64 {
        self.phases[..phase]
            .iter()
            .rev()
            .find_map(|(_, _, p)| match p {
                Phase::Drive {
                    leg,
                    odometer_at_start_m,
                } => Some(
                    odometer_at_start_m
                        + if leg.reverse {
                            -leg.driven_length()
                        } else {
                            leg.driven_length()
                        },
                ),
                _ => None,
            })
            .unwrap_or(0.0)
    }
}

/// Collects phases while a trajectory is laid out.
#[derive(Debug, Default)]
struct Planner {
    phases: Vec<(f64, Phase)>,
    first: Option<(V2, f64)>,
    last: (V2, f64),
    odometer_m: f64,
}

impl Planner {
    /// The phases of `trajectory`.
    fn of(trajectory: &Trajectory) -> Self {
        let accel = match trajectory {
            Trajectory::Highway { .. } => 1.5,
            _ => 0.4,
        };
        let mut plan = Self::default();
        build(trajectory, accel, &mut plan);
        plan
    }

    fn drive(&mut self, pieces: Vec<Piece>, reverse: bool, speed: f64, accel: f64) {
        let Some(first) = pieces.first() else { return };
        let start = first.at(0.0);
        let face = |h: f64| if reverse { h + PI } else { h };
        let start_heading = face(start.heading_rad);
        match self.first {
            None => self.first = Some((start.position, start_heading)),
            Some(_) => self.turn_to(start_heading),
        }
        let leg = Leg::new(pieces, reverse, speed, accel);
        let end = leg.at(leg.length_m);
        let duration = leg.duration();
        let length = leg.length_m;
        self.phases.push((
            duration,
            Phase::Drive {
                leg,
                odometer_at_start_m: self.odometer_m,
            },
        ));
        self.odometer_m += if reverse { -length } else { length };
        self.last = (end.position, face(end.heading_rad));
    }

    fn turn_to(&mut self, heading: f64) {
        let (pos, from) = self.last;
        let by = wrap_angle(heading - from);
        if by.abs() > 1e-9 {
            let duration = (by.abs() / TURN_RATE_RADPS * 1.5).max(1.0);
            self.phases.push((
                duration,
                Phase::Turn {
                    position: pos,
                    from_rad: from,
                    by_rad: by,
                },
            ));
            self.last = (pos, from + by);
        }
    }

    fn pause(&mut self, seconds: f64) {
        if seconds > 0.0 {
            let (position, heading_rad) = self.last;
            self.phases.push((seconds, Phase::Hold { position, heading_rad }));
        }
    }
}

/// Radius of the tightest bend in `run`'s planned path, m (infinite for straight lines; turns
/// in place are not bends).
pub fn tightest_radius_m(run: &Run) -> f64 {
    Planner::of(&run.trajectory)
        .phases
        .iter()
        .filter_map(|(_, p)| match p {
            Phase::Drive { leg, .. } => Some(leg),
            _ => None,
        })
        .flat_map(|leg| &leg.pieces)
        .filter_map(|piece| match piece {
            Piece::Arc { radius_m, .. } => Some(*radius_m),
            Piece::Line { .. } => None,
        })
        .fold(f64::INFINITY, f64::min)
}

/// Whether a run's wander fits its path: the offset path must not fold over itself on the
/// tightest bend (the deviation's peak at most half the bend radius). The error says why.
pub(crate) fn check_wander_fits(run: &Run, wander: &Wander) -> Result<(), String> {
    let reach = WANDER_PEAK_PER_SIGMA * wander.sigma_m;
    let radius = tightest_radius_m(run);
    if reach >= 0.5 * radius {
        return Err(format!(
            "too large for the tightest bend of the path ({radius:.2} m radius): the deviation reaches {reach:.2} m, \
             at most half the radius is allowed"
        ));
    }
    Ok(())
}

fn heading_of(d: V2) -> f64 {
    d.y.atan2(d.x)
}

/// Straight segments between `points` with corners rounded to `radius` (shrunk where the
/// segments are too short).
fn rounded_polyline(points: &[V2], radius: f64) -> Vec<Piece> {
    let mut pieces = Vec::new();
    if points.len() < 2 {
        return pieces;
    }
    let mut cursor = points[0];
    for i in 1..points.len() {
        let a = points[i - 1];
        let b = points[i];
        let seg_heading = heading_of(b - a);
        // trim at b for the corner towards points[i + 1]
        let (end, arc) = if i + 1 < points.len() {
            let c = points[i + 1];
            let turn = wrap_angle(heading_of(c - b) - seg_heading);
            if turn.abs() < 1e-9 {
                (b, None)
            } else {
                let max_trim = 0.5 * (b - a).norm().min((c - b).norm());
                let r = radius.min(max_trim / (turn.abs() / 2.0).tan()).max(1e-3);
                let trim = r * (turn.abs() / 2.0).tan();
                let dir_in = (b - a).normalize();
                let end = b - trim * dir_in;
                let left = V2::new(-dir_in.y, dir_in.x);
                let center = end + turn.signum() * r * left;
                let start_angle = heading_of(end - center);
                (
                    end,
                    Some(Piece::Arc {
                        center,
                        radius_m: r,
                        start_angle_rad: start_angle,
                        sweep_rad: turn,
                    }),
                )
            }
        } else {
            (b, None)
        };
        let length = (end - cursor).norm();
        if length > 1e-9 {
            pieces.push(Piece::Line {
                start: cursor,
                heading_rad: seg_heading,
                length_m: length,
            });
        }
        cursor = end;
        if let Some(arc) = arc {
            cursor = arc.end().position;
            pieces.push(arc);
        }
    }
    pieces
}

fn build(trajectory: &Trajectory, accel: f64, plan: &mut Planner) {
    let v2 = |p: [f64; 2]| V2::new(p[0], p[1]);
    match *trajectory {
        Trajectory::Waypoints {
            ref points,
            speed_mps,
            corner_radius_m,
            pause_s,
        } => {
            let pts: Vec<V2> = points.iter().map(|&p| v2(p)).collect();
            if pause_s > 0.0 {
                for (k, w) in pts.windows(2).enumerate() {
                    if k > 0 {
                        plan.pause(pause_s);
                    }
                    plan.drive(rounded_polyline(w, 0.0), false, speed_mps, accel);
                }
            } else {
                plan.drive(rounded_polyline(&pts, corner_radius_m), false, speed_mps, accel);
            }
        }
        Trajectory::ForwardBackward {
            start,
            heading_deg,
            length_m,
            repeats,
            speed_mps,
            pause_s,
        } => {
            let h = heading_deg.to_radians();
            let a = v2(start);
            let b = a + length_m * V2::new(h.cos(), h.sin());
            for k in 0..repeats {
                if k > 0 {
                    plan.pause(pause_s);
                }
                plan.drive(rounded_polyline(&[a, b], 0.0), false, speed_mps, accel);
                plan.pause(pause_s);
                plan.drive(rounded_polyline(&[b, a], 0.0), true, speed_mps, accel);
            }
        }
        Trajectory::Loop {
            center,
            size_m,
            laps,
            speed_mps,
            corner_radius_m,
        } => {
            let c = v2(center);
            let (hx, hy) = (size_m[0] / 2.0, size_m[1] / 2.0);
            let corners = [
                c + V2::new(hx, -hy),
                c + V2::new(hx, hy),
                c + V2::new(-hx, hy),
                c + V2::new(-hx, -hy),
            ];
            let mut pts = vec![c + V2::new(0.0, -hy)];
            for _ in 0..laps {
                pts.extend_from_slice(&corners);
                pts.push(c + V2::new(0.0, -hy));
            }
            plan.drive(rounded_polyline(&pts, corner_radius_m), false, speed_mps, accel);
        }
        Trajectory::Lawnmower {
            origin,
            heading_deg,
            length_m,
            rows,
            spacing_m,
            speed_mps,
        } => {
            let h = heading_deg.to_radians();
            let along = V2::new(h.cos(), h.sin());
            let left = V2::new(-along.y, along.x);
            let o = v2(origin);
            let r = spacing_m / 2.0;
            let mut pieces = Vec::new();
            for row in 0..rows {
                let forward = row % 2 == 0;
                let start =
                    o + f64::from(row) * spacing_m * left + if forward { V2::zeros() } else { length_m * along };
                let heading = if forward { h } else { h + PI };
                pieces.push(Piece::Line {
                    start,
                    heading_rad: heading,
                    length_m,
                });
                if row + 1 < rows {
                    let end = start + length_m * V2::new(heading.cos(), heading.sin());
                    let sweep = if forward { PI } else { -PI };
                    let center = end + r * left;
                    pieces.push(Piece::Arc {
                        center,
                        radius_m: r,
                        start_angle_rad: heading_of(end - center),
                        sweep_rad: sweep,
                    });
                }
            }
            plan.drive(pieces, false, speed_mps, accel);
        }
        Trajectory::LongDrive {
            start,
            heading_deg,
            length_m,
            meander_m,
            meander_wavelength_m,
            speed_mps,
        } => {
            let h = heading_deg.to_radians();
            let a = v2(start);
            if meander_m <= 0.0 {
                let b = a + length_m * V2::new(h.cos(), h.sin());
                plan.drive(rounded_polyline(&[a, b], 0.0), false, speed_mps, accel);
                return;
            }
            // alternating arcs: a C1 meander of the asked amplitude and wavelength
            let alpha = 2.0 * (4.0 * meander_m / meander_wavelength_m).atan();
            let radius = meander_wavelength_m / (4.0 * alpha.sin());
            let halves = (length_m / (meander_wavelength_m / 2.0)).ceil().max(1.0) as usize;
            let mut pieces = Vec::new();
            let mut pos = a;
            let mut heading = h;
            let mut sweeps = vec![alpha];
            for k in 0..halves {
                sweeps.push(if k % 2 == 0 { -2.0 * alpha } else { 2.0 * alpha });
            }
            sweeps.push(-sweeps.iter().sum::<f64>());
            for sweep in sweeps {
                let dir = sweep.signum();
                let left = V2::new(-heading.sin(), heading.cos());
                let center = pos + dir * radius * left;
                let arc = Piece::Arc {
                    center,
                    radius_m: radius,
                    start_angle_rad: heading_of(pos - center),
                    sweep_rad: sweep,
                };
                let end = arc.end();
                pos = end.position;
                heading = end.heading_rad;
                pieces.push(arc);
            }
            plan.drive(pieces, false, speed_mps, accel);
        }
        Trajectory::Highway {
            lap_length_m,
            bend_radius_m,
            speed_kmh,
            lateral_offset_m,
            laps,
        } => {
            let straight = (lap_length_m - TAU * bend_radius_m) / 2.0;
            let r = bend_radius_m - lateral_offset_m; // counter-clockwise: left is inside
            let mut pieces = Vec::new();
            for _ in 0..laps {
                pieces.push(Piece::Line {
                    start: V2::new(0.0, -r),
                    heading_rad: 0.0,
                    length_m: straight,
                });
                pieces.push(Piece::Arc {
                    center: V2::new(straight, 0.0),
                    radius_m: r,
                    start_angle_rad: -FRAC_PI_2,
                    sweep_rad: PI,
                });
                pieces.push(Piece::Line {
                    start: V2::new(straight, r),
                    heading_rad: PI,
                    length_m: straight,
                });
                pieces.push(Piece::Arc {
                    center: V2::zeros(),
                    radius_m: r,
                    start_angle_rad: FRAC_PI_2,
                    sweep_rad: PI,
                });
            }
            plan.drive(pieces, false, speed_kmh / 3.6, accel);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Run;

    fn run(trajectory: Trajectory) -> Run {
        Run {
            name: "t".into(),
            trajectory,
            soil_moisture: 0.0,
            soil_moisture_per_min: 0.0,
            start_pause_s: 1.0,
            end_pause_s: 1.0,
            wander: None,
            ground_contact: None,
        }
    }

    fn wandering(trajectory: Trajectory, sigma_m: f64) -> Run {
        Run {
            wander: Some(Wander {
                sigma_m,
                wavelength_m: 3.0,
                ramp_m: 1.0,
            }),
            ..run(trajectory)
        }
    }

    fn still() -> Vibration {
        Vibration {
            roll_deg: 0.0,
            pitch_deg: 0.0,
            height_m: 0.0,
            frequency_hz: 1.0,
        }
    }

    /// Velocity and acceleration are the derivatives of position, yaw rate of heading, and
    /// the odometer integrates the forward speed.
    fn check_derivatives(m: &Motion) {
        let h = 1e-4;
        let mut t = 0.013;
        let mut odo = m.at(0.0).odometer_m;
        let mut last_t = 0.0;
        while t < m.duration_s() - 0.01 {
            let (a, k, b) = (m.at(t - h), m.at(t), m.at(t + h));
            let v_num = (b.position_m - a.position_m) / (2.0 * h);
            assert!(
                (v_num - k.velocity_mps).norm() < 1e-3,
                "velocity at {t}: {v_num} vs {}",
                k.velocity_mps
            );
            let yaw_rate = wrap_angle(b.yaw_rad - a.yaw_rad) / (2.0 * h);
            assert!((yaw_rate - k.angular_rate_radps.z).abs() < 1e-3, "yaw rate at {t}");
            // trapezoid integration of speed over the step
            odo += 0.5 * (m.at(last_t).forward_speed_mps + k.forward_speed_mps) * (t - last_t);
            assert!(
                (odo - k.odometer_m).abs() < 1e-2,
                "odometer at {t}: {odo} vs {}",
                k.odometer_m
            );
            last_t = t;
            t += 0.0517;
        }
    }

    /// One trajectory of every kind but the highway (its own test has one).
    fn one_of_each_kind() -> Vec<Trajectory> {
        vec![
            Trajectory::Waypoints {
                points: vec![[0.0, 0.0], [5.0, 0.0], [5.0, 4.0], [0.0, 6.0]],
                speed_mps: 0.6,
                corner_radius_m: 0.5,
                pause_s: 0.0,
            },
            Trajectory::Waypoints {
                points: vec![[0.0, 0.0], [3.0, 0.0], [3.0, 2.0]],
                speed_mps: 0.6,
                corner_radius_m: 0.5,
                pause_s: 1.0,
            },
            Trajectory::ForwardBackward {
                start: [1.0, 2.0],
                heading_deg: 30.0,
                length_m: 4.0,
                repeats: 2,
                speed_mps: 0.5,
                pause_s: 1.0,
            },
            Trajectory::Loop {
                center: [0.0, 0.0],
                size_m: [6.0, 4.0],
                laps: 2,
                speed_mps: 0.7,
                corner_radius_m: 0.8,
            },
            Trajectory::Lawnmower {
                origin: [0.0, 0.0],
                heading_deg: 0.0,
                length_m: 5.0,
                rows: 3,
                spacing_m: 1.0,
                speed_mps: 0.5,
            },
            Trajectory::LongDrive {
                start: [0.0, 0.0],
                heading_deg: 10.0,
                length_m: 30.0,
                meander_m: 1.0,
                meander_wavelength_m: 12.0,
                speed_mps: 1.0,
            },
        ]
    }

    #[test]
    fn every_kind_is_smooth_and_consistent() {
        for kind in one_of_each_kind() {
            let m = Motion::new(&run(kind), &still(), &mut Rng::new(1));
            check_derivatives(&m);
        }
    }

    /// Acceleration is the derivative of velocity, and the forward speed and acceleration
    /// are the speed and acceleration along the body's x axis (away from the instants where
    /// the speed profile switches).
    fn check_accelerations(m: &Motion) {
        let h = 1e-4;
        let mut t = 0.011;
        while t < m.duration_s() - 0.01 {
            let (a, k, b) = (m.at(t - h), m.at(t), m.at(t + h));
            if (a.accel_mps2 - b.accel_mps2).norm() < 1e-2 {
                let acc_num = (b.velocity_mps - a.velocity_mps) / (2.0 * h);
                assert!(
                    (acc_num - k.accel_mps2).norm() < 1e-3,
                    "acceleration at {t}: {acc_num} vs {}",
                    k.accel_mps2
                );
                let fwd_acc = (b.forward_speed_mps - a.forward_speed_mps) / (2.0 * h);
                assert!(
                    (fwd_acc - k.forward_accel_mps2).abs() < 1e-3,
                    "forward acceleration at {t}"
                );
            }
            let forward = k.world_from_body * Vector3::x();
            assert!(
                (forward.xy().dot(&k.velocity_mps.xy()) - k.forward_speed_mps).abs() < 1e-9,
                "forward speed at {t}"
            );
            assert!(
                forward.xy().perp(&k.velocity_mps.xy()).abs() < 1e-9,
                "sideways slip at {t}"
            );
            t += 0.0371;
        }
    }

    #[test]
    fn wandering_paths_are_smooth_and_consistent() {
        for kind in one_of_each_kind() {
            let m = Motion::new(&wandering(kind, 0.08), &still(), &mut Rng::new(1));
            check_derivatives(&m);
            check_accelerations(&m);
        }
    }

    #[test]
    fn passes_over_the_same_ground_wander_apart_and_meet_at_the_stops() {
        let trajectory = Trajectory::ForwardBackward {
            start: [0.0, 0.0],
            heading_deg: 0.0,
            length_m: 8.0,
            repeats: 10,
            speed_mps: 0.5,
            pause_s: 1.0,
        };
        let plain = Motion::new(&run(trajectory.clone()), &still(), &mut Rng::new(1));
        let sigma = 0.1;
        let m = Motion::new(&wandering(trajectory, sigma), &still(), &mut Rng::new(1));
        // where each pass crosses x = 4 (the middle, away from the fades)
        let mut crossings = Vec::new();
        let mut longest = f64::NEG_INFINITY;
        let mut last = m.at(0.0);
        let mut t = 0.0;
        while t < m.duration_s() {
            t += 0.01;
            let k = m.at(t);
            if (last.position_m.x - 4.0) * (k.position_m.x - 4.0) < 0.0 {
                crossings.push(k.position_m.y);
            }
            // at rest it is where the plan is
            if k.forward_speed_mps == 0.0 {
                let p = plain.at(t);
                assert!((k.position_m - p.position_m).norm() < 1e-9, "at rest at {t}");
                assert!(wrap_angle(k.yaw_rad - p.yaw_rad).abs() < 1e-9, "heading at rest at {t}");
            }
            longest = longest.max(k.odometer_m);
            last = k;
        }
        assert_eq!(crossings.len(), 20);
        let rms = (crossings.iter().map(|y| y * y).sum::<f64>() / 20.0).sqrt();
        assert!(rms > 0.4 * sigma && rms < 2.0 * sigma, "sideways RMS {rms}");
        let spread = crossings.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b))
            - crossings.iter().fold(f64::INFINITY, |a, &b| a.min(b));
        assert!(spread > sigma, "passes must differ: spread {spread}");
        // a wandering pass is longer than the planned 8 m, and the odometer knows it
        assert!(longest > 8.0 + 1e-4, "the odometer reached only {longest}");
        let (p_end, k_end) = (plain.at(plain.duration_s()), m.at(m.duration_s()));
        assert!((k_end.position_m - p_end.position_m).norm() < 1e-9);
    }

    #[test]
    fn wander_peak_constant_matches_the_term_count() {
        assert!((WANDER_PEAK_PER_SIGMA - (2.0 * WANDER_TERMS as f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn tightest_radius_is_the_smallest_corner() {
        let r = tightest_radius_m(&run(Trajectory::Loop {
            center: [0.0, 0.0],
            size_m: [6.0, 4.0],
            laps: 1,
            speed_mps: 0.7,
            corner_radius_m: 0.8,
        }));
        assert!((r - 0.8).abs() < 1e-9, "{r}");
        let straight = tightest_radius_m(&run(Trajectory::ForwardBackward {
            start: [0.0, 0.0],
            heading_deg: 0.0,
            length_m: 3.0,
            repeats: 1,
            speed_mps: 0.5,
            pause_s: 1.0,
        }));
        assert!(straight.is_infinite());
    }

    #[test]
    fn forward_backward_keeps_heading_and_returns() {
        let m = Motion::new(
            &run(Trajectory::ForwardBackward {
                start: [0.0, 0.0],
                heading_deg: 0.0,
                length_m: 3.0,
                repeats: 1,
                speed_mps: 0.5,
                pause_s: 1.0,
            }),
            &still(),
            &mut Rng::new(1),
        );
        let end = m.at(m.duration_s());
        assert!(end.position_m.norm() < 1e-9);
        assert!(end.odometer_m.abs() < 1e-9);
        assert!(end.yaw_rad.abs() < 1e-9);
        let mid = m.at(m.duration_s() / 2.0);
        assert!((mid.position_m.x - 3.0).abs() < 1e-9 && mid.forward_speed_mps == 0.0);
    }

    #[test]
    fn highway_lap_closes_at_speed_and_offset() {
        let m = Motion::new(
            &run(Trajectory::Highway {
                lap_length_m: 1600.0,
                bend_radius_m: 60.0,
                speed_kmh: 97.0,
                lateral_offset_m: 1.3,
                laps: 1,
            }),
            &still(),
            &mut Rng::new(1),
        );
        let end = m.at(m.duration_s());
        assert!((end.position_m - Vector3::new(0.0, -58.7, 0.0)).norm() < 1e-6);
        let top = (0..2000)
            .map(|k| m.at(f64::from(k) * m.duration_s() / 2000.0).forward_speed_mps)
            .fold(0.0, f64::max);
        assert!((top - 97.0 / 3.6).abs() < 1e-9);
        check_derivatives(&m);
    }

    #[test]
    fn specific_force_at_rest_is_gravity_up() {
        let m = Motion::new(
            &run(Trajectory::LongDrive {
                start: [0.0, 0.0],
                heading_deg: 0.0,
                length_m: 1.0,
                meander_m: 0.0,
                meander_wavelength_m: 1.0,
                speed_mps: 0.5,
            }),
            &still(),
            &mut Rng::new(1),
        );
        let k = m.at(0.5);
        assert!((k.specific_force_mps2 - Vector3::new(0.0, 0.0, GRAVITY_MPS2)).norm() < 1e-12);
    }
}
