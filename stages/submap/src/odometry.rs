//! Planar dead reckoning from the wheel encoder and the z gyro.

use gprflow_geometry::Planar;

/// Dead reckoning: the heading integrates the z gyro rate (trapezoid rule between IMU
/// samples), the position advances by each wheel-distance increment along the heading at
/// that moment. The pose starts at the origin.
#[derive(Debug, Clone, Default)]
pub struct PlanarOdometry {
    pose: Planar,
    last_gyro: Option<(i64, f64)>,
    last_distance_m: Option<f64>,
}

impl PlanarOdometry {
    /// Dead reckoning from the origin.
    pub fn new() -> Self {
        Self::default()
    }

    /// A z gyro rate, rad/s, at `stamp_ns`. Samples not newer than the last are ignored.
    pub fn gyro(&mut self, stamp_ns: i64, gyro_z_radps: f64) {
        match self.last_gyro {
            Some((t0, w0)) if stamp_ns > t0 => {
                let dt = (stamp_ns - t0) as f64 * 1e-9;
                self.pose.yaw_rad += 0.5 * (w0 + gyro_z_radps) * dt;
                self.last_gyro = Some((stamp_ns, gyro_z_radps));
            }
            Some(_) => {}
            None => self.last_gyro = Some((stamp_ns, gyro_z_radps)),
        }
    }

    /// A cumulative signed wheel distance, m.
    pub fn wheel(&mut self, distance_m: f64) {
        if let Some(d0) = self.last_distance_m {
            let dd = distance_m - d0;
            self.pose.x_m += dd * self.pose.yaw_rad.cos();
            self.pose.y_m += dd * self.pose.yaw_rad.sin();
        }
        self.last_distance_m = Some(distance_m);
    }

    /// The current pose.
    pub fn pose(&self) -> Planar {
        self.pose
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quarter_circle_ends_where_geometry_says() {
        // radius 2 m at 0.5 m/s: yaw rate 0.25 rad/s; pi/2 takes 2 pi s
        let mut odo = PlanarOdometry::new();
        let (v, r) = (0.5, 2.0);
        let steps = 20_000;
        let t_end = std::f64::consts::FRAC_PI_2 * r / v;
        for k in 0..=steps {
            let t = t_end * k as f64 / steps as f64;
            odo.gyro((t * 1e9) as i64, v / r);
            odo.wheel(v * t);
        }
        let p = odo.pose();
        assert!((p.yaw_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
        assert!((p.x_m - 2.0).abs() < 1e-3, "{p:?}");
        assert!((p.y_m - 2.0).abs() < 1e-3, "{p:?}");
    }
}
