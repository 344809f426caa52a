//! The learned registration model (seed 000 §4.5-4.6, "Ground Encoding"), inference side: the
//! contract is `tools/train/SPEC.md`, which training (PyTorch) and this module compute alike.
//!
//! - [`Encoder`]: the ONNX encoder (ONNX Runtime through `ort`, one thread) turns a submap in
//!   ground order into features `K x h x w` ([`Features`]); the submap is standardised over the
//!   whole image first (f64 mean and population std, stored as f32), then goes through the
//!   front end the model's metadata names ([`crate::front_end`]).
//! - [`correlate`] / [`Correlator`]: the spatial correlation (§4.5.3) of reference and query
//!   features, per channel the Pearson correlation of the shared block for every integer column
//!   shift, its argmax refined by a parabola: the vector `v = [tau_1 .. tau_K, m_1 .. m_K]`.
//! - [`Head`]: the linear or nonlinear regression head (JSON) mapping `v` to the shift, m.
//! - [`Model`]: the three together; [`Model::register`] answers "do these two share features"
//!   (`mean m_k >= share_threshold`, §4.5.2) and, when they do, the shift and its variance.
//!
//! Putting a submap in ground order (columns reversed when it was driven backwards) is the
//! caller's job.
//!
//! ONNX Runtime is loaded once per process from a library file ([`onnxruntime_library`] says
//! which), `libonnxruntime.so.1.31.1` as `tools/scripts/ensure-onnxruntime.sh` installs it.

mod correlation;
mod encoder;
mod head;
mod runtime;

pub use correlation::{CorrVector, CorrelationParams, Correlator, correlate};
pub use encoder::{ENCODER_INPUT, ENCODER_OUTPUT, Encoder, Features, STANDARDISE_EPSILON};
pub use head::{Activation, Agreement, HEAD_FORMAT, HEAD_VERSION, Head, HeadKind, HeadLayer};
pub use runtime::{ONNXRUNTIME_ENV, ONNXRUNTIME_LIBRARY, OnnxRuntimeLibrary, onnxruntime_library};

use std::path::Path;

use crate::SubmapView;
use crate::{Error, Result};

/// A registration by the learned model.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedMatch {
    /// Along-body-x position of the query's ground-order column 0 over the reference, m.
    pub shift_m: f64,
    /// `mean_k m_k`, in -1..=1: how much the two share features.
    pub share_score: f64,
    /// The fraction of channels agreeing with `shift_m` (1 when the head has no agreement
    /// check).
    pub agreement: f64,
    /// `sigma_m^2`, m².
    pub variance_m2: f64,
    /// The correlation vector the head took, `[tau_1 .. tau_K, m_1 .. m_K]`.
    pub corr: Vec<f64>,
}

/// Encoder, head and correlation buffers: the learned registration model.
#[derive(Debug)]
pub struct Model {
    /// The ONNX encoder.
    pub encoder: Encoder,
    /// The head and the model's constants.
    pub head: Head,
    correlator: Correlator,
}

impl Model {
    /// Loads the encoder (`onnx`) and the head (`head_json`); `ort_library` as in
    /// [`Encoder::load`].
    ///
    /// # Errors
    /// See [`Encoder::load`] and [`Head::from_json`]; [`Error::Head`] (`encoder_crc32`) when
    /// the head names another encoder file than `onnx`.
    pub fn load(onnx: &Path, head_json: &Path, ort_library: Option<&Path>) -> Result<Model> {
        let head = Head::from_json(head_json)?;
        if let Some(expected) = head.encoder_crc32 {
            let bytes = std::fs::read(onnx).map_err(|source| Error::Io {
                path: onnx.to_path_buf(),
                source,
            })?;
            let found = crc32fast::hash(&bytes);
            if found != expected {
                return Err(Error::Head {
                    file: head_json.to_path_buf(),
                    field: "encoder_crc32".into(),
                    message: format!(
                        "{expected:08x}, but {} has {found:08x}: the head was fitted on another encoder (give the model's encoder and head together)",
                        onnx.display()
                    ),
                });
            }
        }
        let encoder = Encoder::load(onnx, ort_library)?;
        Ok(Model {
            encoder,
            head,
            correlator: Correlator::default(),
        })
    }

    /// The features of `submap` (ground order, not standardised), checked against the head:
    /// `K` channels and `ceil(cols / column_stride)` columns.
    ///
    /// # Errors
    /// See [`Encoder::encode_into`]; [`Error::Onnx`] when the features do not fit the head.
    pub fn encode(&mut self, submap: &SubmapView<'_>) -> Result<Features> {
        let mut features = Features::default();
        self.encode_into(submap, &mut features)?;
        Ok(features)
    }

