//! Proprioception and truth: IMU, wheel encoder, total station and GPS/INS, each a pure
//! function of the body's kinematics and its own noise stream.

use nalgebra::{UnitQuaternion, Vector3};

use crate::motion::Kinematics;
use crate::rng::Rng;
use crate::scenario::{GpsConfig, ImuConfig, TruthConfig, WheelConfig};

fn normal3(rng: &mut Rng) -> Vector3<f64> {
    Vector3::new(rng.normal(), rng.normal(), rng.normal())
}

/// One IMU sample.
#[derive(Debug, Clone, Copy)]
pub struct ImuSample {
    /// Angular rate, rad/s (body frame).
    pub gyro_radps: Vector3<f64>,
    /// Specific force, m/s^2 (body frame).
    pub accel_mps2: Vector3<f64>,
    /// The IMU's own orientation estimate (`world_from_body`).
    pub orientation: UnitQuaternion<f64>,
}

/// A MEMS IMU: white noise and random-walk biases per axis.
#[derive(Debug)]
pub struct Imu {
    cfg: ImuConfig,
    rng: Rng,
    gyro_bias: Vector3<f64>,
    accel_bias: Vector3<f64>,
}

impl Imu {
    /// An IMU whose initial biases and noise come from `rng`.
    pub fn new(cfg: &ImuConfig, mut rng: Rng) -> Self {
        let gyro_bias = normal3(&mut rng) * cfg.gyro_bias_sigma;
        let accel_bias = normal3(&mut rng) * cfg.accel_bias_sigma;
        Self {
            cfg: cfg.clone(),
            rng,
            gyro_bias,
            accel_bias,
        }
    }

    /// Sampling interval, s.
    pub fn dt_s(&self) -> f64 {
        1.0 / self.cfg.rate_hz
    }

    /// Current biases (gyro rad/s, accel m/s^2): the truth an estimator tries to recover.
    pub fn biases(&self) -> (Vector3<f64>, Vector3<f64>) {
        (self.gyro_bias, self.accel_bias)
    }

    /// The next sample at `k`.
    pub fn sample(&mut self, k: &Kinematics) -> ImuSample {
        let dt = self.dt_s();
        let c = &self.cfg;
        // discrete white noise: density / sqrt(dt); bias random walk: density * sqrt(dt)
        let gyro = k.angular_rate_radps + self.gyro_bias + normal3(&mut self.rng) * (c.gyro_noise_density / dt.sqrt());
        let accel =
            k.specific_force_mps2 + self.accel_bias + normal3(&mut self.rng) * (c.accel_noise_density / dt.sqrt());
        self.gyro_bias += normal3(&mut self.rng) * (c.gyro_random_walk * dt.sqrt());
        self.accel_bias += normal3(&mut self.rng) * (c.accel_random_walk * dt.sqrt());
        let tilt = normal3(&mut self.rng) * c.orientation_sigma_deg.to_radians();
        ImuSample {
            gyro_radps: gyro,
            accel_mps2: accel,
            orientation: k.world_from_body * UnitQuaternion::from_scaled_axis(tilt),
        }
    }

    /// Diagonal variances (gyro, accel, orientation) the message reports.
    pub fn variances(&self) -> (f64, f64, f64) {
        let dt = self.dt_s();
        (
            self.cfg.gyro_noise_density.powi(2) / dt,
            self.cfg.accel_noise_density.powi(2) / dt,
            self.cfg.orientation_sigma_deg.to_radians().powi(2),
        )
    }
}

/// One encoder reading.
#[derive(Debug, Clone, Copy)]
pub struct WheelReading {
    /// Cumulative ticks (signed).
    pub ticks: i64,
    /// Distance from the ticks with the nominal radius, m.
    pub distance_m: f64,
    /// Speed over the last interval, m/s.
    pub speed_mps: f64,
}

/// A quadrature wheel encoder with scale error and slip.
#[derive(Debug)]
pub struct WheelEncoder {
    cfg: WheelConfig,
    rng: Rng,
    rolled_m: f64,
    last_odometer_m: Option<f64>,
    last_distance_m: f64,
}

impl WheelEncoder {
    /// An encoder drawing slip from `rng`.
    pub fn new(cfg: &WheelConfig, rng: Rng) -> Self {
        Self {
            cfg: cfg.clone(),
            rng,
            rolled_m: 0.0,
            last_odometer_m: None,
            last_distance_m: 0.0,
        }
    }

    /// Reading at `k`, `dt_s` after the previous reading.
    pub fn read(&mut self, k: &Kinematics, dt_s: f64) -> WheelReading {
        let step = k.odometer_m - self.last_odometer_m.unwrap_or(k.odometer_m);
        self.last_odometer_m = Some(k.odometer_m);
        if step != 0.0 {
            // slip: the wheel turns more than the ground moves when accelerating hard
            let slip = self.cfg.slip_per_accel * k.forward_accel_mps2.abs() + self.cfg.slip_noise * self.rng.normal();
            self.rolled_m += step * (1.0 + slip);
        }
        let circumference = std::f64::consts::TAU * self.cfg.wheel_radius_m;
        let ppr = f64::from(self.cfg.pulses_per_revolution);
        let true_tick_m = circumference * (1.0 + self.cfg.scale_error) / ppr;
        let ticks = (self.rolled_m / true_tick_m).floor() as i64;
        let distance_m = ticks as f64 * circumference / ppr;
        let speed_mps = if dt_s > 0.0 {
            (distance_m - self.last_distance_m) / dt_s
        } else {
            0.0
        };
        self.last_distance_m = distance_m;
        WheelReading {
            ticks,
            distance_m,
            speed_mps,
        }
    }
}

