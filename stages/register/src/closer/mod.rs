//! The loop closer: submaps in, matches out (seed 000 §4.3-4.5), in plain values; the
//! `register` stage (module `node`) only turns messages into [`SubmapIn`]s and poses, and
//! [`Match`]es into messages.
//!
//! Every valid submap is put in ground order ([`ground_order`]) and kept as a reference
//! (one every `reference_spacing_m` of travel). A new submap, the query, is placed in the
//! association frame (the estimate or the ground truth for the oracle association) and
//! matched with the references that pass the loop-candidate gates ([`crate::candidates`]) by
//! the method's [`Matcher`] ([`matcher`]: one implementation per [`Method`]).
//!
//! A query waits until the association frame reaches it: the estimate (or truth) must cover
//! its oldest trace (its anchor with the oracle). A match carries the two anchor stamps and
//! the shift between them; with [`Stamps::Overlap`] a shift found on the grid (every method
//! but the oracle) goes out instead as the moments the two passes were over the middle of
//! their shared ground (the submaps' column stamps, [`overlap_stamps`]) with an along-track
//! offset of zero, free of the wheel's scale error that the grid, laid on wheel distance,
//! puts into a shift.

pub mod matcher;
mod store;

use std::collections::VecDeque;

use gprflow_geometry::{NonFinitePose, Planar, Track};

use crate::Result;
use crate::SubmapView;
use crate::candidates::{Anchor, CandidateGates, Placed, ReferenceIndex, candidates};
use crate::learned::Features;
use store::PixelSpill;

pub use matcher::{Context, Engineered, Learned, Matcher, Oracle, Outcome, Zeroth};

/// How a candidate pair is registered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Pearson correlation of the submaps over the along-track shift (eq. 4.2-4.3).
    Engineered,
    /// The learned model: ONNX encoder, spatial correlation and head (§4.5; tools/train/SPEC.md).
    Learned,
    /// The ground-truth transform (needs the `truth` input; evaluation only).
    Oracle,
    /// The zeroth-order model of Table 4.1: always the mean shift of the learned model's
    /// training pairs (the head's `zeroth_m`); a baseline for evaluation only.
    Zeroth,
}

impl Method {
    /// The name registrations carry.
    pub fn name(self) -> &'static str {
        match self {
            Self::Engineered => "engineered",
            Self::Learned => "learned",
            Self::Oracle => "oracle",
            Self::Zeroth => "zeroth",
        }
    }
}

/// Where submaps are placed to find loop candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Association {
    /// The current estimate (the `estimate` feedback input): the normal mode.
    Estimate,
    /// The ground truth (the `truth` input): the oracle association, for evaluation only.
    Truth,
}

/// Which two moments a registration found on the submap grid relates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Stamps {
    /// The two anchors, with the shift between them counted on the grid: in wheel metres, so
    /// the wheel's scale error enters the measurement.
    Anchors,
    /// The two passes' moments over the middle of their shared ground (the submaps'
    /// `column_stamps_ns`), with an offset of zero: no wheel scale in the measurement, but no
    /// metric offset for the estimator either (see the README's Localisation section).
    Overlap,
}

/// Settings of the [`LoopCloser`] (the method's own are its [`Matcher`]'s).
#[derive(Debug, Clone, PartialEq)]
pub struct CloserParams {
    /// Where loop candidates come from.
    pub association: Association,
    /// Loop-candidate gates.
    pub candidates: CandidateGates,
    /// Along-track sigma of each match, m (`None`: the matcher's [`Matcher::sigma_m`]).
    pub sigma_m: Option<f64>,
    /// Keep a reference every this much travel, m.
    pub reference_spacing_m: f64,
    /// Try a query every this much travel, m.
    pub query_spacing_m: f64,
    /// Longest gap between two poses of the association frame that is interpolated, s.
    pub max_track_gap_s: f64,
    /// Which moments a grid method's match relates.
    pub stamps: Stamps,
    /// References whose pixels stay in memory, the newest; older ones are moved to a
    /// temporary file and read back when a query needs them (see `store`).
    pub references_in_memory: usize,
}

