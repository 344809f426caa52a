//! [`Drops`]: the count of unusable messages a stage skipped.

use std::fmt::Display;

use super::Input;

/// Counts the messages a stage drops as unusable (non-finite values, wrong sizes, stamps going
/// back): the first [`Drops::LOGGED`] are logged with their input, topic and seq, the total at
/// the end. A bad message is reported, never a reason to stop the stage.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Drops {
    count: u64,
}

impl Drops {
    /// Drops logged one by one; later ones are only counted.
    pub const LOGGED: u64 = 10;

    /// No drops yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Counts one dropped message of `input`, logging it (with `stage` and `why`) while few.
    pub fn record(&mut self, stage: &str, input: &Input<'_>, why: &dyn Display) {
        self.count += 1;
        if self.count <= Self::LOGGED {
            tracing::warn!(
                input = input.name(),
                topic = input.topic(),
                seq = input.seq(),
                "{stage}: dropped: {why}"
            );
        }
    }

    /// Messages dropped so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Logs the total, if any (from [`Stage::finish`](super::Stage::finish)).
    pub fn report(&self, stage: &str) {
        if self.count > 0 {
            tracing::warn!(messages = self.count, "{stage}: messages dropped as unusable");
        }
    }
}
