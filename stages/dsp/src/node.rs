//! The stage adapter (being written).
