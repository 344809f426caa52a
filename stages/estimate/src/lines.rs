//! Initial values for Hough-line parameters (seed 000 Fig. 5.7, eq. 5.8-5.12).
//!
//! A line observation is a forward distance `z` from a pose; the observed point of the line is
//! `world_from_body * [z, 0, 0]` (eq. 5.8-5.9). Two such points at least a minimum baseline
//! apart give the line through them, whose normal form is the initial guess (eq. 5.10-5.12,
//! written with the normal of the point difference so that vertical lines need no slope).

use nalgebra::{Vector2, Vector3};

use crate::lie::Pose3;
use crate::values::HoughLine;

/// The observed line point in the world plane (eq. 5.8-5.9).
#[must_use]
pub fn observed_point(world_from_body: &Pose3, forward_distance_m: f64) -> Vector2<f64> {
    let p = world_from_body.trans_m + world_from_body.rot * Vector3::new(forward_distance_m, 0.0, 0.0);
    Vector2::new(p.x, p.y)
}

/// The Hough line through two points (eq. 5.10-5.12), `None` when they are closer than
/// `min_baseline_m`.
#[must_use]
pub fn line_through(a: &Vector2<f64>, b: &Vector2<f64>, min_baseline_m: f64) -> Option<HoughLine> {
    let d = b - a;
    let len = d.norm();
    if !(len >= min_baseline_m && len > 0.0) {
        return None;
    }
    let mut n = Vector2::new(-d.y, d.x) / len;
    let mut rho = n.dot(a);
    if rho < 0.0 {
        n = -n;
        rho = -rho;
    }
    Some(HoughLine {
        rho_m: rho,
        theta_rad: n.y.atan2(n.x),
    })
}

/// Picks the initial guess from observations `(pose, distance)` in time order: the first
/// observation paired with the first later one at least `min_baseline_m` away (the earliest
/// points carry the least odometry drift).
#[must_use]
pub fn initial_line(observations: &[(Pose3, f64)], min_baseline_m: f64) -> Option<HoughLine> {
    let (first, rest) = observations.split_first()?;
    let a = observed_point(&first.0, first.1);
    rest.iter()
        .find_map(|(p, z)| line_through(&a, &observed_point(p, *z), min_baseline_m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::forward_distance_to_line;
    use crate::lie::so3_exp;

    #[test]
    fn recovers_a_line_from_two_observations() {
        let truth = HoughLine {
            rho_m: 25.0,
            theta_rad: 0.3,
        };
        let pose =
            |x: f64, y: f64, yaw: f64| Pose3::new(so3_exp(&Vector3::new(0.0, 0.0, yaw)), Vector3::new(x, y, 0.0));
        let obs: Vec<(Pose3, f64)> = [pose(0.0, 0.0, 0.1), pose(1.0, 0.2, 0.2), pose(3.0, -4.0, 0.5)]
            .into_iter()
            .map(|p| {
                let z = forward_distance_to_line(&p, &truth).0;
                (p, z)
            })
            .collect();
        let l = initial_line(&obs, 2.0).expect("baseline reached");
        assert!(
            (l.rho_m - truth.rho_m).abs() < 1e-9 && (l.theta_rad - truth.theta_rad).abs() < 1e-9,
            "{l:?}"
        );
        assert!(initial_line(&obs[..2], 100.0).is_none());
    }
}