    /// [`Model::encode`] into `features`, whose buffer is reused.
    ///
    /// # Errors
    /// See [`Model::encode`].
    pub fn encode_into(&mut self, submap: &SubmapView<'_>, features: &mut Features) -> Result<()> {
        self.encoder.encode_into(submap, features)?;
        let cols = submap.cols.div_ceil(self.head.column_stride);
        if features.channels != self.head.channels || features.cols != cols {
            return Err(Error::Onnx {
                model: self.encoder.model_path().to_path_buf(),
                message: format!(
                    "features {} x {} x {} for a {} x {} submap, the head expects {} channels and {cols} columns (stride {})",
                    features.channels,
                    features.rows,
                    features.cols,
                    submap.rows,
                    submap.cols,
                    self.head.channels,
                    self.head.column_stride
                ),
            });
        }
        Ok(())
    }

    /// The correlation vector of `query` over `reference` (features of submaps with
    /// `resolution_m` per column) with the head's parameters.
    ///
    /// # Errors
    /// See [`Correlator::correlate`]; features with other than the head's channel count.
    pub fn correlate(&mut self, reference: &Features, query: &Features, resolution_m: f64) -> Result<CorrVector> {
        if reference.channels != self.head.channels {
            return Err(Error::Shape(format!(
                "reference features have {} channels, the head {}",
                reference.channels, self.head.channels
            )));
        }
        self.correlator
            .correlate(reference, query, &self.head.correlation_params(resolution_m))
    }

    /// Registers `query` on `reference`: `None` when they share no features
    /// (`mean_k m_k < share_threshold`, or, where the head has an [`Agreement`] check, too few
    /// channels agree with the head's shift), else the head's shift and `sigma_m^2`.
    ///
    /// # Errors
    /// See [`Model::correlate`].
    pub fn register(
        &mut self,
        reference: &Features,
        query: &Features,
        resolution_m: f64,
    ) -> Result<Option<LearnedMatch>> {
        let (found, refusal) = self.assess(reference, query, resolution_m)?;
        Ok(refusal.is_none().then_some(found))
    }

    /// What [`Model::register`] decides, with its numbers either way: the match (shift, share
    /// score, agreement) and why it was refused, if it was.
    ///
    /// # Errors
    /// See [`Model::correlate`].
    pub fn assess(
        &mut self,
        reference: &Features,
        query: &Features,
        resolution_m: f64,
    ) -> Result<(LearnedMatch, Option<Refusal>)> {
        let corr = self.correlate(reference, query, resolution_m)?;
        Ok(self.decide(corr))
    }

    /// [`Model::assess`] of the query seen several ways (`queries`: its features at each
    /// travel-time stretch the stage tries, [`crate::stretch`]) over `reference`: the one whose
    /// share score (mean channel peak) is highest decides, refused or not. Returns the decision
    /// and the index of that query.
    ///
    /// # Errors
    /// See [`Model::correlate`]; [`Error::Shape`] when `queries` is empty.
    pub fn assess_best(
        &mut self,
        reference: &Features,
        queries: &[Features],
        resolution_m: f64,
    ) -> Result<(LearnedMatch, Option<Refusal>, usize)> {
        let mut best: Option<(CorrVector, usize)> = None;
        for (i, query) in queries.iter().enumerate() {
            let corr = self.correlate(reference, query, resolution_m)?;
            if best.as_ref().is_none_or(|(b, _)| corr.share_score() > b.share_score()) {
                best = Some((corr, i));
            }
        }
        let Some((corr, i)) = best else {
            return Err(Error::Shape("no query features to register".into()));
        };
        let (found, refusal) = self.decide(corr);
        Ok((found, refusal, i))
    }

    /// The head's shift and the two checks on one correlation vector.
    fn decide(&self, corr: CorrVector) -> (LearnedMatch, Option<Refusal>) {
        let share_score = corr.share_score();
        let shift_m = self.head.predict(&corr.values);
        let (agreement, agrees) = match self.head.agreement {
            Some(check) => {
                let fraction = check.fraction(&corr, shift_m);
                (fraction, fraction >= check.min_fraction)
            }
            None => (1.0, true),
        };
        let refusal = if share_score < self.head.share_threshold {
            Some(Refusal::NoSharedFeatures)
        } else if !agrees {
            Some(Refusal::ChannelsDisagree)
        } else {
            None
        };
        let found = LearnedMatch {
            shift_m,
            share_score,
            agreement,
            variance_m2: self.head.sigma_m * self.head.sigma_m,
            corr: corr.values,
        };
        (found, refusal)
    }
}

/// Why the learned model refused a pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// `mean_k m_k < share_threshold`.
    NoSharedFeatures,
    /// Fewer than the agreement check's `min_fraction` of the channels agree with the shift.
    ChannelsDisagree,
}

impl Refusal {
    /// The refusal in snake_case words, as the diagnostics output names it.
    pub fn name(self) -> &'static str {
        match self {
            Self::NoSharedFeatures => "no_shared_features",
            Self::ChannelsDisagree => "channels_disagree",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_can_move_to_another_thread() {
        fn send<T: Send>() {}
        send::<Model>();
        send::<Correlator>();
    }
}
