//! The `register` stage: submaps in, [`Registration`]s out (seed 000 §4.3-4.5).
//!
//! Every valid submap is put in ground order ([`ground_order`]) and kept as a reference
//! (one every `reference_spacing_m` of travel). A new submap, the query, is placed in the
//! association frame (the estimate, read as a feedback input, or the ground truth for the
//! oracle association) and registered with the references that pass the loop-candidate
//! gates ([`crate::candidates`]). The method is the engineered correlation baseline, the
//! learned model, or the oracle (the ground-truth transform; evaluation only). Submaps
//! below the saliency gate are neither references nor queries; a match below the method's
//! own gate (peak correlation, or the learned "shared features" check) is not sent.
//!
//! A query waits until the association frame reaches it: the estimate (or truth) must cover
//! its oldest trace (its anchor with the oracle), so registrations go out slightly after
//! their submap. A registration carries the two anchor stamps and the shift between them;
//! with `stamps: overlap` a shift found on the grid (every method but the oracle) goes out
//! instead as the moments the two passes were over the middle of their shared ground (the
//! submaps' column stamps, `overlap_stamps`) with an along-track offset of zero, free of
//! the wheel's scale error that the grid, laid on wheel distance, puts into a shift.

use std::collections::VecDeque;
use std::path::PathBuf;

use gprflow_msg::{
    Covariance6, Header, Message, Point, Pose, PoseStamped, Quaternion, Registration, StateEstimate, Submap, Time,
};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use gprflow_geometry::{Planar, Track};

use crate::candidates::{Anchor, CandidateGates, Placed, candidates};
use crate::engineered::{EngineeredParams, SubmapView, register as engineered_register};
use crate::learned::{Features, Head, Model};
use crate::{Error, Result, positive, stretch};

/// How a candidate pair is registered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
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
    fn name(self) -> &'static str {
        match self {
            Self::Engineered => "engineered",
            Self::Learned => "learned",
            Self::Oracle => "oracle",
            Self::Zeroth => "zeroth",
        }
    }
}

/// Where submaps are placed to find loop candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Association {
    /// The current estimate (the `estimate` feedback input): the normal mode.
    Estimate,
    /// The ground truth (the `truth` input): the oracle association, for evaluation only.
    Truth,
}

/// Which two moments a registration found on the submap grid relates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
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

/// Parameters of the `register` stage.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RegisterParams {
    /// Registration method (default engineered).
    pub method: Method,
    /// Where loop candidates come from (default estimate).
    pub association: Association,
    /// Loop-candidate gates.
    pub candidates: CandidateGates,
    /// The engineered method's search.
    pub engineered: EngineeredParams,
    /// The learned model's encoder (default stages/register/models/ground_encoding.onnx).
    pub model: PathBuf,
    /// The learned model's head (default stages/register/models/ground_encoding.head.json;
    /// ground_encoding.nonlinear.json is the nonlinear one).
    pub head: PathBuf,
    /// ONNX Runtime library (default: from tools/scripts/ensure-onnxruntime.sh, see
    /// [`crate::learned::onnxruntime_library`]).
    pub onnxruntime: Option<PathBuf>,
    /// Smallest peak correlation the engineered method accepts (default 0.3).
    pub min_score: f64,
    /// Smallest saliency (average-pooled row-wise standard deviation) of a submap that is
    /// registered at all (default 0: every valid submap).
    pub min_saliency: f32,
    /// Along-track sigma sent with each registration, m (default: 0.1 engineered, the head's
    /// `sigma_m` learned, 0.02 oracle).
    pub sigma_m: Option<f64>,
    /// Keep a reference every this much travel, m (default 0.3).
    pub reference_spacing_m: f64,
    /// Try a query every this much travel, m (default 0.5).
    pub query_spacing_m: f64,
    /// Longest gap between two poses of the association frame that is interpolated, s (default 1).
    pub max_track_gap_s: f64,
    /// Which moments a grid method's registration relates (default anchors; the oracle always
    /// sends the ground-truth offset between the anchors).
    pub stamps: Stamps,
    /// The learned method's travel-time stretch search: each query is also encoded with its
    /// rows stretched by `1 +- k * stretch_step` for `k` in `1..=stretch_steps`, and for each
    /// pair the stretch whose features share most with the reference (highest mean channel
    /// peak) is the one the checks and the head judge. It follows the wave speed changing
    /// between passes (drying soil). Default 0 (off); graphs/localize.yaml sets 1. It
    /// registers more pairs on runs whose soil dried between passes, and lets through rare
    /// wrong matches the checks were not chosen for, which the estimator's registration gate
    /// is there to drop (README, "Localisation").
    pub stretch_steps: usize,
    /// Relative stretch between two neighbouring factors of the search (default 0.015).
    pub stretch_step: f64,
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            method: Method::Engineered,
            association: Association::Estimate,
            candidates: CandidateGates::default(),
            engineered: EngineeredParams::default(),
            model: PathBuf::from("stages/register/models/ground_encoding.onnx"),
            head: PathBuf::from("stages/register/models/ground_encoding.head.json"),
            onnxruntime: None,
            min_score: 0.3,
            min_saliency: 0.0,
            sigma_m: None,
            reference_spacing_m: 0.3,
            query_spacing_m: 0.5,
            max_track_gap_s: 1.0,
            stamps: Stamps::Anchors,
            stretch_steps: 0,
            stretch_step: 0.015,
        }
    }
}

