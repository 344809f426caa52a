//! Accuracy of recorded runs against ground truth: trajectories read from recordings or
//! TUM files, absolute trajectory error (with and without SE(3) alignment, Sturm et al.
//! 2012), relative pose error, and Hough-line parameter error.
//!
//! Definitions follow the evo package so that `evo_ape` / `evo_rpe` on the same TUM files
//! give the same numbers (a peer test checks): ATE on translations of associated poses,
//! aligned by Umeyama's method without scale when asked; RPE between poses `delta` frames
//! apart, `E_i = (Q_i^-1 Q_{i+d})^-1 (P_i^-1 P_{i+d})`, translation part, over the pairs
//! (0, d), (d, 2d), ...
//!
//! [`diff`] compares two recorded runs for regression.
//!
//! [`lgpr`] measures LGPR tracking as seed 001 does (eq. 11, along- and cross-track).
//!
//! [`fit_wheel`] calibrates a wheel against the truth (the scale `ingest`'s `wheel_scale` takes).

pub mod diagnostics;
pub mod diff;
pub mod lgpr;
pub mod messages;
mod trajectory;
mod wheel;

pub use trajectory::{PoseTopicKind, Trajectory, TrajectoryError, pose_topics, read_tum, write_tum};
pub use wheel::{WheelFit, WheelTrack, fit_wheel, wheel_period_errors};

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

/// A `world_from_body` pose.
pub type Pose = Isometry3<f64>;

/// Summary statistics of a set of errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Standard deviation (population).
    pub std: f64,
    /// Minimum.
    pub min: f64,
    /// Maximum.
    pub max: f64,
    /// Number of values.
    pub count: usize,
}

impl Stats {
    /// Statistics of `values` (`None` when empty).
    pub fn of(values: &[f64]) -> Option<Self> {
        if values.is_empty() {
            return None;
        }
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let rmse = (values.iter().map(|v| v * v).sum::<f64>() / n).sqrt();
        let std = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len().is_multiple_of(2) {
            0.5 * (sorted[mid - 1] + sorted[mid])
        } else {
            sorted[mid]
        };
        Some(Self {
            rmse,
            mean,
            median,
            std,
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            count: values.len(),
        })
    }
}

/// Estimated and true poses at the same instants.
#[derive(Debug, Clone, Default)]
pub struct Associated {
    /// Stamps, ns.
    pub stamps_ns: Vec<i64>,
    /// Estimated poses (`world_from_body`).
    pub estimate: Vec<Isometry3<f64>>,
    /// True poses at the same stamps.
    pub truth: Vec<Isometry3<f64>>,
}

/// Pairs every estimated pose with the truth at its stamp, interpolated (linear position,
/// slerp rotation) between truth samples at most `max_gap_ns` apart; estimates outside the
/// truth's span or in a gap are left out.
pub fn associate(estimate: &Trajectory, truth: &Trajectory, max_gap_ns: i64) -> Associated {
    let mut out = Associated::default();
    for (stamp, pose) in estimate.stamps_ns.iter().zip(&estimate.poses) {
        if let Some(t) = truth.interpolate(*stamp, max_gap_ns) {
            out.stamps_ns.push(*stamp);
            out.estimate.push(*pose);
            out.truth.push(t);
        }
    }
    out
}

/// The rigid transform `truth_from_estimate` minimising the squared distances of
/// positions (Umeyama 1991, no scale).
pub fn umeyama_alignment(estimate: &[Vector3<f64>], truth: &[Vector3<f64>]) -> Isometry3<f64> {
    let n = estimate.len().min(truth.len());
    if n == 0 {
        return Isometry3::identity();
    }
    let mean = |v: &[Vector3<f64>]| v.iter().take(n).sum::<Vector3<f64>>() / n as f64;
    let (mu_e, mu_t) = (mean(estimate), mean(truth));
    let mut sigma = Matrix3::zeros();
    for (e, t) in estimate.iter().zip(truth).take(n) {
        sigma += (t - mu_t) * (e - mu_e).transpose();
    }
    sigma /= n as f64;
    let svd = sigma.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Isometry3::identity();
    };
    let mut s = Matrix3::identity();
    if (u.determinant() * v_t.determinant()) < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * v_t;
    let rotation = UnitQuaternion::from_matrix(&r);
    let t = mu_t - rotation * mu_e;
    Isometry3::from_parts(Translation3::from(t), rotation)
}