/// `pixels` (`rows x cols`, row-major, columns in driving order) in ground order: columns
/// reversed when the submap was driven backwards, so column 0 is the smallest along-body-x.
pub fn ground_order(pixels: &[f32], rows: usize, cols: usize, backward: bool) -> Vec<f32> {
    if !backward {
        return pixels.to_vec();
    }
    let mut out = Vec::with_capacity(pixels.len());
    for row in pixels.chunks_exact(cols).take(rows) {
        out.extend(row.iter().rev());
    }
    out
}

/// A submap as it comes (columns in driving order), in plain values.
#[derive(Debug, Clone, Copy)]
pub struct SubmapIn<'a> {
    /// Submap id.
    pub id: u32,
    /// Rows (travel time).
    pub rows: usize,
    /// Columns (along track).
    pub cols: usize,
    /// Metres per column.
    pub resolution_m: f64,
    /// `rows x cols`, row-major.
    pub pixels: &'a [f32],
    /// When the rig was over each column, ns (empty when the submap has none).
    pub column_stamps_ns: &'a [i64],
    /// Wheel distance at the first column, m.
    pub start_distance_m: f64,
    /// Wheel distance at the last column, m.
    pub end_distance_m: f64,
    /// Odometry pose at the first column.
    pub start_pose: Planar,
    /// Odometry pose at the last column.
    pub end_pose: Planar,
    /// Stamp of the first column, ns.
    pub start_stamp_ns: i64,
    /// Stamp of the last column, ns.
    pub end_stamp_ns: i64,
}

/// A submap ready to be registered: ground-order pixels and where it sits.
#[derive(Debug)]
pub struct Keyed {
    /// Submap id.
    pub id: u32,
    /// Where it sits.
    pub anchor: Anchor,
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Metres per column.
    pub resolution_m: f64,
    /// Ground-order pixels; empty for a reference kept without them (moved to the spill file,
    /// or not needed by the method).
    pub pixels: Vec<f32>,
    /// When the rig was over each column, ns, in ground order (empty when the submap has none).
    pub column_stamps_ns: Vec<i64>,
    /// The learned model's features, encoded once when the submap is first needed: as a
    /// query with loop candidates, or kept as a reference (most submaps are neither).
    pub features: Option<Features>,
    /// Where its pixels are in the spill file, once moved there (bytes).
    spilled_at: Option<u64>,
}

impl Keyed {
    /// Its pixels and grid.
    pub fn view(&self) -> SubmapView<'_> {
        SubmapView {
            pixels: &self.pixels,
            rows: self.rows,
            cols: self.cols,
            resolution_m: self.resolution_m,
        }
    }

    /// Checks the submap and puts it in ground order; `Err` says what is wrong with it.
    ///
    /// # Errors
    /// A pixel count other than `rows x cols` (or none), a pixel that is not finite, column
    /// stamps of another count than the columns, a bad resolution or distance.
    pub fn new(m: &SubmapIn<'_>) -> std::result::Result<Self, String> {
        let (rows, cols) = (m.rows, m.cols);
        if rows == 0 || cols == 0 || m.pixels.len() != rows * cols {
            return Err(format!("pixels: {} values for {rows} x {cols}", m.pixels.len()));
        }
        if let Some(i) = m.pixels.iter().position(|v| !v.is_finite()) {
            return Err(format!("pixels[{i}] is {}", m.pixels[i]));
        }
        if !(m.column_stamps_ns.is_empty() || m.column_stamps_ns.len() == cols) {
            return Err(format!(
                "column_stamps_ns: {} values for {cols} columns",
                m.column_stamps_ns.len()
            ));
        }
        if !(m.resolution_m.is_finite() && m.resolution_m > 0.0) {
            return Err(format!("resolution_m: {}", m.resolution_m));
        }
        if !(m.start_distance_m.is_finite() && m.end_distance_m.is_finite()) {
            return Err(format!(
                "start/end_distance_m: {} / {}",
                m.start_distance_m, m.end_distance_m
            ));
        }
        let backward = m.end_distance_m < m.start_distance_m;
        let (start, end) = (m.start_pose, m.end_pose);
        Ok(Self {
            id: m.id,
            anchor: Anchor {
                stamp_ns: if backward { m.end_stamp_ns } else { m.start_stamp_ns },
                odom: if backward { end } else { start },
                odom_start: start,
                start_stamp_ns: m.start_stamp_ns,
                backward,
            },
            rows,
            cols,
            resolution_m: m.resolution_m,
            pixels: ground_order(m.pixels, rows, cols, backward),
            column_stamps_ns: if backward {
                m.column_stamps_ns.iter().rev().copied().collect()
            } else {
                m.column_stamps_ns.to_vec()
            },
            features: None,
            spilled_at: None,
        })
    }
}