/// A total station: the true position with a few millimetres of noise.
#[derive(Debug)]
pub struct TotalStation {
    noise_m: f64,
    rng: Rng,
}

impl TotalStation {
    /// A total station drawing noise from `rng`.
    pub fn new(cfg: &TruthConfig, rng: Rng) -> Self {
        Self {
            noise_m: cfg.noise_m,
            rng,
        }
    }

    /// The measured position for `k`.
    pub fn measure(&mut self, k: &Kinematics) -> Vector3<f64> {
        k.position_m + normal3(&mut self.rng) * self.noise_m
    }
}

/// A GPS/INS fix.
#[derive(Debug, Clone, Copy)]
pub struct GpsFix {
    /// Position, m.
    pub position_m: Vector3<f64>,
    /// Orientation (`world_from_body`).
    pub orientation: UnitQuaternion<f64>,
    /// Velocity in the body frame, m/s.
    pub velocity_body_mps: Vector3<f64>,
}

/// GPS/INS with a second-order Gauss-Markov position error: a first-order Gauss-Markov
/// process (correlation time `correlation_time_s`) low-passed once more with the same time
/// constant, scaled to the configured RMS. The INS between fixes makes a GPS/INS error smooth:
/// its rate stays within the INS's velocity error (a few cm/s), where a first-order process
/// would step by `rms * sqrt(2 dt / tau)` (1.4 cm per 0.1 s fix at 0.25 m and 60 s), a
/// velocity error of 14 cm/s the INS would not make.
#[derive(Debug)]
pub struct Gps {
    cfg: GpsConfig,
    rng: Rng,
    /// The first-order process driving the error, and the error.
    drive: Vector3<f64>,
    error: Vector3<f64>,
}

impl Gps {
    /// A receiver whose error starts from its stationary distribution.
    pub fn new(cfg: &GpsConfig, mut rng: Rng) -> Self {
        // stationary: the first stage at sqrt(2) sigma; the second at sigma, correlated with
        // the first by 1/sqrt(2)
        let sigma = Self::sigma(cfg);
        let a = normal3(&mut rng);
        let b = normal3(&mut rng);
        let drive = (a * std::f64::consts::SQRT_2).component_mul(&sigma);
        let error = (a * std::f64::consts::FRAC_1_SQRT_2 + b * std::f64::consts::FRAC_1_SQRT_2).component_mul(&sigma);
        Self {
            cfg: cfg.clone(),
            rng,
            drive,
            error,
        }
    }

    fn sigma(cfg: &GpsConfig) -> Vector3<f64> {
        let h = cfg.horizontal_rms_m / std::f64::consts::SQRT_2;
        Vector3::new(h, h, cfg.vertical_rms_m)
    }

    /// Per-axis standard deviation of the error, m.
    pub fn sigma_m(&self) -> Vector3<f64> {
        Self::sigma(&self.cfg)
    }

    /// The fix at `k`, `dt_s` after the previous one.
    pub fn fix(&mut self, k: &Kinematics, dt_s: f64) -> GpsFix {
        let tau = self.cfg.correlation_time_s;
        let phi = (-dt_s / tau).exp();
        // the second stage follows the first (exact for a first stage held over the step)
        self.error = self.drive + (self.error - self.drive) * phi;
        let step = (1.0 - phi * phi).sqrt() * std::f64::consts::SQRT_2;
        self.drive = self.drive * phi + self.sigma_m().component_mul(&normal3(&mut self.rng)) * step;
        let heading_noise = normal3(&mut self.rng) * 0.1f64.to_radians();
        GpsFix {
            position_m: k.position_m + self.error,
            orientation: k.world_from_body * UnitQuaternion::from_scaled_axis(heading_noise),
            velocity_body_mps: k.world_from_body.inverse() * k.velocity_mps + normal3(&mut self.rng) * 0.02,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error keeps the configured RMS and is smooth: its step between 10 Hz fixes stays
    /// near an INS's velocity error, far below a first-order process's `rms sqrt(2 dt / tau)`.
    #[test]
    fn gps_ins_error_has_its_rms_and_moves_smoothly() {
        let cfg = GpsConfig::default();
        let k = Kinematics::at_rest();
        let (mut sum_sq, mut step_sq, mut n) = (0.0, 0.0, 0.0);
        // 40 receivers x 2000 s
        for r in 0..40 {
            let mut gps = Gps::new(&cfg, Rng::derive(7, "gps-test", r));
            let mut before = gps.fix(&k, 0.1).position_m;
            for _ in 0..20_000 {
                let now = gps.fix(&k, 0.1).position_m;
                sum_sq += now.x * now.x + now.y * now.y;
                step_sq += (now - before).xy().norm_squared();
                n += 1.0;
                before = now;
            }
        }
        let rms = (sum_sq / n).sqrt();
        assert!(
            (rms - cfg.horizontal_rms_m).abs() < 0.1 * cfg.horizontal_rms_m,
            "horizontal RMS {rms} m"
        );
        let step = (step_sq / n).sqrt();
        let first_order = cfg.horizontal_rms_m * (2.0 * 0.1 / cfg.correlation_time_s).sqrt();
        assert!(
            step < 0.05 * first_order,
            "RMS step {step} m per fix (first order: {first_order} m)"
        );
    }
}
