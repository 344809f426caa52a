//! One [`Matcher`] per [`Method`]: how a reference and a query are matched, and whether the
//! method's own gate takes the pair.
//!
//! - [`Engineered`]: the Pearson correlation over the along-track shift
//!   ([`crate::engineered`]), gated on its peak.
//! - [`Learned`]: the learned model ([`crate::learned`]) with the travel-time stretch search
//!   ([`crate::stretch`]), gated on its "shared features" checks.
//! - [`Oracle`]: the ground-truth transform between the anchors (evaluation only).
//! - [`Zeroth`]: a constant shift, the zeroth-order model (evaluation only).

use gprflow_geometry::Track;

use super::{Counts, Keyed, Method};
use crate::engineered::{EngineeredParams, register_with as engineered_register};
use crate::learned::{Correlator, Features, Model, Refusal};
use crate::{Error, Result, SubmapView, stretch};

/// What a matcher may look at besides the two submaps.
#[derive(Debug, Clone, Copy)]
pub struct Context<'a> {
    /// The ground truth (empty unless the stage has it).
    pub truth: &'a Track,
    /// Longest gap between two poses of a track that is interpolated, ns.
    pub max_gap_ns: i64,
}

/// A matcher's verdict on a pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Outcome {
    /// Matched: the query's ground-order column 0 lies `shift_m` along the reference's.
    Matched {
        /// The shift, m.
        shift_m: f64,
        /// The method's score.
        score: f64,
        /// The travel-time stretch of the query that matched (1 but for the learned search).
        stretch: f64,
    },
    /// The method's gate refused the pair (or the two cannot be compared).
    Refused {
        /// Why, in snake_case words (`low_score`, `shape`, `no_shared_features`, ...).
        why: &'static str,
        /// The shift the method found before refusing, m (NaN when none).
        shift_m: f64,
        /// Its score (NaN when none).
        score: f64,
        /// The stretch of the query that was judged.
        stretch: f64,
    },
}

impl Outcome {
    /// Refused before the method found any shift.
    pub fn refused(why: &'static str) -> Self {
        Self::Refused {
            why,
            shift_m: f64::NAN,
            score: f64::NAN,
            stretch: 1.0,
        }
    }
}

/// How a candidate pair is matched: one implementation per [`Method`].
pub trait Matcher: std::fmt::Debug + Send {
    /// The method.
    fn method(&self) -> Method;

    /// The along-track sigma of the method's matches, m.
    fn sigma_m(&self) -> f64;

    /// Whether the shift is found on the submap grid (in wheel metres), so that it can go
    /// out as overlap stamps instead.
    fn on_grid(&self) -> bool {
        true
    }

    /// Whether the method needs the ground truth to reach a query before matching it.
    fn needs_truth(&self) -> bool {
        false
    }

    /// Whether [`Matcher::assess`] reads a reference's pixels (a reference kept for a method
    /// that does not keeps only what [`Matcher::prepare`] made of them).
    fn reference_needs_pixels(&self) -> bool {
        true
    }

    /// Readies a submap for matching, as a query with loop candidates or as it is kept as a
    /// reference; called for each, at most once doing work.
    ///
    /// # Errors
    /// The method's (the learned model's encoder).
    fn prepare(&mut self, _keyed: &mut Keyed, _counts: &mut Counts) -> Result<()> {
        Ok(())
    }

    /// Readies a prepared query for its candidate pairs, before the first [`Matcher::assess`].
    ///
    /// # Errors
    /// The method's (the learned model's encoder).
    fn begin_query(&mut self, _query: &Keyed, _counts: &mut Counts) -> Result<()> {
        Ok(())
    }

    /// Matches `query` with `reference`.
    ///
    /// # Errors
    /// The method's, but for two submaps that cannot be compared (refused).
    fn assess(&mut self, reference: &Keyed, query: &Keyed, context: &Context<'_>) -> Result<Outcome>;
}

/// Pearson correlation of the submaps over the along-track shift (eq. 4.2-4.3).
#[derive(Debug, Clone)]
pub struct Engineered {
    /// The shift search.
    params: EngineeredParams,
    /// Smallest peak correlation accepted.
    min_score: f64,
    /// The correlation's buffers, reused from pair to pair.
    correlator: Correlator,
}

impl Engineered {
    /// The matcher with its shift search and the smallest peak correlation it accepts.
    pub fn new(params: EngineeredParams, min_score: f64) -> Self {
        Self {
            params,
            min_score,
            correlator: Correlator::default(),
        }
    }
}

impl Matcher for Engineered {
    fn method(&self) -> Method {
        Method::Engineered
    }

    fn sigma_m(&self) -> f64 {
        0.1
    }