impl RegisterParams {
    fn check(&self) -> Result<()> {
        self.candidates.check()?;
        stretch::factors(self.stretch_step, self.stretch_steps)?;
        positive("reference_spacing_m", self.reference_spacing_m)?;
        positive("query_spacing_m", self.query_spacing_m)?;
        positive("max_track_gap_s", self.max_track_gap_s)?;
        if let Some(s) = self.sigma_m {
            positive("sigma_m", s)?;
        }
        if !(self.min_score.is_finite() && (-1.0..=1.0).contains(&self.min_score)) {
            return Err(Error::Param {
                key: "min_score",
                message: format!("must be a correlation in -1..=1, got {}", self.min_score),
            });
        }
        if !self.min_saliency.is_finite() {
            return Err(Error::Param {
                key: "min_saliency",
                message: format!("must be finite, got {}", self.min_saliency),
            });
        }
        Ok(())
    }

    /// The sigma sent: the parameter, else the method's (`learned`: the model's own).
    fn sigma(&self, learned_sigma_m: Option<f64>) -> f64 {
        self.sigma_m.unwrap_or(match self.method {
            Method::Engineered => 0.1,
            Method::Learned => learned_sigma_m.unwrap_or(0.1),
            Method::Oracle | Method::Zeroth => 0.02,
        })
    }
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

fn planar_of(p: &Pose) -> Planar {
    let q = &p.orientation;
    Planar::from_quaternion(p.position.x, p.position.y, [q.x, q.y, q.z, q.w])
}

/// A submap ready to be registered: ground-order pixels and where it sits.
#[derive(Debug)]
struct Entry {
    id: u32,
    anchor: Anchor,
    rows: usize,
    cols: usize,
    resolution_m: f64,
    pixels: Vec<f32>,
    /// When the rig was over each column, ns, in ground order (empty when the submap has none).
    column_stamps_ns: Vec<i64>,
    /// The learned model's features, encoded once when the submap is first needed: as a
    /// query with loop candidates, or kept as a reference (most submaps are neither).
    features: Option<Features>,
}

impl Entry {
    fn view(&self) -> SubmapView<'_> {
        SubmapView {
            pixels: &self.pixels,
            rows: self.rows,
            cols: self.cols,
            resolution_m: self.resolution_m,
        }
    }

    /// Checks the message and builds the entry; `Err` says what is wrong with it.
    fn from_msg(m: &Submap<'_>) -> std::result::Result<Self, String> {
        let (rows, cols) = (m.rows as usize, m.cols as usize);
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
        let (start, end) = (planar_of(&m.start_pose), planar_of(&m.end_pose));
        let end_stamp_ns = m.header.stamp.to_ns();
        let start_stamp_ns = m.start_stamp.to_ns();
        Ok(Self {
            id: m.id,
            anchor: Anchor {
                stamp_ns: if backward { end_stamp_ns } else { start_stamp_ns },
                odom: if backward { end } else { start },
                odom_start: start,
                start_stamp_ns,
                backward,
            },
            rows,
            cols,
            resolution_m: m.resolution_m,
            pixels: ground_order(&m.pixels, rows, cols, backward),
            column_stamps_ns: if backward {
                m.column_stamps_ns.iter().rev().copied().collect()
            } else {
                m.column_stamps_ns.to_vec()
            },
            features: None,
        })
    }
}

