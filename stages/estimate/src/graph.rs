//! The nonlinear factor graph.

use std::sync::Arc;

use crate::Result;
use crate::factor::Factor;
use crate::values::Values;

/// Index of a factor in a [`FactorGraph`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FactorId(pub usize);

/// A list of factors over the variables of a [`Values`].
/// Factors are shared (`Arc`) so that a snapshot for a background solve costs a few pointer copies.
#[derive(Debug, Default, Clone)]
pub struct FactorGraph {
    factors: Vec<Arc<dyn Factor>>,
}

impl FactorGraph {
    /// No factors.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a factor.
    pub fn add(&mut self, f: impl Factor + 'static) -> FactorId {
        self.factors.push(Arc::new(f));
        FactorId(self.factors.len() - 1)
    }

    /// Adds a shared factor.
    pub fn add_shared(&mut self, f: Arc<dyn Factor>) -> FactorId {
        self.factors.push(f);
        FactorId(self.factors.len() - 1)
    }

    /// Number of factors.
    #[must_use]
    pub fn len(&self) -> usize {
        self.factors.len()
    }

    /// True without factors.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.factors.is_empty()
    }

    /// All factors in insertion order.
    #[must_use]
    pub fn factors(&self) -> &[Arc<dyn Factor>] {
        &self.factors
    }

    /// Total error `sum_f loss_f` (GTSAM's `NonlinearFactorGraph::error`).
    ///
    /// # Errors
    /// A factor whose variables are missing or of the wrong kind.
    pub fn error(&self, values: &Values) -> Result<f64> {
        self.factors.iter().map(|f| f.error(values)).sum()
    }
}