/// A match of a query with a reference: the query at `stamps_ns.1` lies `along_m` along
/// track from the reference at `stamps_ns.0`.
#[derive(Debug, Clone, PartialEq)]
pub struct Match {
    /// The reference submap's id.
    pub reference: u32,
    /// The query submap's id.
    pub query: u32,
    /// The two moments related (reference, query), ns: the anchors, or the overlap stamps.
    pub stamps_ns: (i64, i64),
    /// Along-track offset, m (0 with overlap stamps).
    pub along_m: f64,
    /// Along-track variance, m².
    pub variance_m2: f64,
    /// The method's score (peak correlation, share score; 1 oracle, 0 zeroth).
    pub score: f64,
    /// The method.
    pub method: Method,
    /// The travel-time stretch of the query the learned method took (1 otherwise).
    pub stretch: f64,
}

/// What happened to the submaps and pairs.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Counts {
    /// Queries with loop candidates.
    pub queries: u64,
    /// Candidate pairs.
    pub pairs: u64,
    /// Pairs the method's gate refused.
    pub rejected: u64,
    /// Submaps the association frame never placed.
    pub never_placed: u64,
    /// Learned matches whose query was stretched.
    pub stretched: u64,
    /// Encoder runs, the stretch search's among them.
    pub encoded: u64,
}

/// One candidate pair the matcher judged, registered or refused (the diagnostics output).
#[derive(Debug, Clone, PartialEq)]
pub struct Attempt {
    /// Reference submap id.
    pub reference: u32,
    /// Query submap id.
    pub query: u32,
    /// The two anchors' stamps (reference, query), ns.
    pub anchors_ns: (i64, i64),
    /// `registered`, or why the method refused ([`Outcome::Refused`]).
    pub outcome: &'static str,
    /// The shift the method found, m (NaN when none).
    pub shift_m: f64,
    /// Its score (NaN when none).
    pub score: f64,
    /// The query's stretch that was judged.
    pub stretch: f64,
}

/// The loop closer: keeps references, finds loop candidates for each query and matches them.
#[derive(Debug)]
pub struct LoopCloser {
    params: CloserParams,
    matcher: Box<dyn Matcher>,
    estimate: Track,
    truth: Track,
    pending: VecDeque<Keyed>,
    references: Vec<Keyed>,
    /// The settled references: those the association frame has passed, whose place in it
    /// no later pose changes (the frame's poses arrive in stamp order), for the candidate
    /// search.
    index: ReferenceIndex,
    /// References before this one are settled (in `index`, or not placeable).
    settled: usize,
    /// References before this index hold no pixels in memory.
    in_memory_from: usize,
    spill: PixelSpill,
    last_query_odom: Option<Planar>,
    counts: Counts,
    /// Every pair judged since the last [`LoopCloser::take_attempts`], when kept.
    attempts: Option<Vec<Attempt>>,
}

impl LoopCloser {
    /// A loop closer matching with `matcher`.
    pub fn new(params: CloserParams, matcher: Box<dyn Matcher>) -> Self {
        Self {
            index: ReferenceIndex::new(&params.candidates),
            settled: 0,
            params,
            matcher,
            estimate: Track::new(),
            truth: Track::new(),
            pending: VecDeque::new(),
            references: Vec::new(),
            in_memory_from: 0,
            spill: PixelSpill::default(),
            last_query_odom: None,
            counts: Counts::default(),
            attempts: None,
        }
    }