/// What happened to the submaps and pairs, reported at the end.
#[derive(Debug, Default)]
struct Counts {
    invalid: u64,
    not_salient: u64,
    queries: u64,
    pairs: u64,
    rejected: u64,
    sent: u64,
    never_placed: u64,
    /// Learned registrations whose query was stretched.
    stretched: u64,
    /// Encoder runs, the stretch search's among them.
    encoded: u64,
}

/// The register stage.
#[derive(Debug)]
pub struct RegisterStage {
    params: RegisterParams,
    model: Option<Model>,
    /// The learned method's travel-time stretches, 1 among them.
    stretches: Vec<f64>,
    /// The zeroth-order model's constant shift, m.
    zeroth_m: Option<f64>,
    out: Output<Registration>,
    estimate: Track,
    truth: Track,
    pending: VecDeque<Entry>,
    references: Vec<Entry>,
    last_query_odom: Option<Planar>,
    last_primary_ns: i64,
    counts: Counts,
    drops: Drops,
}

impl RegisterStage {
    fn max_gap_ns(&self) -> i64 {
        (self.params.max_track_gap_s * 1e9) as i64
    }

    fn association(&self) -> &Track {
        match self.params.association {
            Association::Estimate => &self.estimate,
            Association::Truth => &self.truth,
        }
    }

    /// The association frame (and the truth, for the oracle) reach this entry.
    fn ready(&self, e: &Entry) -> bool {
        let reached = |t: &Track, stamp: i64| t.last_stamp_ns().is_some_and(|last| last >= stamp);
        let placed = match self.params.association {
            Association::Estimate => reached(&self.estimate, e.anchor.start_stamp_ns),
            Association::Truth => reached(&self.truth, e.anchor.stamp_ns),
        };
        placed && (self.params.method != Method::Oracle || reached(&self.truth, e.anchor.stamp_ns))
    }

    fn process_pending(&mut self, stamp_ns: i64, out: &mut Outputs, all: bool) -> std::result::Result<(), StageError> {
        while let Some(front) = self.pending.front() {
            if !all && !self.ready(front) {
                break;
            }
            let Some(entry) = self.pending.pop_front() else { break };
            self.process(entry, stamp_ns, out)?;
        }
        Ok(())
    }

    fn process(&mut self, mut q: Entry, stamp_ns: i64, out: &mut Outputs) -> std::result::Result<(), StageError> {
        let gap = self.max_gap_ns();
        let Some(q_pose) = q.anchor.locate(self.association(), gap) else {
            self.counts.never_placed += 1;
            return Ok(());
        };
        let spaced = self.last_query_odom.is_none_or(|p| {
            (p.x_m - q.anchor.odom.x_m).hypot(p.y_m - q.anchor.odom.y_m) >= self.params.query_spacing_m
        });
        if spaced {
            let placed: Vec<Placed> = self
                .references
                .iter()
                .enumerate()
                .filter_map(|(index, r)| {
                    Some(Placed {
                        index,
                        stamp_ns: r.anchor.stamp_ns,
                        pose: r.anchor.locate(self.association(), gap)?,
                    })
                })
                .collect();
            let found = candidates(&self.params.candidates, q.anchor.stamp_ns, &q_pose, &placed);
            if !found.is_empty() {
                self.counts.queries += 1;
                self.last_query_odom = Some(q.anchor.odom);
            }
            let queries = if found.is_empty() {
                Vec::new()
            } else {
                self.encode(&mut q)?;
                self.query_features(&q)?
            };
            for (index, _) in found {
                self.counts.pairs += 1;
                match self.register_pair(index, &q, &queries)? {
                    Some(msg) => {
                        let msg = Registration {
                            header: Header::new(stamp_ns, "base_link"),
                            ..msg
                        };
                        out.send(self.out, &msg)?;
                        self.counts.sent += 1;
                    }
                    None => self.counts.rejected += 1,
                }
            }
        }
        let keep = self.references.last().is_none_or(|r| {
            (r.anchor.odom.x_m - q.anchor.odom.x_m).hypot(r.anchor.odom.y_m - q.anchor.odom.y_m)
                >= self.params.reference_spacing_m
        });
        if keep {
            self.encode(&mut q)?;
            self.references.push(q);
        }
        Ok(())
    }

