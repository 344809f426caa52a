//! Which line a detected apex belongs to.
//!
//! Each apex is a point on the ground (where the antenna passed over the line) with its apex
//! time (the line's depth). A line is the set of apexes given its id. A new apex joins:
//! - a line whose apexes span at least `min_link_m`: when it lies within `max_cross_m` of the
//!   ground line fitted through its newest `fit_points` apexes (total least squares; the
//!   odometry frame drifts over a long drive), the nearest such line;
//! - else a line with apexes at one place: when it lies between `min_link_m` and
//!   `max_link_m` from them, the nearest such line;
//!
//! and in both cases only at an apex time within `max_apex_time_diff_ns` of the line's mean.
//! Otherwise it starts a new line. A fitted line is preferred over a single place.

use gprflow_params::positive;

use crate::{ParamError, Result};

/// Parameters of [`Associator`].
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct AssociationParams {
    /// Largest distance of an apex from a fitted line it joins, m (default 0.6).
    pub max_cross_m: f64,
    /// Largest difference of apex time from the line's mean, ns (default 2).
    pub max_apex_time_diff_ns: f64,
    /// Apexes closer than this are one place: a line needs apexes this far apart to have a
    /// direction, m (default 1).
    pub min_link_m: f64,
    /// Farthest a second apex may lie from a line seen at one place only, m (default 12).
    pub max_link_m: f64,
    /// The line is fitted through this many of its newest apexes (default 3): the submaps'
    /// odometry drifts over a long drive.
    pub fit_points: usize,
    /// Largest difference between the measured forward distance and the one an estimated
    /// line predicts (the `lines` stage's line-map feedback), m (default 1.5).
    pub max_forward_m: f64,
}

impl Default for AssociationParams {
    fn default() -> Self {
        Self {
            max_cross_m: 0.6,
            max_apex_time_diff_ns: 2.0,
            min_link_m: 1.0,
            max_link_m: 12.0,
            fit_points: 3,
            max_forward_m: 1.5,
        }
    }
}

impl AssociationParams {
    /// Checks every value; the error names the key.
    ///
    /// # Errors
    /// A value out of range.
    pub fn check(&self) -> gprflow_params::Result {
        positive("association.max_cross_m", self.max_cross_m)?;
        positive("association.max_apex_time_diff_ns", self.max_apex_time_diff_ns)?;
        positive("association.min_link_m", self.min_link_m)?;
        positive("association.max_link_m", self.max_link_m)?;
        positive("association.max_forward_m", self.max_forward_m)?;
        if self.fit_points < 2 {
            return Err(ParamError::new(
                "association.fit_points",
                format!("must be at least 2, got {}", self.fit_points),
            ));
        }
        if self.max_link_m < self.min_link_m {
            return Err(ParamError::new(
                "association.max_link_m",
                format!(
                    "must be at least min_link_m ({}), got {}",
                    self.min_link_m, self.max_link_m
                ),
            ));
        }
        Ok(())
    }
}

/// An apex on the ground: position in the association frame (m) and apex time (ns).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundPoint {
    /// x, m.
    pub x_m: f64,
    /// y, m.
    pub y_m: f64,
    /// Two-way time of the apex, ns.
    pub apex_time_ns: f64,
}

/// One line's apexes.
#[derive(Debug, Clone)]
struct LineTrack {
    id: u32,
    points: Vec<GroundPoint>,
}

/// A ground line: a point on it and its unit direction.
#[derive(Debug, Clone, Copy)]
struct Fit {
    centre: [f64; 2],
    direction: [f64; 2],
    span_m: f64,
}

impl LineTrack {
    fn mean_apex_time_ns(&self) -> f64 {
        self.points.iter().map(|p| p.apex_time_ns).sum::<f64>() / self.points.len() as f64
    }

    /// The total-least-squares line through the newest `newest` apexes and their extent
    /// along it (the association frame drifts: old apexes would bend the line).
    fn fit(&self, newest: usize) -> Fit {
        let points = &self.points[self.points.len().saturating_sub(newest.max(2))..];
        let n = points.len() as f64;
        let cx = points.iter().map(|p| p.x_m).sum::<f64>() / n;
        let cy = points.iter().map(|p| p.y_m).sum::<f64>() / n;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for p in points {
            let (dx, dy) = (p.x_m - cx, p.y_m - cy);
            sxx += dx * dx;
            sxy += dx * dy;
            syy += dy * dy;
        }
        // principal axis of the scatter matrix
        let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let direction = [angle.cos(), angle.sin()];
        let along = |p: &GroundPoint| (p.x_m - cx) * direction[0] + (p.y_m - cy) * direction[1];
        let (lo, hi) = points
            .iter()
            .map(along)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), a| (lo.min(a), hi.max(a)));
        Fit {
            centre: [cx, cy],
            direction,
            span_m: hi - lo,
        }
    }
}

impl Fit {
    fn distance_m(&self, p: &GroundPoint) -> f64 {
        let (dx, dy) = (p.x_m - self.centre[0], p.y_m - self.centre[1]);
        (dx * self.direction[1] - dy * self.direction[0]).abs()
    }
}

/// Assigns line ids to apexes (see the module docs).
#[derive(Debug, Clone)]
pub struct Associator {
    params: AssociationParams,
    lines: Vec<LineTrack>,
}

impl Associator {
    /// # Errors
    /// A bad parameter.
    pub fn new(params: AssociationParams) -> Result<Self> {
        params.check()?;
        Ok(Self {
            params,
            lines: Vec::new(),
        })
    }