    /// Keeps every pair the matcher judges, for [`LoopCloser::take_attempts`].
    #[must_use]
    pub fn keeping_attempts(mut self) -> Self {
        self.attempts = Some(Vec::new());
        self
    }

    /// The pairs judged since the last call, in order (none unless
    /// [`keeping_attempts`](Self::keeping_attempts)).
    pub fn take_attempts(&mut self) -> Vec<Attempt> {
        self.attempts.as_mut().map(std::mem::take).unwrap_or_default()
    }

    /// The matcher's method.
    pub fn method(&self) -> Method {
        self.matcher.method()
    }

    /// What happened so far.
    pub fn counts(&self) -> &Counts {
        &self.counts
    }

    /// References kept.
    pub fn references(&self) -> usize {
        self.references.len()
    }

    /// Bytes of the references' pixels and features held in memory, and bytes of pixels
    /// moved to the spill file.
    pub fn reference_bytes(&self) -> (u64, u64) {
        let held = self
            .references
            .iter()
            .map(|r| {
                let features = r
                    .features
                    .as_ref()
                    .map_or(0, |f| std::mem::size_of_val(f.data.as_slice()));
                (std::mem::size_of_val(r.pixels.as_slice()) + features + r.column_stamps_ns.len() * 8) as u64
            })
            .sum();
        (held, self.spill.bytes())
    }

    /// Adds a pose of the estimate (the association frame with [`Association::Estimate`]).
    ///
    /// # Errors
    /// A pose that is not finite.
    pub fn add_estimate(&mut self, stamp_ns: i64, pose: Planar) -> std::result::Result<(), NonFinitePose> {
        self.add_pose(Association::Estimate, stamp_ns, pose)
    }

    /// Adds a ground-truth pose.
    ///
    /// # Errors
    /// A pose that is not finite.
    pub fn add_truth(&mut self, stamp_ns: i64, pose: Planar) -> std::result::Result<(), NonFinitePose> {
        self.add_pose(Association::Truth, stamp_ns, pose)
    }

    /// Adds a pose to the estimate or the truth. One that arrives out of stamp order in the
    /// association frame may move settled references: they are all placed again.
    fn add_pose(&mut self, to: Association, stamp_ns: i64, pose: Planar) -> std::result::Result<(), NonFinitePose> {
        let track = match to {
            Association::Estimate => &mut self.estimate,
            Association::Truth => &mut self.truth,
        };
        let appended = track.last_stamp_ns().is_none_or(|last| stamp_ns > last);
        track.insert(stamp_ns, pose)?;
        if !appended && self.params.association == to {
            self.index.clear();
            self.settled = 0;
        }
        Ok(())
    }

    /// Settles the references the association frame has passed since the last call.
    fn settle_references(&mut self) {
        let gap = self.max_gap_ns();
        let track = match self.params.association {
            Association::Estimate => &self.estimate,
            Association::Truth => &self.truth,
        };
        let Some(last) = track.last_stamp_ns() else { return };
        while let Some(r) = self.references.get(self.settled) {
            if r.anchor.stamp_ns > last {
                break;
            }
            if let Some(pose) = r.anchor.locate(track, gap) {
                self.index.insert(Placed {
                    index: self.settled,
                    stamp_ns: r.anchor.stamp_ns,
                    pose,
                });
            }
            self.settled += 1;
        }
    }

    /// Queues a submap; [`LoopCloser::poll`] takes it once the association frame reaches it.
    pub fn push(&mut self, keyed: Keyed) {
        self.pending.push_back(keyed);
    }

    /// The matches of the queued submaps the association frame reaches (`all`: of every
    /// queued submap, at the end), in order.
    ///
    /// # Errors
    /// The matcher's ([`Matcher`]).
    pub fn poll(&mut self, all: bool) -> Result<Vec<Match>> {
        let mut matches = Vec::new();
        while let Some(front) = self.pending.front() {
            if !all && !self.ready(front) {
                break;
            }
            let Some(keyed) = self.pending.pop_front() else { break };
            self.process(keyed, &mut matches)?;
        }
        Ok(matches)
    }

