//! Loop-candidate selection (seed 000 §4.3, §4.8.4): which earlier submaps a new submap is
//! registered with.
//!
//! Every submap is placed by its *anchor*, the ground position of its ground-order column 0
//! (see [`Anchor`]), in an association frame: the current estimate (the normal mode) or the
//! ground truth (the oracle association used only for evaluation). A reference is a candidate
//! for a query when, in the reference anchor's frame, the query anchor lies within
//! `max_along_m` along track and `max_cross_m` across it, the headings agree within
//! `max_heading_deg`, and the two were driven at least `min_separation_s` apart (sequential
//! submaps share their traces; registering them would only repeat the wheel odometry).

use std::collections::HashMap;

use gprflow_geometry::{Planar, Track};

use gprflow_params::positive;

/// Where a submap sits: its ground-order column 0. A submap driven forwards starts there (its
/// oldest trace); one driven backwards ends there (its newest trace).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    /// Stamp of the anchor trace, ns.
    pub stamp_ns: i64,
    /// Odometry pose of the anchor (the submap stage's dead reckoning).
    pub odom: Planar,
    /// Odometry pose of the submap's oldest trace.
    pub odom_start: Planar,
    /// Stamp of the oldest trace, ns.
    pub start_stamp_ns: i64,
    /// Driven backwards (columns reversed into ground order).
    pub backward: bool,
}

impl Anchor {
    /// The anchor's pose in a frame where the track is known: the track at the anchor's stamp
    /// when it reaches that far, else the track at the oldest trace composed with the
    /// submap's own odometry from there to the anchor.
    pub fn locate(&self, track: &Track, max_gap_ns: i64) -> Option<Planar> {
        track.at(self.stamp_ns, max_gap_ns).or_else(|| {
            let start = track.at(self.start_stamp_ns, max_gap_ns)?;
            Some(start.compose(&self.odom_start.between(&self.odom)))
        })
    }
}

/// Gates of [`candidates`].
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct CandidateGates {
    /// Largest along-track offset of the query anchor from the reference anchor, m (default
    /// 1.0; keep it below the registration's largest shift so the true shift is searched).
    pub max_along_m: f64,
    /// Largest cross-track offset, m (default 0.3: the radar sees a narrow strip).
    pub max_cross_m: f64,
    /// Largest heading difference, degrees (default 15).
    pub max_heading_deg: f64,
    /// Smallest time between the two submaps' anchors, s (default 15: longer than a submap
    /// takes to drive, so sequential submaps are never candidates).
    pub min_separation_s: f64,
    /// References tried per query, nearest first (default 1).
    pub per_query: usize,
}

impl Default for CandidateGates {
    fn default() -> Self {
        Self {
            max_along_m: 1.0,
            max_cross_m: 0.3,
            max_heading_deg: 15.0,
            min_separation_s: 15.0,
            per_query: 1,
        }
    }
}

impl CandidateGates {
    /// # Errors
    /// A gate that is not a positive finite number (`per_query` at least 1).
    pub fn check(&self) -> gprflow_params::Result {
        positive("candidates.max_along_m", self.max_along_m)?;
        positive("candidates.max_cross_m", self.max_cross_m)?;
        positive("candidates.max_heading_deg", self.max_heading_deg)?;
        positive("candidates.min_separation_s", self.min_separation_s)?;
        gprflow_params::at_least("candidates.per_query", self.per_query, 1)
    }
}

/// A placed reference: its index in the caller's list, anchor stamp and pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placed {
    /// Index in the caller's reference list.
    pub index: usize,
    /// Anchor stamp, ns.
    pub stamp_ns: i64,
    /// Anchor pose in the association frame.
    pub pose: Planar,
}

/// The references (at most `per_query`, nearest first) that pass the gates for a query
/// anchored at `query` (stamp, pose); each with the query's along-track offset from it.
pub fn candidates(gates: &CandidateGates, query_stamp_ns: i64, query: &Planar, refs: &[Placed]) -> Vec<(usize, f64)> {
    let min_sep_ns = (gates.min_separation_s * 1e9) as i64;
    let max_heading = gates.max_heading_deg.to_radians();
    let mut found: Vec<(f64, usize, f64)> = refs
        .iter()
        .filter(|r| (query_stamp_ns - r.stamp_ns).abs() >= min_sep_ns)
        .filter_map(|r| {
            let (along, cross, dyaw) = r.pose.relative(query);
            (along.abs() <= gates.max_along_m && cross.abs() <= gates.max_cross_m && dyaw.abs() <= max_heading)
                .then(|| (along.hypot(cross), r.index, along))
        })
        .collect();
    found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    found
        .into_iter()
        .take(gates.per_query)
        .map(|(_, i, along)| (i, along))
        .collect()
}

/// The placed references on a grid of cells as wide as the gates reach
/// (`hypot(max_along_m, max_cross_m)`), so that a query looks at the references in the nine
/// cells around it instead of at every reference. Every reference that passes the gates for a
/// query lies within that reach of it, so [`ReferenceIndex::near`] holds all of them (and some
/// that [`candidates`] then refuses).
#[derive(Debug, Clone)]
pub struct ReferenceIndex {
    cell_m: f64,
    cells: HashMap<(i64, i64), Vec<Placed>>,
}