/// Absolute trajectory error: translation distances of associated poses, optionally after
/// aligning the estimate to the truth.
pub fn ate(a: &Associated, align: bool) -> Option<Stats> {
    let est: Vec<Vector3<f64>> = a.estimate.iter().map(|p| p.translation.vector).collect();
    let tru: Vec<Vector3<f64>> = a.truth.iter().map(|p| p.translation.vector).collect();
    let t = if align {
        umeyama_alignment(&est, &tru)
    } else {
        Isometry3::identity()
    };
    let errors: Vec<f64> = est
        .iter()
        .zip(&tru)
        .map(|(e, g)| (t * nalgebra::Point3::from(*e)).coords - g)
        .map(|d| d.norm())
        .collect();
    Stats::of(&errors)
}

/// Relative pose error, translation part, between poses `delta` frames apart: pairs
/// (0, d), (d, 2d), ... as evo forms them by default.
pub fn rpe(a: &Associated, delta: usize) -> Option<Stats> {
    let delta = delta.max(1);
    let errors: Vec<f64> = (0..a.estimate.len().saturating_sub(delta))
        .step_by(delta)
        .map(|i| {
            let q = a.truth[i].inverse() * a.truth[i + delta];
            let p = a.estimate[i].inverse() * a.estimate[i + delta];
            (q.inverse() * p).translation.vector.norm()
        })
        .collect();
    Stats::of(&errors)
}

/// Position error split in the truth's heading frame (seed 001 eq. 11): along track
/// (the truth's forward axis) and cross track (its left axis), signed, m.
pub fn track_errors(a: &Associated) -> (Vec<f64>, Vec<f64>) {
    let mut along = Vec::with_capacity(a.truth.len());
    let mut cross = Vec::with_capacity(a.truth.len());
    for (e, t) in a.estimate.iter().zip(&a.truth) {
        let d = e.translation.vector - t.translation.vector;
        let forward = t.rotation * Vector3::x();
        let heading = forward.y.atan2(forward.x);
        let (s, c) = heading.sin_cos();
        along.push(c * d.x + s * d.y);
        cross.push(-s * d.x + c * d.y);
    }
    (along, cross)
}

/// Error of estimated Hough lines against true ones (matched by id).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LineError {
    /// RMSE of rho, m.
    pub rho_rmse_m: f64,
    /// RMSE of theta (wrapped), rad.
    pub theta_rmse_rad: f64,
    /// Lines matched.
    pub matched: usize,
}

