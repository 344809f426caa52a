//! gprflow runtime in one crate, for tools and for users' own stages: messages, bus, stage
//! SDK, recordings, graph files, launcher and evaluation.
//!
//! Each part is its own crate under `runtime/`, layered so that lower layers never depend on
//! higher ones: `gprflow-geometry` (planar poses) and `gprflow-msg` <- `gprflow-bus` (zenoh behind its `zenoh` feature) <-
//! `gprflow-stage` <- `gprflow-record` <- `gprflow-graph` (graph files, [`launch`],
//! [`bridge`]); `gprflow-eval` (with [`diff`]) reads recordings. Stages depend on the crates
//! they use (messages and the stage SDK), not on this one.

pub use gprflow_bus as bus;
pub use gprflow_eval as eval;
pub use gprflow_eval::diff;
pub use gprflow_geometry as geometry;
pub use gprflow_graph as graph;
pub use gprflow_graph::{bridge, launch};
pub use gprflow_msg as msg;
pub use gprflow_record as record;
pub use gprflow_stage as stage;