    /// Encodes `e` with the learned model unless it is already encoded (or the method has
    /// no model).
    fn encode(&mut self, e: &mut Entry) -> std::result::Result<(), StageError> {
        if let (Some(model), None) = (self.model.as_mut(), e.features.as_ref()) {
            e.features = Some(model.encode(&e.view()).map_err(StageError::failed)?);
            self.counts.encoded += 1;
        }
        Ok(())
    }

    /// The learned model's features of query `q` at every stretch of the search (the order of
    /// `self.stretches`); empty for the other methods.
    fn query_features(&mut self, q: &Entry) -> std::result::Result<Vec<Features>, StageError> {
        let (Some(model), Some(unstretched)) = (self.model.as_mut(), q.features.as_ref()) else {
            return Ok(Vec::new());
        };
        let mut out = Vec::with_capacity(self.stretches.len());
        let mut pixels = Vec::new();
        for &factor in &self.stretches {
            if factor == 1.0 {
                out.push(unstretched.clone());
                continue;
            }
            stretch::stretch_rows(&q.view(), factor, &mut pixels).map_err(StageError::failed)?;
            let view = SubmapView {
                pixels: &pixels,
                ..q.view()
            };
            out.push(model.encode(&view).map_err(StageError::failed)?);
            self.counts.encoded += 1;
        }
        Ok(out)
    }

    /// The registration of query `q` (`queries`: its learned features at each stretch) against
    /// reference `index`, or `None` when the method's gate refuses it.
    fn register_pair(
        &mut self,
        index: usize,
        q: &Entry,
        queries: &[Features],
    ) -> std::result::Result<Option<Registration>, StageError> {
        let r = &self.references[index];
        let mut learned_sigma = None;
        let (shift_m, score) = match self.params.method {
            Method::Engineered => {
                let m = match engineered_register(&r.view(), &q.view(), &self.params.engineered) {
                    Ok(m) => m,
                    // different shapes (a recording with two radars, say): not comparable
                    Err(Error::Shape(why)) => {
                        tracing::debug!(reference = r.id, query = q.id, "not registered: {why}");
                        return Ok(None);
                    }
                    Err(e) => return Err(StageError::failed(e)),
                };
                match m {
                    Some(m) if m.score >= self.params.min_score => (m.shift_m, m.score),
                    _ => return Ok(None),
                }
            }
            Method::Learned => {
                let (Some(model), Some(fr)) = (self.model.as_mut(), r.features.as_ref()) else {
                    return Ok(None);
                };
                if queries.is_empty() {
                    return Ok(None);
                }
                learned_sigma = Some(model.head.sigma_m);
                let (m, refusal, at) = model
                    .assess_best(fr, queries, q.resolution_m)
                    .map_err(StageError::failed)?;
                let stretch = self.stretches.get(at).copied().unwrap_or(1.0);
                // one line per pair, registered or not (tools/scripts/refusals.py reads the
                // refused; built only when it goes out)
                if tracing::enabled!(tracing::Level::DEBUG) {
                    let verdict =
                        refusal.map_or_else(|| "registered".to_owned(), |why| format!("not registered: {why:?}"));
                    tracing::debug!(
                        reference = r.id,
                        query = q.id,
                        reference_stamp_ns = r.anchor.stamp_ns,
                        query_stamp_ns = q.anchor.stamp_ns,
                        shift_m = m.shift_m,
                        share_score = m.share_score,
                        agreement = m.agreement,
                        stretch,
                        corr = ?m.corr,
                        "{verdict}"
                    );
                }
                if refusal.is_some() {
                    return Ok(None);
                }
                if stretch != 1.0 {
                    self.counts.stretched += 1;
                }
                (m.shift_m, m.share_score)
            }
            Method::Zeroth => match self.zeroth_m {
                Some(z) => (z, 0.0),
                None => return Ok(None),
            },
            Method::Oracle => {
                let gap = self.max_gap_ns();
                let (Some(a), Some(b)) = (
                    self.truth.at(r.anchor.stamp_ns, gap),
                    self.truth.at(q.anchor.stamp_ns, gap),
                ) else {
                    return Ok(None);
                };
                (a.relative(&b).0, 1.0)
            }
        };
        let sigma = self.params.sigma(learned_sigma);
        let on_grid = self.params.method != Method::Oracle;
        let overlap = (on_grid && self.params.stamps == Stamps::Overlap)
            .then(|| overlap_stamps(r, q, shift_m))
            .flatten();
        let (stamps_ns, along_m) = match overlap {
            Some(stamps) => (stamps, 0.0),
            None => ((r.anchor.stamp_ns, q.anchor.stamp_ns), shift_m),
        };
        Ok(Some(registration(
            r,
            q,
            stamps_ns,
            along_m,
            score,
            sigma,
            self.params.method.name(),
        )))
    }
}

