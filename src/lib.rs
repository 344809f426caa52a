//! gprflow runtime: messages, bus, stage SDK, graph files, launcher and MCAP I/O.

pub mod bridge;
pub mod bus;
pub mod diff;
pub mod eval;
pub mod graph;
pub mod launch;
pub mod msg;
pub mod record;
pub mod stage;
