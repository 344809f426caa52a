//! The `register` stage's parameters: the graph file's `params`, their defaults and checks.

use std::path::PathBuf;

use crate::candidates::CandidateGates;
use crate::closer::{Association, CloserParams, Method, Stamps};
use crate::engineered::EngineeredParams;
use gprflow_params::{ParamError, finite, positive};

use crate::stretch;

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
    /// is there to drop (docs/localisation.md).
    pub stretch_steps: usize,
    /// Relative stretch between two neighbouring factors of the search (default 0.015).
    pub stretch_step: f64,
    /// Also publish every candidate pair judged, registered or refused and why, on the
    /// `attempt` output (`RegistrationAttempt`), for `gprflow eval` (default false).
    pub diagnostics: bool,
    /// References whose pixels the engineered method keeps in memory, the newest (default
    /// 256, about 77 m of travel at the default spacing); older references' pixels move to a
    /// temporary file and are read back when a query finds them as loop candidates, so the
    /// stage's memory does not grow with the run's length by their pixels. The learned method
    /// keeps only each reference's features.
    pub references_in_memory: usize,
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
            diagnostics: false,
            references_in_memory: 256,
        }
    }
}

impl RegisterParams {
    /// Checks every value; the ports' part (truth, estimate) is the node's.
    pub(super) fn check(&self) -> gprflow_params::Result {
        self.candidates.check()?;
        crate::check_shift_search(self.engineered.max_shift_m, self.engineered.min_overlap)
            .map_err(|e| e.within("engineered"))?;
        stretch::check_factors(self.stretch_step, self.stretch_steps)?;
        positive("reference_spacing_m", self.reference_spacing_m)?;
        positive("query_spacing_m", self.query_spacing_m)?;
        positive("max_track_gap_s", self.max_track_gap_s)?;
        if let Some(s) = self.sigma_m {
            positive("sigma_m", s)?;
        }
        if !(self.min_score.is_finite() && (-1.0..=1.0).contains(&self.min_score)) {
            return Err(ParamError::new(
                "min_score",
                format!("must be a correlation in -1..=1, got {}", self.min_score),
            ));
        }
        finite("min_saliency", f64::from(self.min_saliency))
    }

    /// The loop closer's share of the parameters.
    pub(super) fn closer(&self) -> CloserParams {
        CloserParams {
            association: self.association,
            candidates: self.candidates.clone(),
            sigma_m: self.sigma_m,
            reference_spacing_m: self.reference_spacing_m,
            query_spacing_m: self.query_spacing_m,
            max_track_gap_s: self.max_track_gap_s,
            stamps: self.stamps,
            references_in_memory: self.references_in_memory,
        }
    }
}