/// The moments (reference, query), ns, the two passes were over the middle of the ground
/// they share when the query's column 0 lies `shift_m` along the reference's; `None` when
/// they share none or a submap has no column stamps.
fn overlap_stamps(r: &Entry, q: &Entry, shift_m: f64) -> Option<(i64, i64)> {
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

/// A registration of `q` against `r`: `q` at `stamps_ns.1` lies `along_m` along track from
/// `r` at `stamps_ns.0`; the other axes get a large variance (an along-track-only measurement).
fn registration(
    r: &Entry,
    q: &Entry,
    stamps_ns: (i64, i64),
    along_m: f64,
    score: f64,
    sigma_m: f64,
    method: &str,
) -> Registration {
    const LOOSE: f64 = 1e4;
    let variance = sigma_m * sigma_m;
    let mut cov = [0.0; 36];
    for (i, v) in [variance, LOOSE, LOOSE, LOOSE, LOOSE, LOOSE].into_iter().enumerate() {
        cov[i * 7] = v;
    }
    Registration {
        header: Header::default(),
        reference_submap: r.id,
        query_submap: q.id,
        reference_stamp: Time::from_ns(stamps_ns.0),
        query_stamp: Time::from_ns(stamps_ns.1),
        reference_from_query: Pose {
            position: Point {
                x: along_m,
                y: 0.0,
                z: 0.0,
            },
            orientation: Quaternion {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 1.0,
            },
        },
        covariance: Covariance6(cov),
        along_track_m: along_m,
        along_track_variance_m2: variance,
        score: score as f32,
        method: method.to_owned(),
    }
}

fn param_error(e: Error) -> StageError {
    match e {
        Error::Param { key, message } => StageError::Params(ParamError {
            path: key.split('.').map(str::to_owned).collect(),
            message,
        }),
        other => StageError::failed(other),
    }
}

impl Stage for RegisterStage {
    type Params = RegisterParams;
    const NAME: &'static str = "register";
    const ABOUT: &'static str = "GPR submap registration (engineered correlation, learned model, or oracle) with loop candidates from the estimate";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            port("submap", Submap::TYPE_NAME, false),
            // the estimate, as a feedback input: where the submaps are (association: estimate)
            port("estimate", StateEstimate::TYPE_NAME, true),
            // ground truth: for the oracle association and the oracle method only
            port("truth", PoseStamped::TYPE_NAME, true),
        ])
    }

    fn outputs(_: &Self::Params) -> std::result::Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("registration", Registration::TYPE_NAME)])
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        params.check().map_err(param_error)?;
        let needs_truth = params.association == Association::Truth || params.method == Method::Oracle;
        if needs_truth && ports.input("truth").is_none() {
            return Err(StageError::Params(ParamError {
                path: vec!["method".into()],
                message: "the oracle method and the truth association need the `truth` input (ground-truth poses)"
                    .into(),
            }));
        }
        if params.association == Association::Estimate && ports.input("estimate").is_none() {
            return Err(StageError::Params(ParamError {
                path: vec!["association".into()],
                message:
                    "association `estimate` needs the `estimate` input (the estimator's state, as a feedback input)"
                        .into(),
            }));
        }
        let model = match params.method {
            Method::Learned => Some(
                Model::load(&params.model, &params.head, params.onnxruntime.as_deref()).map_err(StageError::failed)?,
            ),
            _ => None,
        };
        let zeroth_m = match params.method {
            Method::Zeroth => Some(Head::from_json(&params.head).map_err(StageError::failed)?.zeroth_m),
            _ => None,
        };
        if let Some(m) = &model {
            tracing::info!(
                model = %params.model.display(),
                head = %params.head.display(),
                "register: learned model, {} channels, column stride {}, share threshold {}, agreement {}, sigma {} m",
                m.head.channels,
                m.head.column_stride,
                m.head.share_threshold,
                m.head.agreement.map_or("none".to_string(), |a| format!(
                    "{:.3} of the channels within {} m",
                    a.min_fraction, a.tolerance_m
                )),
                m.head.sigma_m
            );
        }
        let stretches = stretch::factors(params.stretch_step, params.stretch_steps).map_err(param_error)?;
        Ok(Self {
            params,
            model,
            stretches,
            zeroth_m,
            out: ports.output("registration")?,
            estimate: Track::new(),
            truth: Track::new(),
            pending: VecDeque::new(),
            references: Vec::new(),
            last_query_odom: None,
            last_primary_ns: i64::MIN,
            counts: Counts::default(),
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        match input.name() {
            "submap" => {
                self.last_primary_ns = self.last_primary_ns.max(input.stamp_ns());
                let m: Submap = input.decode()?;
                if !m.valid {
                    self.counts.invalid += 1;
                } else if m.saliency < self.params.min_saliency {
                    self.counts.not_salient += 1;
                } else {
                    match Entry::from_msg(&m) {
                        Ok(e) => self.pending.push_back(e),
                        Err(why) => self.drops.record(Self::NAME, &input, &why),
                    }
                }
            }
            "truth" => {
                self.last_primary_ns = self.last_primary_ns.max(input.stamp_ns());
                let m: PoseStamped = input.decode()?;
                if let Err(e) = self.truth.insert(m.header.stamp.to_ns(), planar_of(&m.pose)) {
                    self.drops.record(Self::NAME, &input, &e.to_string());
                }
            }
            "estimate" => {
                let m: StateEstimate = input.decode()?;
                if let Err(e) = self
                    .estimate
                    .insert(m.header.stamp.to_ns(), planar_of(&m.world_from_body.pose))
                {
                    self.drops.record(Self::NAME, &input, &e.to_string());
                }
                // Registrations go out on primary inputs only: a feedback message's stamp is
                // older than the output watermark.
                return Ok(());
            }
            _ => return Ok(()),
        }
        self.process_pending(self.last_primary_ns, out, false)
    }

    fn finish(&mut self, out: &mut Outputs) -> std::result::Result<(), StageError> {
        if self.last_primary_ns > i64::MIN {
            self.process_pending(self.last_primary_ns, out, true)?;
        }
        let c = &self.counts;
        tracing::info!(
            sent = c.sent,
            pairs = c.pairs,
            queries = c.queries,
            rejected = c.rejected,
            references = self.references.len(),
            invalid = c.invalid,
            not_salient = c.not_salient,
            never_placed = c.never_placed,
            stretched = c.stretched,
            encoded = c.encoded,
            "register ({}): {} registrations from {} candidate pairs ({} refused by the method's gate)",
            self.params.method.name(),
            c.sent,
            c.pairs,
            c.rejected
        );
        self.drops.report(Self::NAME);
        Ok(())
    }
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

    #[test]
    fn params_are_checked() {
        assert!(RegisterParams::default().check().is_ok());
        let bad = RegisterParams {
            min_score: 2.0,
            ..RegisterParams::default()
        };
        assert!(matches!(bad.check(), Err(Error::Param { key: "min_score", .. })));
        let bad = RegisterParams {
            sigma_m: Some(-1.0),
            ..RegisterParams::default()
        };
        assert!(matches!(bad.check(), Err(Error::Param { key: "sigma_m", .. })));
        for (steps, step) in [(1, f64::NAN), (1, 0.0), (10, 0.03)] {
            let bad = RegisterParams {
                stretch_steps: steps,
                stretch_step: step,
                ..RegisterParams::default()
            };
            assert!(
                matches!(
                    bad.check(),
                    Err(Error::Param {
                        key: "stretch_step",
                        ..
                    })
                ),
                "{steps} x {step}"
            );
        }
        // no search: the step is not used
        let off = RegisterParams {
            stretch_steps: 0,
            stretch_step: f64::NAN,
            ..RegisterParams::default()
        };
        assert!(off.check().is_ok());
        assert_eq!(RegisterParams::default().sigma(Some(0.03)), 0.1);
        let learned = RegisterParams {
            method: Method::Learned,
            ..RegisterParams::default()
        };
        assert_eq!(learned.sigma(Some(0.03)), 0.03);
    }

    #[test]
    fn registration_carries_the_along_track_variance_in_x() {
        let e = |id, stamp_ns| Entry {
            id,
            anchor: Anchor {
                stamp_ns,
                odom: Planar {
                    x_m: 0.0,
                    y_m: 0.0,
                    yaw_rad: 0.0,
                },
                odom_start: Planar {
                    x_m: 0.0,
                    y_m: 0.0,
                    yaw_rad: 0.0,
                },
                start_stamp_ns: stamp_ns,
                backward: false,
            },
            rows: 1,
            cols: 1,
            resolution_m: 0.01,
            pixels: vec![0.0],
            column_stamps_ns: Vec::new(),
            features: None,
        };
        let m = registration(&e(3, 1), &e(9, 2), (10, 20), 0.25, 0.8, 0.1, "engineered");
        assert_eq!((m.reference_submap, m.query_submap), (3, 9));
        assert_eq!((m.reference_stamp.to_ns(), m.query_stamp.to_ns()), (10, 20));
        assert!((m.covariance.0[0] - 0.01).abs() < 1e-15 && m.covariance.0[7] > 1.0);
        assert_eq!(m.reference_from_query.position.x, 0.25);
    }

    /// An entry of `cols` columns of 0.01 m crossed at `t0_ns + step_ns * c`, from a message
    /// as the stage gets it.
    fn timed_entry(cols: usize, t0_ns: i64, step_ns: i64, backward: bool) -> Entry {
        let stamps: Vec<i64> = (0..cols as i64).map(|c| t0_ns + step_ns * c).collect();
        let (start, end) = if backward { (1.0, 0.0) } else { (0.0, 1.0) };
        let m = Submap {
            rows: 1,
            cols: cols as u32,
            resolution_m: 0.01,
            start_distance_m: start,
            end_distance_m: end,
            pixels: std::borrow::Cow::Owned(vec![0.0; cols]),
            column_stamps_ns: std::borrow::Cow::Owned(stamps),
            ..Submap::default()
        };
        Entry::from_msg(&m).expect("a good submap")
    }

    #[test]
    fn a_grid_shift_goes_out_as_the_moments_over_the_middle_of_the_shared_ground() {
        let (r, q) = (timed_entry(100, 1_000, 10, false), timed_entry(100, 5_000, 20, false));
        // query column 0 over reference column 30: they share query columns 0..=69
        assert_eq!(overlap_stamps(&r, &q, 0.3), Some((1_000 + 645, 5_000 + 690)));
        // query column 30 over reference column 0: query columns 30..=99
        assert_eq!(overlap_stamps(&r, &q, -0.3), Some((1_000 + 345, 5_000 + 1290)));
        assert_eq!(overlap_stamps(&r, &q, 0.0), Some((1_000 + 495, 5_000 + 990)));
        // nothing shared
        assert_eq!(overlap_stamps(&r, &q, 1.5), None);
        let none = Entry {
            column_stamps_ns: Vec::new(),
            ..timed_entry(100, 0, 10, false)
        };
        assert_eq!(overlap_stamps(&none, &q, 0.3), None);
        // a backward submap's stamps are put in ground order with its pixels: its column 0
        // (in ground order) is its newest
        let back = timed_entry(100, 1_000, 10, true);
        assert_eq!(back.column_stamps_ns[0], 1_000 + 990);
        assert_eq!(overlap_stamps(&back, &q, 0.3), Some((1_000 + 990 - 645, 5_000 + 690)));
    }

    #[test]
    fn column_stamps_of_the_wrong_length_are_refused() {
        let m = Submap {
            rows: 1,
            cols: 3,
            resolution_m: 0.01,
            pixels: std::borrow::Cow::Owned(vec![0.0; 3]),
            column_stamps_ns: std::borrow::Cow::Owned(vec![0, 1]),
            ..Submap::default()
        };
        let why = Entry::from_msg(&m).expect_err("two stamps for three columns");
        assert!(why.contains("column_stamps_ns: 2 values for 3 columns"), "{why}");
    }
}
