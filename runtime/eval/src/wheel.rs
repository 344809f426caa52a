//! Wheel calibration: the true ground distance per recorded wheel metre, measured against
//! ground truth.
//!
//! Each interval between two wheel readings is compared with the truth's displacement over
//! the same interval, projected on the body's forward axis (the mean of the two interpolated
//! orientations). The projection is signed, so the truth's position noise does not add up
//! the way a path length's does (it telescopes over a run of intervals), and reversals count
//! with the wheel's sign. The scale is the sum of the projections over the sum of the wheel's
//! distances: what a driver should multiply its wheel distances by (`ingest`'s
//! `wheel_scale`). It absorbs the encoder's radius error and the mean slip of the
//! recordings' driving.

use nalgebra::Vector3;
use serde::Serialize;

use super::trajectory::{Trajectory, TrajectoryError, scan_topic};
use gprflow_msg::{self as msg, Message, WheelOdometry};
use gprflow_record::Recording;

/// A recording's wheel distances, stamps increasing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WheelTrack {
    /// Stamps, ns.
    pub stamps_ns: Vec<i64>,
    /// Cumulative signed distance, m.
    pub distances_m: Vec<f64>,
}

impl WheelTrack {
    /// The wheel odometry on `topic` (default: the recording's topic of type
    /// `WheelOdometry`).
    ///
    /// # Errors
    /// No such topic (naming the topics there are), an undecodable message or a non-finite
    /// distance (topic, seq and field).
    pub fn from_recording(rec: &Recording, topic: Option<&str>) -> Result<Self, TrajectoryError> {
        let topics = rec.topics();
        let wanted = topic.map(|t| format!("/{}", t.trim_start_matches('/')));
        let found = topics
            .iter()
            .find(|(name, ty)| ty == WheelOdometry::TYPE_NAME && wanted.as_ref().is_none_or(|w| w == name))
            .map(|(name, _)| name.clone());
        let Some(found) = found else {
            return Err(TrajectoryError::NoWheelTopic {
                file: rec.path().to_owned(),
                topic: wanted,
                available: topics.into_iter().map(|(t, ty)| format!("{t} ({ty})")).collect(),
            });
        };
        let mut readings = Vec::new();
        scan_topic(rec, &found, |data| {
            let w = msg::decode::<WheelOdometry>(data).map_err(|e| e.to_string())?;
            if !w.distance_m.is_finite() {
                return Err(format!("distance_m is {}", w.distance_m));
            }
            readings.push((w.header.stamp.to_ns(), w.distance_m));
            Ok(())
        })?;
        readings.sort_by_key(|r| r.0);
        Ok(Self {
            stamps_ns: readings.iter().map(|r| r.0).collect(),
            distances_m: readings.iter().map(|r| r.1).collect(),
        })
    }
}

/// Wheel against truth over a recording (or several, summed with [`WheelFit::with`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct WheelFit {
    /// Signed ground distance along the body's forward axis over the compared intervals, m
    /// (with the wheel's sign: positive whichever way the wheel turned).
    pub ground_m: f64,
    /// The wheel's distance over the same intervals, m (sum of absolute steps).
    pub wheel_m: f64,
    /// Intervals compared (the wheel moved and the truth covers both ends).
    pub intervals: usize,
    /// Intervals where the wheel moved but the truth has a gap (or turns half round).
    pub skipped: usize,
}

impl WheelFit {
    /// The calibration: true ground metres per wheel metre (`None` before the wheel moved).
    pub fn scale(&self) -> Option<f64> {
        (self.wheel_m > 0.0).then(|| self.ground_m / self.wheel_m)
    }

    /// Both fits together (several recordings of one rig).
    #[must_use]
    pub fn with(self, other: Self) -> Self {
        Self {
            ground_m: self.ground_m + other.ground_m,
            wheel_m: self.wheel_m + other.wheel_m,
            intervals: self.intervals + other.intervals,
            skipped: self.skipped + other.skipped,
        }
    }
}

/// The truth's displacement from `t0_ns` to `t1_ns` along the body's mean forward axis over
/// that interval, m: `None` when the truth has a longer gap than `max_gap_ns` at either end,
/// or the body turned half round (no mean axis).
fn forward_displacement(truth: &Trajectory, t0_ns: i64, t1_ns: i64, max_gap_ns: i64) -> Option<f64> {
    let (a, b) = (
        truth.interpolate(t0_ns, max_gap_ns)?,
        truth.interpolate(t1_ns, max_gap_ns)?,
    );
    let forward = (a.rotation * Vector3::x() + b.rotation * Vector3::x()).try_normalize(1e-9)?;
    Some((b.translation.vector - a.translation.vector).dot(&forward))
}