    fn max_gap_ns(&self) -> i64 {
        (self.params.max_track_gap_s * 1e9) as i64
    }

    fn association(&self) -> &Track {
        match self.params.association {
            Association::Estimate => &self.estimate,
            Association::Truth => &self.truth,
        }
    }

    /// The association frame (and the truth, for the oracle) reach this submap.
    fn ready(&self, e: &Keyed) -> bool {
        let reached = |t: &Track, stamp: i64| t.last_stamp_ns().is_some_and(|last| last >= stamp);
        let placed = match self.params.association {
            Association::Estimate => reached(&self.estimate, e.anchor.start_stamp_ns),
            Association::Truth => reached(&self.truth, e.anchor.stamp_ns),
        };
        placed && (!self.matcher.needs_truth() || reached(&self.truth, e.anchor.stamp_ns))
    }

    fn process(&mut self, mut q: Keyed, matches: &mut Vec<Match>) -> Result<()> {
        let gap = self.max_gap_ns();
        let Some(q_pose) = q.anchor.locate(self.association(), gap) else {
            self.counts.never_placed += 1;
            return Ok(());
        };
        let spaced = self.last_query_odom.is_none_or(|p| {
            (p.x_m - q.anchor.odom.x_m).hypot(p.y_m - q.anchor.odom.y_m) >= self.params.query_spacing_m
        });
        if spaced {
            // The settled references near the query, and the newest ones placed afresh.
            self.settle_references();
            let mut placed = Vec::new();
            self.index.near(&q_pose, &mut placed);
            let newest = self.references.iter().enumerate().skip(self.settled);
            placed.extend(newest.filter_map(|(index, r)| {
                Some(Placed {
                    index,
                    stamp_ns: r.anchor.stamp_ns,
                    pose: r.anchor.locate(self.association(), gap)?,
                })
            }));
            let found = candidates(&self.params.candidates, q.anchor.stamp_ns, &q_pose, &placed);
            if !found.is_empty() {
                self.counts.queries += 1;
                self.last_query_odom = Some(q.anchor.odom);
                self.matcher.prepare(&mut q, &mut self.counts)?;
                self.matcher.begin_query(&q, &mut self.counts)?;
            }
            for (index, _) in found {
                self.counts.pairs += 1;
                match self.match_pair(index, &q)? {
                    Some(m) => matches.push(m),
                    None => self.counts.rejected += 1,
                }
            }
        }
        let keep = self.references.last().is_none_or(|r| {
            (r.anchor.odom.x_m - q.anchor.odom.x_m).hypot(r.anchor.odom.y_m - q.anchor.odom.y_m)
                >= self.params.reference_spacing_m
        });
        if keep {
            self.matcher.prepare(&mut q, &mut self.counts)?;
            if !self.matcher.reference_needs_pixels() {
                q.pixels = Vec::new();
            }
            self.references.push(q);
            self.spill_old_references()?;
        }
        Ok(())
    }

    /// Moves the pixels of all but the newest `references_in_memory` references to the spill
    /// file.
    fn spill_old_references(&mut self) -> Result<()> {
        let keep_from = self.references.len().saturating_sub(self.params.references_in_memory);
        while self.in_memory_from < keep_from {
            let r = &mut self.references[self.in_memory_from];
            if !r.pixels.is_empty() {
                r.spilled_at = Some(self.spill.put(&r.pixels)?);
                r.pixels = Vec::new();
            }
            self.in_memory_from += 1;
        }
        Ok(())
    }

    /// The match of query `q` with reference `index`, or `None` when the method refuses it.
    fn match_pair(&mut self, index: usize, q: &Keyed) -> Result<Option<Match>> {
        // a spilled reference's pixels come back for the match and go again after it
        let spilled = self.references[index].spilled_at;
        if let Some(offset) = spilled {
            let r = &mut self.references[index];
            let mut pixels = Vec::new();
            self.spill.get(offset, r.rows * r.cols, &mut pixels)?;
            r.pixels = pixels;
        }
        let matched = self.match_held(index, q);
        if spilled.is_some() {
            self.references[index].pixels = Vec::new();
        }
        matched
    }