impl ReferenceIndex {
    /// An empty index for `gates` (checked: positive distances).
    #[must_use]
    pub fn new(gates: &CandidateGates) -> Self {
        Self {
            cell_m: gates.max_along_m.hypot(gates.max_cross_m),
            cells: HashMap::new(),
        }
    }

    fn cell(&self, pose: &Planar) -> (i64, i64) {
        // Saturating casts: a pose far out of range lands in an edge cell, still found by a
        // query there (and refused by the gates).
        (
            (pose.x_m / self.cell_m).floor() as i64,
            (pose.y_m / self.cell_m).floor() as i64,
        )
    }

    /// Adds a placed reference.
    pub fn insert(&mut self, placed: Placed) {
        let cell = self.cell(&placed.pose);
        self.cells.entry(cell).or_default().push(placed);
    }

    /// Forgets every reference.
    pub fn clear(&mut self) {
        self.cells.clear();
    }

    /// References held.
    #[must_use]
    pub fn len(&self) -> usize {
        self.cells.values().map(Vec::len).sum()
    }

    /// No reference held.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// Appends to `out` the references in the nine cells around `query`.
    pub fn near(&self, query: &Planar, out: &mut Vec<Placed>) {
        let (cx, cy) = self.cell(query);
        for dx in -1..=1 {
            for dy in -1..=1 {
                if let Some(list) = self.cells.get(&(cx.saturating_add(dx), cy.saturating_add(dy))) {
                    out.extend_from_slice(list);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f64, y: f64, yaw_deg: f64) -> Planar {
        Planar {
            x_m: x,
            y_m: y,
            yaw_rad: yaw_deg.to_radians(),
        }
    }

    #[test]
    fn anchor_beyond_the_track_uses_the_submap_odometry() {
        let mut t = Track::new();
        t.insert(0, p(10.0, 0.0, 90.0)).expect("insert");
        t.insert(1_000, p(10.0, 1.0, 90.0)).expect("insert");
        // odometry frame rotated against the track's: 2 m forward from the start
        let a = Anchor {
            stamp_ns: 5_000,
            odom: p(2.0, 0.0, 0.0),
            odom_start: p(0.0, 0.0, 0.0),
            start_stamp_ns: 1_000,
            backward: false,
        };
        let at = a.locate(&t, 10_000).expect("located");
        assert!((at.x_m - 10.0).abs() < 1e-12 && (at.y_m - 3.0).abs() < 1e-12, "{at:?}");
    }

    #[test]
    fn the_index_finds_what_a_scan_of_every_reference_finds() {
        // References scattered over 20 x 20 m with every heading, queries likewise: the
        // candidates among the index's nine cells are those among all references.
        let g = CandidateGates {
            per_query: 5,
            max_along_m: 1.0,
            max_cross_m: 0.3,
            max_heading_deg: 40.0,
            ..CandidateGates::default()
        };
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut index = ReferenceIndex::new(&g);
        let mut all = Vec::new();
        for i in 0..3000 {
            let placed = Placed {
                index: i,
                stamp_ns: 0,
                pose: p(20.0 * next() - 10.0, 20.0 * next() - 10.0, 360.0 * next()),
            };
            index.insert(placed);
            all.push(placed);
        }
        assert_eq!(index.len(), 3000);
        let (mut found_some, mut near) = (0, Vec::new());
        for _ in 0..2000 {
            let q = p(20.0 * next() - 10.0, 20.0 * next() - 10.0, 360.0 * next());
            near.clear();
            index.near(&q, &mut near);
            assert!(near.len() < 200, "{} of 3000 looked at", near.len());
            let scanned = candidates(&g, 100_000_000_000, &q, &all);
            assert_eq!(candidates(&g, 100_000_000_000, &q, &near), scanned, "query {q:?}");
            found_some += usize::from(!scanned.is_empty());
        }
        assert!(found_some > 500, "{found_some}");
        index.clear();
        assert!(index.is_empty());
    }

    #[test]
    fn gates_pick_the_nearest_reference_on_the_same_line() {
        let refs = [
            Placed {
                index: 0,
                stamp_ns: 0,
                pose: p(0.0, 0.0, 0.0),
            },
            Placed {
                index: 1,
                stamp_ns: 0,
                pose: p(0.6, 0.05, 0.0),
            },
            // across the line
            Placed {
                index: 2,
                stamp_ns: 0,
                pose: p(0.9, 0.5, 0.0),
            },
            // facing the other way
            Placed {
                index: 3,
                stamp_ns: 0,
                pose: p(0.9, 0.0, 180.0),
            },
            // too recent
            Placed {
                index: 4,
                stamp_ns: 90_000_000_000,
                pose: p(0.9, 0.0, 0.0),
            },
            // too far along
            Placed {
                index: 5,
                stamp_ns: 0,
                pose: p(-0.5, 0.0, 0.0),
            },
        ];
        let g = CandidateGates {
            per_query: 3,
            ..CandidateGates::default()
        };
        let found = candidates(&g, 100_000_000_000, &p(0.8, 0.0, 2.0), &refs);
        let ids: Vec<usize> = found.iter().map(|f| f.0).collect();
        assert_eq!(ids, vec![1, 0]);
        assert!((found[0].1 - 0.2).abs() < 1e-9);
        assert!(g.check().is_ok());
        assert!(
            CandidateGates {
                max_cross_m: f64::NAN,
                ..g.clone()
            }
            .check()
            .is_err()
        );
        assert!(CandidateGates { per_query: 0, ..g }.check().is_err());
    }
}