/// Compares each wheel step with the truth's forward displacement over it; the truth is
/// interpolated across gaps of at most `max_gap_ns`.
pub fn fit_wheel(wheel: &WheelTrack, truth: &Trajectory, max_gap_ns: i64) -> WheelFit {
    let mut fit = WheelFit::default();
    let steps = wheel.stamps_ns.windows(2).zip(wheel.distances_m.windows(2));
    for (t, d) in steps {
        let step = d[1] - d[0];
        if step == 0.0 {
            continue;
        }
        let Some(along) = forward_displacement(truth, t[0], t[1], max_gap_ns) else {
            fit.skipped += 1;
            continue;
        };
        fit.ground_m += step.signum() * along;
        fit.wheel_m += step.abs();
        fit.intervals += 1;
    }
    fit
}

/// The wheel's along-track error over consecutive periods of `period_ns`, scaled by `scale`:
/// for each period in which the wheel moved and the truth covers every step, `scale` times the
/// wheel's distance minus the truth's forward displacement, both summed over the period's steps
/// (as [`fit_wheel`] compares them). Their RMS is the noise of the wheel's distance per period,
/// the truth's own position noise included (it does not telescope away at a period's two ends):
/// an upper bound on what an estimator's wheel sigma per state should be.
pub fn wheel_period_errors(
    wheel: &WheelTrack,
    truth: &Trajectory,
    scale: f64,
    period_ns: i64,
    max_gap_ns: i64,
) -> Vec<f64> {
    let mut errors = Vec::new();
    let Some(&first) = wheel.stamps_ns.first() else {
        return errors;
    };
    let period_ns = period_ns.max(1);
    // (period index, error so far, moved, covered)
    let mut current: Option<(i64, f64, bool, bool)> = None;
    let steps = wheel.stamps_ns.windows(2).zip(wheel.distances_m.windows(2));
    for (t, d) in steps {
        let index = (t[0] - first) / period_ns;
        if let Some((k, error, moved, covered)) = current
            && k != index
        {
            if moved && covered {
                errors.push(error);
            }
            current = None;
        }
        let (_, error, moved, covered) = current.get_or_insert((index, 0.0, false, true));
        let step = d[1] - d[0];
        if step == 0.0 {
            continue;
        }
        match forward_displacement(truth, t[0], t[1], max_gap_ns) {
            Some(along) => {
                *error += scale * step - along;
                *moved = true;
            }
            None => *covered = false,
        }
    }
    if let Some((_, error, true, true)) = current {
        errors.push(error);
    }
    errors
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    use super::*;

    /// A rig driving 4 m straight, a 1 m quarter circle, then backing 3 m (reversing at 10 s,
    /// on a truth sample: a truth interval across a sharp reversal cuts its corner), sampled
    /// every `dt_ns`: (stamps, poses, the distance driven so far, signed).
    fn drive(dt_ns: i64) -> (Vec<i64>, Vec<Isometry3<f64>>, Vec<f64>) {
        let speed = 0.5;
        let (l1, l2, l3) = (4.0, 1.0, 3.0);
        let r = l2 / std::f64::consts::FRAC_PI_2;
        let total_s = (l1 + l2 + l3) / speed;
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        let mut t = 0;
        while (t as f64) * 1e-9 <= total_s + 1e-9 {
            let s = t as f64 * 1e-9 * speed;
            let (x, y, yaw, driven) = if s < l1 {
                (s, 0.0, 0.0, s)
            } else if s < l1 + l2 {
                let a = (s - l1) / r;
                (l1 + r * a.sin(), r * (1.0 - a.cos()), a, s)
            } else {
                let back = s - l1 - l2;
                (l1 + r, r - back, std::f64::consts::FRAC_PI_2, l1 + l2 - back)
            };
            out.0.push(t);
            out.1.push(Isometry3::from_parts(
                Translation3::new(x, y, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            ));
            out.2.push(driven);
            t += dt_ns;
        }
        out
    }

    fn wheel_reading(recorded_per_true: f64, noise: impl Fn(usize) -> f64) -> WheelTrack {
        let (stamps_ns, _, driven) = drive(20_000_000);
        WheelTrack {
            stamps_ns,
            distances_m: driven
                .iter()
                .enumerate()
                .map(|(i, d)| d * recorded_per_true + noise(i))
                .collect(),
        }
    }

    #[test]
    fn a_wheel_reading_short_is_scaled_back_over_turns_and_reversals() {
        // truth at 20 Hz, the wheel at 50 Hz, reading 2 % short
        let (stamps_ns, poses, _) = drive(50_000_000);
        let truth = Trajectory { stamps_ns, poses };
        let wheel = wheel_reading(1.0 / 1.02, |_| 0.0);
        let fit = fit_wheel(&wheel, &truth, 100_000_000);
        let scale = fit.scale().expect("moved");
        assert!((scale - 1.02).abs() < 2e-4, "{scale} {fit:?}");
        // forward 5 m, back 3 m: every metre counts once
        assert!((fit.ground_m - 8.0).abs() < 1e-3, "{fit:?}");
        assert_eq!(fit.skipped, 0);
    }

    #[test]
    fn truth_noise_does_not_bias_the_scale() {
        // 3 mm of total-station noise on 1 cm steps would add ~4 % to a path length
        let (stamps_ns, mut poses, _) = drive(50_000_000);
        let mut state = 12345u64;
        let mut gauss = || {
            // sum of 12 uniforms: a unit normal, near enough
            (0..12)
                .map(|_| {
                    state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                    (state >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0
        };
        for p in &mut poses {
            p.translation.vector += Vector3::new(gauss(), gauss(), 0.0) * 0.003;
        }
        let truth = Trajectory { stamps_ns, poses };
        let wheel = wheel_reading(1.0, |_| 0.0);
        let scale = fit_wheel(&wheel, &truth, 100_000_000).scale().expect("moved");
        assert!((scale - 1.0).abs() < 2e-3, "{scale}");
    }

    #[test]
    fn the_period_errors_are_the_wheel_noise_summed_over_each_period() {
        // truth at 20 Hz, the wheel at 50 Hz with 1 mm of white noise on each reading: over a
        // 100 ms period the error is the difference of two readings' noise (sd 1.4 mm)
        let (stamps_ns, poses, _) = drive(50_000_000);
        let truth = Trajectory { stamps_ns, poses };
        let mut state = 99u64;
        let mut noise = Vec::new();
        for _ in 0..1000 {
            let g: f64 = (0..12)
                .map(|_| {
                    state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                    (state >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0;
            noise.push(0.001 * g);
        }
        let wheel = wheel_reading(1.0, |i| noise[i]);
        let errors = wheel_period_errors(&wheel, &truth, 1.0, 100_000_000, 100_000_000);
        // 16 s of driving in 100 ms periods, but for the one with the reversal's stop
        assert!(errors.len() > 150, "{}", errors.len());
        let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
        assert!((rms - 0.0014).abs() < 0.0004, "{rms}");
        // a wheel reading 2 % short, scaled back, has no error; unscaled, 2 % of each period's
        // 5 cm
        let short = wheel_reading(1.0 / 1.02, |_| 0.0);
        let scaled = wheel_period_errors(&short, &truth, 1.02, 100_000_000, 100_000_000);
        assert!(scaled.iter().all(|e| e.abs() < 2e-4), "{scaled:?}");
        let unscaled = wheel_period_errors(&short, &truth, 1.0, 100_000_000, 100_000_000);
        let largest = unscaled.iter().fold(0.0_f64, |m, e| m.max(e.abs()));
        assert!((largest - 0.05 * (1.0 - 1.0 / 1.02)).abs() < 2e-4, "{largest}");
    }

    #[test]
    fn truth_gaps_are_skipped_and_fits_add_up() {
        let (stamps_ns, poses, _) = drive(50_000_000);
        // drop the truth from 2 s to 4 s
        let (stamps_ns, poses): (Vec<i64>, Vec<_>) = stamps_ns
            .into_iter()
            .zip(poses)
            .filter(|(t, _)| !(2_000_000_000..4_000_000_000).contains(t))
            .unzip();
        let truth = Trajectory { stamps_ns, poses };
        let wheel = wheel_reading(1.0 / 1.02, |_| 0.0);
        let fit = fit_wheel(&wheel, &truth, 100_000_000);
        // the steps with an end in the gap (1.95 s to 4 s between truth samples)
        let inside = |t: i64| t > 1_950_000_000 && t < 4_000_000_000;
        let expected = wheel
            .stamps_ns
            .windows(2)
            .filter(|w| inside(w[0]) || inside(w[1]))
            .count();
        assert!(expected > 100, "{expected}");
        assert_eq!(fit.skipped, expected, "{fit:?}");
        assert!((fit.scale().expect("moved") - 1.02).abs() < 2e-4);
        let both = fit.with(fit);
        assert_eq!(both.intervals, 2 * fit.intervals);
        assert_eq!(both.scale(), fit.scale());
        assert_eq!(WheelFit::default().scale(), None);
    }

    #[test]
    fn a_step_that_turns_half_round_has_no_forward_axis_and_is_skipped() {
        let pose = |x: f64, yaw: f64| {
            Isometry3::from_parts(
                Translation3::new(x, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            )
        };
        let truth = Trajectory {
            stamps_ns: vec![0, 10, 20],
            poses: vec![pose(0.0, 0.0), pose(0.01, 0.0), pose(0.01, std::f64::consts::PI)],
        };
        let wheel = WheelTrack {
            stamps_ns: vec![0, 10, 20],
            distances_m: vec![0.0, 0.01, 0.02],
        };
        let fit = fit_wheel(&wheel, &truth, 100);
        assert_eq!((fit.intervals, fit.skipped), (1, 1), "{fit:?}");
        assert!(fit.ground_m.is_finite() && (fit.scale().expect("moved") - 1.0).abs() < 1e-12);
    }
}