    fn match_held(&mut self, index: usize, q: &Keyed) -> Result<Option<Match>> {
        let r = &self.references[index];
        let context = Context {
            truth: &self.truth,
            max_gap_ns: self.max_gap_ns(),
        };
        // `refused`: why, when the method refused the pair
        let (refused, shift_m, score, stretch) = match self.matcher.assess(r, q, &context)? {
            Outcome::Matched {
                shift_m,
                score,
                stretch,
            } => (None, shift_m, score, stretch),
            Outcome::Refused {
                why,
                shift_m,
                score,
                stretch,
            } => (Some(why), shift_m, score, stretch),
        };
        if let Some(attempts) = &mut self.attempts {
            attempts.push(Attempt {
                reference: r.id,
                query: q.id,
                anchors_ns: (r.anchor.stamp_ns, q.anchor.stamp_ns),
                outcome: refused.unwrap_or("registered"),
                shift_m,
                score,
                stretch,
            });
        }
        if refused.is_some() {
            return Ok(None);
        }
        if stretch != 1.0 {
            self.counts.stretched += 1;
        }
        let sigma = self.params.sigma_m.unwrap_or_else(|| self.matcher.sigma_m());
        let overlap = (self.matcher.on_grid() && self.params.stamps == Stamps::Overlap)
            .then(|| overlap_stamps(r, q, shift_m))
            .flatten();
        let (stamps_ns, along_m) = match overlap {
            Some(stamps) => (stamps, 0.0),
            None => ((r.anchor.stamp_ns, q.anchor.stamp_ns), shift_m),
        };
        Ok(Some(Match {
            reference: r.id,
            query: q.id,
            stamps_ns,
            along_m,
            variance_m2: sigma * sigma,
            score,
            method: self.matcher.method(),
            stretch,
        }))
    }
}