    fn assess(&mut self, r: &Keyed, q: &Keyed, _: &Context<'_>) -> Result<Outcome> {
        let m = match engineered_register(&mut self.correlator, &r.view(), &q.view(), &self.params) {
            Ok(m) => m,
            // different shapes (a recording with two radars, say): not comparable
            Err(Error::Shape(why)) => {
                tracing::debug!(reference = r.id, query = q.id, "not registered: {why}");
                return Ok(Outcome::refused("shape"));
            }
            Err(e) => return Err(e),
        };
        Ok(match m {
            Some(m) if m.score >= self.min_score => Outcome::Matched {
                shift_m: m.shift_m,
                score: m.score,
                stretch: 1.0,
            },
            Some(m) => Outcome::Refused {
                why: "low_score",
                shift_m: m.shift_m,
                score: m.score,
                stretch: 1.0,
            },
            None => Outcome::refused("no_overlap"),
        })
    }
}

/// The learned model with the travel-time stretch search.
#[derive(Debug)]
pub struct Learned {
    model: Model,
    /// The travel-time stretches, 1 among them.
    stretches: Vec<f64>,
    /// The current query's features at each stretch (the order of `stretches`).
    queries: Vec<Features>,
}

impl Learned {
    /// The matcher of `model`, searching `stretches` ([`stretch::factors`]).
    pub fn new(model: Model, stretches: Vec<f64>) -> Self {
        Self {
            model,
            stretches,
            queries: Vec::new(),
        }
    }
}

impl Matcher for Learned {
    fn method(&self) -> Method {
        Method::Learned
    }

    /// A reference is matched on the features encoded when it was kept.
    fn reference_needs_pixels(&self) -> bool {
        false
    }

    fn sigma_m(&self) -> f64 {
        self.model.head.sigma_m
    }

    /// Encodes `keyed` unless it is already encoded.
    fn prepare(&mut self, keyed: &mut Keyed, counts: &mut Counts) -> Result<()> {
        if keyed.features.is_none() {
            keyed.features = Some(self.model.encode(&keyed.view())?);
            counts.encoded += 1;
        }
        Ok(())
    }

    /// The query's features at every stretch of the search.
    fn begin_query(&mut self, q: &Keyed, counts: &mut Counts) -> Result<()> {
        self.queries.clear();
        let Some(unstretched) = q.features.as_ref() else {
            return Ok(());
        };
        let mut pixels = Vec::new();
        for &factor in &self.stretches {
            if factor == 1.0 {
                self.queries.push(unstretched.clone());
                continue;
            }
            stretch::stretch_rows(&q.view(), factor, &mut pixels)?;
            let view = SubmapView {
                pixels: &pixels,
                ..q.view()
            };
            self.queries.push(self.model.encode(&view)?);
            counts.encoded += 1;
        }
        Ok(())
    }

    fn assess(&mut self, r: &Keyed, q: &Keyed, _: &Context<'_>) -> Result<Outcome> {
        let Some(fr) = r.features.as_ref() else {
            return Ok(Outcome::refused("no_reference_features"));
        };
        if self.queries.is_empty() {
            return Ok(Outcome::refused("no_query_features"));
        }
        let (m, refusal, at) = self.model.assess_best(fr, &self.queries, q.resolution_m)?;
        let stretch = self.stretches.get(at).copied().unwrap_or(1.0);
        tracing::trace!(
            reference = r.id,
            query = q.id,
            shift_m = m.shift_m,
            share_score = m.share_score,
            agreement = m.agreement,
            stretch,
            corr = ?m.corr,
            "learned: {}",
            refusal.map_or("registered", Refusal::name)
        );
        if let Some(why) = refusal {
            return Ok(Outcome::Refused {
                why: why.name(),
                shift_m: m.shift_m,
                score: m.share_score,
                stretch,
            });
        }
        Ok(Outcome::Matched {
            shift_m: m.shift_m,
            score: m.share_score,
            stretch,
        })
    }
}

/// The ground-truth transform between the two anchors (evaluation only).
#[derive(Debug, Clone, Copy, Default)]
pub struct Oracle;

impl Matcher for Oracle {
    fn method(&self) -> Method {
        Method::Oracle
    }

    fn reference_needs_pixels(&self) -> bool {
        false
    }

    fn sigma_m(&self) -> f64 {
        0.02
    }

    fn on_grid(&self) -> bool {
        false
    }

    fn needs_truth(&self) -> bool {
        true
    }

    fn assess(&mut self, r: &Keyed, q: &Keyed, context: &Context<'_>) -> Result<Outcome> {
        let gap = context.max_gap_ns;
        let (Some(a), Some(b)) = (
            context.truth.at(r.anchor.stamp_ns, gap),
            context.truth.at(q.anchor.stamp_ns, gap),
        ) else {
            return Ok(Outcome::refused("no_truth"));
        };
        Ok(Outcome::Matched {
            shift_m: a.relative(&b).0,
            score: 1.0,
            stretch: 1.0,
        })
    }
}

/// The zeroth-order model of Table 4.1: always the same shift (evaluation only).
#[derive(Debug, Clone, Copy)]
pub struct Zeroth {
    /// The shift, m (the head's `zeroth_m`).
    pub shift_m: f64,
}

impl Matcher for Zeroth {
    fn method(&self) -> Method {
        Method::Zeroth
    }

    fn reference_needs_pixels(&self) -> bool {
        false
    }

    fn sigma_m(&self) -> f64 {
        0.02
    }

    fn assess(&mut self, _: &Keyed, _: &Keyed, _: &Context<'_>) -> Result<Outcome> {
        Ok(Outcome::Matched {
            shift_m: self.shift_m,
            score: 0.0,
            stretch: 1.0,
        })
    }
}