    /// Number of lines started so far.
    pub fn line_count(&self) -> usize {
        self.lines.len()
    }

    /// Whether line `id` exists and its apexes' mean time is within the gate of `apex_time_ns`.
    pub fn same_depth(&self, id: u32, apex_time_ns: f64) -> bool {
        self.lines
            .iter()
            .find(|l| l.id == id)
            .is_some_and(|l| (l.mean_apex_time_ns() - apex_time_ns).abs() <= self.params.max_apex_time_diff_ns)
    }

    /// Adds `p` to line `id` (associated by other means: the estimated line map).
    pub fn add(&mut self, id: u32, p: GroundPoint) {
        match self.lines.iter_mut().find(|l| l.id == id) {
            Some(line) => line.points.push(p),
            None => self.lines.push(LineTrack { id, points: vec![p] }),
        }
    }

    /// The id of the line `p` belongs to (a new one when none takes it); `p` is added to it.
    pub fn associate(&mut self, p: GroundPoint) -> u32 {
        let params = &self.params;
        // (fitted line first, then distance)
        let mut best: Option<(bool, f64, usize)> = None;
        for (index, line) in self.lines.iter().enumerate() {
            if (line.mean_apex_time_ns() - p.apex_time_ns).abs() > params.max_apex_time_diff_ns {
                continue;
            }
            let fit = line.fit(params.fit_points);
            let candidate = if fit.span_m >= params.min_link_m {
                let d = fit.distance_m(&p);
                (d <= params.max_cross_m).then_some((false, d))
            } else {
                let d = (p.x_m - fit.centre[0]).hypot(p.y_m - fit.centre[1]);
                (params.min_link_m..=params.max_link_m)
                    .contains(&d)
                    .then_some((true, d))
            };
            if let Some((single, d)) = candidate
                && best.is_none_or(|(bs, bd, _)| (single, d) < (bs, bd))
            {
                best = Some((single, d, index));
            }
        }
        match best {
            Some((_, _, index)) => {
                self.lines[index].points.push(p);
                self.lines[index].id
            }
            None => {
                let id = self.lines.iter().map(|l| l.id + 1).max().unwrap_or(0);
                self.lines.push(LineTrack { id, points: vec![p] });
                id
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x_m: f64, y_m: f64, apex_time_ns: f64) -> GroundPoint {
        GroundPoint { x_m, y_m, apex_time_ns }
    }

    /// The crossings of a lawnmower drive (rows along y, 4 m apart) with the line y = 4 + x / 7.
    fn crossings(line_y0: f64, slope: f64, t_ns: f64) -> Vec<GroundPoint> {
        (0..8)
            .map(|k| {
                let x = 4.0 * f64::from(k);
                at(x, line_y0 + slope * x, t_ns)
            })
            .collect()
    }

    #[test]
    fn crossings_of_one_line_are_one_line() {
        let mut a = Associator::new(AssociationParams::default()).expect("params");
        let ids: Vec<u32> = crossings(4.0, 1.0 / 7.0, 10.0)
            .into_iter()
            .map(|p| a.associate(p))
            .collect();
        assert!(ids.iter().all(|&i| i == ids[0]), "{ids:?}");
        assert_eq!(a.line_count(), 1);
    }

    #[test]
    fn two_lines_at_different_depths_stay_apart() {
        let mut a = Associator::new(AssociationParams::default()).expect("params");
        let (l1, l2) = (crossings(4.0, 1.0 / 7.0, 10.0), crossings(-5.0, 1.0, 15.0));
        let mut ids = (Vec::new(), Vec::new());
        for (p, q) in l1.into_iter().zip(l2) {
            ids.0.push(a.associate(p));
            ids.1.push(a.associate(q));
        }
        assert!(ids.0.iter().all(|&i| i == ids.0[0]), "{ids:?}");
        assert!(ids.1.iter().all(|&i| i == ids.1[0]), "{ids:?}");
        assert_ne!(ids.0[0], ids.1[0]);
    }

    #[test]
    fn an_apex_off_the_fitted_line_starts_a_new_one() {
        let mut a = Associator::new(AssociationParams::default()).expect("params");
        for p in crossings(4.0, 0.0, 10.0).into_iter().take(3) {
            a.associate(p);
        }
        // on the next row, 2 m off the line, at the same depth
        assert_eq!(a.associate(at(12.0, 6.0, 10.0)), 1);
        // on the line again
        assert_eq!(a.associate(at(16.0, 4.1, 10.0)), 0);
    }

    #[test]
    fn the_same_place_twice_does_not_give_a_direction() {
        let mut a = Associator::new(AssociationParams::default()).expect("params");
        assert_eq!(a.associate(at(0.0, 4.0, 10.0)), 0);
        // 0.5 m away: closer than min_link_m, not a second crossing
        assert_eq!(a.associate(at(0.3, 4.4, 10.0)), 1);
        // far beyond max_link_m
        assert_eq!(a.associate(at(30.0, 4.0, 10.0)), 2);
    }

    #[test]
    fn bad_params_name_the_key() {
        let e = Associator::new(AssociationParams {
            max_link_m: 0.5,
            ..AssociationParams::default()
        })
        .expect_err("order");
        assert!(e.to_string().starts_with("association.max_link_m"), "{e}");
        let e = Associator::new(AssociationParams {
            max_cross_m: f64::NAN,
            ..AssociationParams::default()
        })
        .expect_err("nan");
        assert!(e.to_string().starts_with("association.max_cross_m"), "{e}");
    }
}