/// The moments (reference, query), ns, the two passes were over the middle of the ground
/// they share when the query's column 0 lies `shift_m` along the reference's; `None` when
/// they share none or a submap has no column stamps.
pub fn overlap_stamps(r: &Keyed, q: &Keyed, shift_m: f64) -> Option<(i64, i64)> {
    let (cr, cq) = (r.column_stamps_ns.len(), q.column_stamps_ns.len());
    if cr == 0 || cq == 0 {
        return None;
    }
    // query column c lies over reference column offset + c * scale
    let offset = shift_m / r.resolution_m;
    let scale = q.resolution_m / r.resolution_m;
    let first = (-offset / scale).max(0.0);
    let last = (((cr - 1) as f64 - offset) / scale).min((cq - 1) as f64);
    if !(first.is_finite() && last.is_finite()) || first > last {
        return None;
    }
    let c_q = 0.5 * (first + last);
    let at = |stamps: &[i64], c: f64| {
        let c = c.clamp(0.0, (stamps.len() - 1) as f64);
        let (i, frac) = (c.floor() as usize, c - c.floor());
        let (a, b) = (stamps[i], stamps[(i + 1).min(stamps.len() - 1)]);
        a + ((b - a) as f64 * frac).round() as i64
    };
    Some((
        at(&r.column_stamps_ns, offset + c_q * scale),
        at(&q.column_stamps_ns, c_q),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ground_order_reverses_columns_of_backward_submaps() {
        let px: Vec<f32> = (0..6).map(|v| v as f32).collect();
        assert_eq!(ground_order(&px, 2, 3, false), px);
        assert_eq!(ground_order(&px, 2, 3, true), vec![2.0, 1.0, 0.0, 5.0, 4.0, 3.0]);
    }

    /// A submap of `cols` columns of 0.01 m crossed at `t0_ns + step_ns * c`.
    fn timed(cols: usize, t0_ns: i64, step_ns: i64, backward: bool) -> Keyed {
        let stamps: Vec<i64> = (0..cols as i64).map(|c| t0_ns + step_ns * c).collect();
        let (start, end) = if backward { (1.0, 0.0) } else { (0.0, 1.0) };
        let origin = Planar {
            x_m: 0.0,
            y_m: 0.0,
            yaw_rad: 0.0,
        };
        Keyed::new(&SubmapIn {
            id: 0,
            rows: 1,
            cols,
            resolution_m: 0.01,
            pixels: &vec![0.0; cols],
            column_stamps_ns: &stamps,
            start_distance_m: start,
            end_distance_m: end,
            start_pose: origin,
            end_pose: origin,
            start_stamp_ns: 0,
            end_stamp_ns: 0,
        })
        .expect("a good submap")
    }

    /// A loop closer with the engineered method, estimate association and default gates.
    fn engineered_closer(references_in_memory: usize) -> LoopCloser {
        let params = CloserParams {
            association: Association::Estimate,
            candidates: CandidateGates::default(),
            sigma_m: None,
            reference_spacing_m: 0.3,
            query_spacing_m: 0.5,
            max_track_gap_s: 1.0,
            stamps: Stamps::Anchors,
            references_in_memory,
        };
        let engineered = Engineered::new(crate::engineered::EngineeredParams::default(), 0.3);
        LoopCloser::new(params, Box::new(engineered))
    }

    #[test]
    fn references_settle_once_the_frame_passes_them_and_a_late_pose_places_them_again() {
        let mut closer = engineered_closer(256);
        let at = |x_m: f64| Planar {
            x_m,
            y_m: 0.0,
            yaw_rad: 0.0,
        };
        // anchors at 1 000 and 3 000 ns, where the frame will be at x 1 and 3 m
        let anchored = |stamp_ns: i64| {
            let mut r = timed(10, stamp_ns, 10, false);
            (r.anchor.stamp_ns, r.anchor.start_stamp_ns) = (stamp_ns, stamp_ns);
            r
        };
        closer.references = vec![anchored(1_000), anchored(3_000)];
        closer.add_estimate(0, at(0.0)).expect("finite");
        closer.add_estimate(2_000, at(2.0)).expect("finite");
        closer.settle_references();
        // the frame has passed the first anchor only
        assert_eq!((closer.settled, closer.index.len()), (1, 1));
        let mut near = Vec::new();
        closer.index.near(&at(1.0), &mut near);
        assert!((near[0].pose.x_m - 1.0).abs() < 1e-9, "{near:?}");
        closer.add_estimate(4_000, at(4.0)).expect("finite");
        closer.settle_references();
        assert_eq!((closer.settled, closer.index.len()), (2, 2));
        // a pose between two others moves the first anchor: everything is placed again
        closer.add_estimate(1_000, at(1.5)).expect("finite");
        assert_eq!((closer.settled, closer.index.len()), (0, 0));
        closer.settle_references();
        near.clear();
        closer.index.near(&at(1.5), &mut near);
        let first = near.iter().find(|p| p.index == 0).expect("placed");
        assert!((first.pose.x_m - 1.5).abs() < 1e-9, "{near:?}");
    }

    #[test]
    fn a_grid_shift_goes_out_as_the_moments_over_the_middle_of_the_shared_ground() {
        let (r, q) = (timed(100, 1_000, 10, false), timed(100, 5_000, 20, false));
        // query column 0 over reference column 30: they share query columns 0..=69
        assert_eq!(overlap_stamps(&r, &q, 0.3), Some((1_000 + 645, 5_000 + 690)));
        // query column 30 over reference column 0: query columns 30..=99
        assert_eq!(overlap_stamps(&r, &q, -0.3), Some((1_000 + 345, 5_000 + 1290)));
        assert_eq!(overlap_stamps(&r, &q, 0.0), Some((1_000 + 495, 5_000 + 990)));
        // nothing shared
        assert_eq!(overlap_stamps(&r, &q, 1.5), None);
        let none = Keyed {
            column_stamps_ns: Vec::new(),
            ..timed(100, 0, 10, false)
        };
        assert_eq!(overlap_stamps(&none, &q, 0.3), None);
        // a backward submap's stamps are put in ground order with its pixels: its column 0
        // (in ground order) is its newest
        let back = timed(100, 1_000, 10, true);
        assert_eq!(back.column_stamps_ns[0], 1_000 + 990);
        assert_eq!(overlap_stamps(&back, &q, 0.3), Some((1_000 + 990 - 645, 5_000 + 690)));
    }

    /// Two passes east along the same 24 m of ground with a random texture (20 rows, 5 cm
    /// columns), 3 m submaps every metre, the second pass 100 s after the first; the estimate
    /// is the truth. Returns the matches and the reference store's (held, spilled) bytes.
    fn two_passes(references_in_memory: usize) -> (Vec<Match>, (u64, u64)) {
        let (rows, res, len_m, speed) = (20usize, 0.05, 3.0, 0.5);
        let texture = |row: usize, x_m: f64| -> f32 {
            let cell = (x_m / res).round() as i64;
            let h =
                (cell as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (row as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            ((h >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        };
        let mut closer = engineered_closer(references_in_memory);
        let pose = |x_m: f64| Planar {
            x_m,
            y_m: 0.0,
            yaw_rad: 0.0,
        };
        let stamp = |pass: i64, x_m: f64| pass * 100_000_000_000 + (x_m / speed * 1e9) as i64;
        let mut matches = Vec::new();
        let mut id = 0;
        for pass in 0..2 {
            for step in 0..22 {
                let x0 = f64::from(step);
                let cols = (len_m / res) as usize;
                let mut pixels = vec![0f32; rows * cols];
                for r in 0..rows {
                    for c in 0..cols {
                        pixels[r * cols + c] = texture(r, x0 + c as f64 * res);
                    }
                }
                let stamps: Vec<i64> = (0..cols).map(|c| stamp(pass, x0 + c as f64 * res)).collect();
                for (c, t) in stamps.iter().enumerate().step_by(10) {
                    closer.add_estimate(*t, pose(x0 + c as f64 * res)).expect("finite");
                }
                let end_x = x0 + (cols - 1) as f64 * res;
                closer.add_estimate(stamps[cols - 1], pose(end_x)).expect("finite");
                closer.push(
                    Keyed::new(&SubmapIn {
                        id,
                        rows,
                        cols,
                        resolution_m: res,
                        pixels: &pixels,
                        column_stamps_ns: &stamps,
                        start_distance_m: x0,
                        end_distance_m: end_x,
                        start_pose: pose(x0),
                        end_pose: pose(end_x),
                        start_stamp_ns: stamps[0],
                        end_stamp_ns: stamps[cols - 1],
                    })
                    .expect("a good submap"),
                );
                id += 1;
                matches.extend(closer.poll(false).expect("matches"));
            }
        }
        matches.extend(closer.poll(true).expect("matches"));
        (matches, closer.reference_bytes())
    }

    #[test]
    fn references_moved_to_the_spill_file_match_as_they_did_in_memory() {
        let (in_memory, (held_all, spilled_none)) = two_passes(usize::MAX);
        let (spilled, (held_one, spilled_bytes)) = two_passes(1);
        assert!(in_memory.len() >= 10, "the second pass registers: {}", in_memory.len());
        assert!(in_memory.iter().all(|m| m.along_m.abs() < 0.05), "{in_memory:?}");
        assert_eq!(spilled, in_memory);
        assert_eq!(spilled_none, 0);
        // 44 submaps, one reference each (1 m apart); one keeps its pixels
        let pixels = 20 * 60 * 4;
        assert!(
            held_all >= 44 * pixels && held_one < 2 * pixels + 44 * 60 * 8,
            "{held_all} {held_one}"
        );
        assert_eq!(spilled_bytes, 43 * pixels);
    }

    #[test]
    fn the_method_sets_the_sigma_unless_the_parameter_does() {
        let engineered = Engineered::new(crate::engineered::EngineeredParams::default(), 0.3);
        assert_eq!(engineered.sigma_m(), 0.1);
        assert_eq!((Oracle.sigma_m(), Zeroth { shift_m: 0.0 }.sigma_m()), (0.02, 0.02));
        assert!(!Oracle.on_grid() && Oracle.needs_truth() && engineered.on_grid());
    }
}
