//! Planar geometry shared by the stages, the simulator and the tools: a pose on the ground
//! plane ([`Planar`]), angle wrapping ([`wrap_angle`]) and a stamped track of poses
//! interpolated between samples ([`Track`]).
//!
//! Frames follow the house convention: x forward at heading 0, y left, heading
//! counter-clockwise positive, angles in radians.

use std::collections::BTreeMap;
use std::f64::consts::{PI, TAU};

/// A planar pose: position (m) and heading (rad) in some frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Planar {
    /// x, m.
    pub x_m: f64,
    /// y, m.
    pub y_m: f64,
    /// Heading (yaw), rad.
    pub yaw_rad: f64,
}

impl Planar {
    /// The pose with heading from a unit quaternion's yaw (`[x, y, z, w]`).
    pub fn from_quaternion(x_m: f64, y_m: f64, q: [f64; 4]) -> Self {
        let [qx, qy, qz, qw] = q;
        let yaw_rad = (2.0 * (qw * qz + qx * qy)).atan2(1.0 - 2.0 * (qy * qy + qz * qz));
        Self { x_m, y_m, yaw_rad }
    }

    /// Whether every component is finite.
    pub fn is_finite(&self) -> bool {
        self.x_m.is_finite() && self.y_m.is_finite() && self.yaw_rad.is_finite()
    }

    /// `other` in this pose's frame: (along, across, heading difference wrapped to ±π).
    pub fn relative(&self, other: &Planar) -> (f64, f64, f64) {
        let (dx, dy) = (other.x_m - self.x_m, other.y_m - self.y_m);
        let (s, c) = self.yaw_rad.sin_cos();
        (
            c * dx + s * dy,
            -s * dx + c * dy,
            wrap_angle(other.yaw_rad - self.yaw_rad),
        )
    }

    /// This pose composed with `delta` (expressed in this pose's frame).
    pub fn compose(&self, delta: &Planar) -> Planar {
        let (s, c) = self.yaw_rad.sin_cos();
        Planar {
            x_m: self.x_m + c * delta.x_m - s * delta.y_m,
            y_m: self.y_m + s * delta.x_m + c * delta.y_m,
            yaw_rad: wrap_angle(self.yaw_rad + delta.yaw_rad),
        }
    }

    /// `other` in this pose's frame, as a pose.
    pub fn between(&self, other: &Planar) -> Planar {
        let (x_m, y_m, yaw_rad) = self.relative(other);
        Planar { x_m, y_m, yaw_rad }
    }
}

/// An angle wrapped to `(-π, π]`.
pub fn wrap_angle(a: f64) -> f64 {
    let t = (a + PI).rem_euclid(TAU) - PI;
    if t <= -PI { t + TAU } else { t }
}

/// A pose that is not finite, refused by [`Track::insert`].
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("pose at {stamp_ns} ns is not finite: {pose:?}")]
pub struct NonFinitePose {
    /// Its stamp, ns.
    pub stamp_ns: i64,
    /// The pose.
    pub pose: Planar,
}

/// Stamped planar poses (a state estimate or the ground truth), interpolated between samples.
/// A later pose at the same stamp replaces the earlier one (a re-smoothed state).
#[derive(Debug, Clone, Default)]
pub struct Track {
    poses: BTreeMap<i64, Planar>,
}

impl Track {
    /// An empty track.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds or replaces the pose at `stamp_ns`.
    ///
    /// # Errors
    /// A pose that is not finite (nothing is stored).
    pub fn insert(&mut self, stamp_ns: i64, pose: Planar) -> Result<(), NonFinitePose> {
        if !pose.is_finite() {
            return Err(NonFinitePose { stamp_ns, pose });
        }
        self.poses.insert(stamp_ns, pose);
        Ok(())
    }

    /// Newest stamp, ns.
    pub fn last_stamp_ns(&self) -> Option<i64> {
        self.poses.keys().next_back().copied()
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// No poses yet.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The pose at `stamp_ns`, linear between the two poses around it (heading along the
    /// shorter arc); `None` outside the track or across a gap longer than `max_gap_ns`.
    pub fn at(&self, stamp_ns: i64, max_gap_ns: i64) -> Option<Planar> {
        let (&t1, p1) = self.poses.range(stamp_ns..).next()?;
        if t1 == stamp_ns {
            return Some(*p1);
        }
        let (&t0, p0) = self.poses.range(..stamp_ns).next_back()?;
        if t1 - t0 > max_gap_ns {
            return None;
        }
        let a = (stamp_ns - t0) as f64 / (t1 - t0) as f64;
        Some(Planar {
            x_m: p0.x_m + a * (p1.x_m - p0.x_m),
            y_m: p0.y_m + a * (p1.y_m - p0.y_m),
            yaw_rad: wrap_angle(p0.yaw_rad + a * wrap_angle(p1.yaw_rad - p0.yaw_rad)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EPS: f64 = 1e-12;

    fn p(x: f64, y: f64, yaw_deg: f64) -> Planar {
        Planar {
            x_m: x,
            y_m: y,
            yaw_rad: yaw_deg.to_radians(),
        }
    }

    #[test]
    fn relative_pose_is_in_the_reference_frame() {
        let r = p(1.0, 1.0, 90.0);
        let (along, cross, dyaw) = r.relative(&p(1.0, 3.0, 100.0));
        assert!((along - 2.0).abs() < 1e-12 && cross.abs() < 1e-12);
        assert!((dyaw - 10f64.to_radians()).abs() < 1e-12);
        let back = r.compose(&r.between(&p(4.0, -2.0, -170.0)));
        assert!((back.x_m - 4.0).abs() < 1e-12 && (back.y_m + 2.0).abs() < 1e-12);
        assert!((wrap_angle(back.yaw_rad - (-170f64).to_radians())).abs() < 1e-12);
    }

    #[test]
    fn wrap_stays_in_range_and_keeps_the_angle() {
        for a in [-10.0, -std::f64::consts::PI, 0.0, 3.2, 7.0, std::f64::consts::PI] {
            let w = wrap_angle(a);
            assert!(
                w > -std::f64::consts::PI && w <= std::f64::consts::PI + 1e-12,
                "{a} -> {w}"
            );
            assert!(
                (w.sin() - a.sin()).abs() < 1e-12 && (w.cos() - a.cos()).abs() < 1e-12,
                "{a} -> {w}"
            );
        }
    }

    #[test]
    fn track_interpolates_and_refuses_gaps_and_outside() {
        let mut t = Track::new();
        t.insert(0, p(0.0, 0.0, 170.0)).expect("insert");
        t.insert(100, p(1.0, 2.0, -170.0)).expect("insert");
        let m = t.at(50, 1000).expect("inside");
        assert!((m.x_m - 0.5).abs() < 1e-12 && (m.y_m - 1.0).abs() < 1e-12);
        // the shorter arc across ±180 degrees
        assert!((m.yaw_rad.abs() - std::f64::consts::PI).abs() < 1e-9);
        assert!(t.at(101, 1000).is_none() && t.at(-1, 1000).is_none());
        assert!(t.at(50, 99).is_none());
        assert!(t.insert(200, p(f64::NAN, 0.0, 0.0)).is_err());
        assert_eq!(t.len(), 2);
    }

    #[test]
    fn a_quaternion_about_z_gives_its_yaw() {
        let yaw: f64 = 1.2;
        let q = [0.0, 0.0, (yaw / 2.0).sin(), (yaw / 2.0).cos()];
        assert!((Planar::from_quaternion(0.0, 0.0, q).yaw_rad - yaw).abs() < EPS);
    }
}