/// RMSE of (rho, theta) over the estimated lines, each paired with a true line one to one,
/// nearest first (squared rho and theta differences summed; the ids of a mapping run need
/// not be the truth's); the same line may be written with (rho, theta) or
/// (-rho, theta + pi). Lines left without a partner are not counted.
pub fn line_error(estimate: &[gprflow_msg::HoughLine], truth: &[gprflow_msg::HoughLine]) -> Option<LineError> {
    let wrap = |a: f64| (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    let difference = |e: &gprflow_msg::HoughLine, t: &gprflow_msg::HoughLine| {
        let direct = ((e.rho_m - t.rho_m).powi(2), wrap(e.theta_rad - t.theta_rad).powi(2));
        let flipped = (
            (-e.rho_m - t.rho_m).powi(2),
            wrap(e.theta_rad + std::f64::consts::PI - t.theta_rad).powi(2),
        );
        if direct.0 + direct.1 <= flipped.0 + flipped.1 {
            direct
        } else {
            flipped
        }
    };
    let mut pairs: Vec<(f64, f64, usize, usize)> = estimate
        .iter()
        .enumerate()
        .flat_map(|(i, e)| truth.iter().enumerate().map(move |(j, t)| (i, j, e, t)))
        .map(|(i, j, e, t)| {
            let (dr, dt) = difference(e, t);
            (dr, dt, i, j)
        })
        .filter(|(dr, dt, _, _)| (dr + dt).is_finite())
        .collect();
    pairs.sort_by(|a, b| (a.0 + a.1).total_cmp(&(b.0 + b.1)));
    let (mut used_e, mut used_t) = (vec![false; estimate.len()], vec![false; truth.len()]);
    let (mut sr, mut st, mut n) = (0.0, 0.0, 0usize);
    for (dr, dt, i, j) in pairs {
        if used_e[i] || used_t[j] {
            continue;
        }
        used_e[i] = true;
        used_t[j] = true;
        sr += dr;
        st += dt;
        n += 1;
    }
    (n > 0).then(|| LineError {
        rho_rmse_m: (sr / n as f64).sqrt(),
        theta_rmse_rad: (st / n as f64).sqrt(),
        matched: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn traj(points: &[(i64, [f64; 3], f64)]) -> Trajectory {
        Trajectory {
            stamps_ns: points.iter().map(|p| p.0).collect(),
            poses: points
                .iter()
                .map(|p| {
                    Isometry3::from_parts(
                        Translation3::new(p.1[0], p.1[1], p.1[2]),
                        UnitQuaternion::from_euler_angles(0.0, 0.0, p.2),
                    )
                })
                .collect(),
        }
    }

    #[test]
    fn alignment_recovers_a_rigid_motion_and_ate_drops_to_zero() {
        let truth = traj(
            &(0..50)
                .map(|i| {
                    (
                        i * 100,
                        [f64::from(i as i32).sin() * 3.0, 0.1 * i as f64, 0.02 * i as f64],
                        0.1 * i as f64,
                    )
                })
                .collect::<Vec<_>>(),
        );
        let moved = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_euler_angles(0.1, -0.05, 0.7),
        );
        let estimate = Trajectory {
            stamps_ns: truth.stamps_ns.clone(),
            poses: truth.poses.iter().map(|p| moved * p).collect(),
        };
        let a = associate(&estimate, &truth, 1_000);
        assert_eq!(a.estimate.len(), 50);
        assert!(ate(&a, false).expect("ate").rmse > 1.0);
        assert!(ate(&a, true).expect("ate").rmse < 1e-9);
        // a rigid motion of the whole trajectory leaves relative poses alone
        assert!(rpe(&a, 1).expect("rpe").max < 1e-9);
    }

    #[test]
    fn interpolation_and_gaps() {
        let truth = traj(&[
            (0, [0.0, 0.0, 0.0], 0.0),
            (100, [1.0, 0.0, 0.0], 0.0),
            (1000, [2.0, 0.0, 0.0], 0.0),
        ]);
        let est = traj(&[
            (50, [0.5, 0.0, 0.0], 0.0),
            (500, [1.5, 0.0, 0.0], 0.0),
            (2000, [0.0; 3], 0.0),
        ]);
        let a = associate(&est, &truth, 200);
        assert_eq!(a.stamps_ns, vec![50]);
        assert!((a.truth[0].translation.vector.x - 0.5).abs() < 1e-12);
    }

    #[test]
    fn track_errors_split_in_the_truth_heading_frame() {
        // heading north; the estimate 1 m east of the truth and 2 m ahead
        let truth = traj(&[(0, [0.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2)]);
        let est = traj(&[(0, [1.0, 2.0, 0.0], 0.0)]);
        let (along, cross) = track_errors(&associate(&est, &truth, 0));
        assert!((along[0] - 2.0).abs() < 1e-12, "{along:?}");
        assert!(
            (cross[0] + 1.0).abs() < 1e-12,
            "east of a northbound truth is to its right: {cross:?}"
        );
    }

    #[test]
    fn stats_are_the_usual_ones() {
        let s = Stats::of(&[3.0, 4.0, 0.0, 1.0]).expect("stats");
        assert!((s.rmse - (26.0f64 / 4.0).sqrt()).abs() < 1e-12);
        assert_eq!((s.median, s.min, s.max, s.count), (2.0, 0.0, 4.0, 4));
        assert!(Stats::of(&[]).is_none());
    }

    #[test]
    fn lines_pair_with_the_nearest_true_line_whatever_their_ids() {
        let line = |id, rho_m, theta_rad| gprflow_msg::HoughLine {
            id,
            rho_m,
            theta_rad,
            covariance: [0.0; 4],
        };
        let truth = [line(0, 6.0, 0.2), line(1, 2.0, -1.0)];
        // ids swapped, the second written the other way round, both a little off
        let estimate = [line(0, 2.1, -1.0), line(1, -6.0, 0.2 + std::f64::consts::PI + 0.01)];
        let e = line_error(&estimate, &truth).expect("matched");
        assert_eq!(e.matched, 2);
        assert!((e.rho_rmse_m - (0.01f64 / 2.0).sqrt()).abs() < 1e-12, "{e:?}");
        assert!((e.theta_rmse_rad - (0.0001f64 / 2.0).sqrt()).abs() < 1e-9, "{e:?}");
        // one estimated line: paired with its nearest only
        let e = line_error(&estimate[..1], &truth).expect("matched");
        assert_eq!(e.matched, 1);
        assert!((e.rho_rmse_m - 0.1).abs() < 1e-12, "{e:?}");
        assert!(line_error(&[], &truth).is_none());
    }
}
