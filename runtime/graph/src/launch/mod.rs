//! The launcher: turns a validated [`Graph`](crate::Graph) into one process per node,
//! supervises them, and cleans up.
//!
//! [`plan`] is pure: it wires every node's inputs and outputs to topics (`node/output`),
//! counts each topic's consumers (for the start-up handshake), adds the recorder, and gives
//! the run a unique iceoryx2 resource prefix. [`launch`] writes each node's
//! [`NodeSpec`](gprflow_stage::NodeSpec) to a file, starts `gprflow stage <kind> --spec FILE`
//! (or the user's executable with the same argument), forwards their logs, and waits. When a
//! process fails, the others are asked to stop (SIGTERM, then SIGKILL after a grace period)
//! and the failure is reported with the tail of its stderr. Children die with the launcher
//! (`PR_SET_PDEATHSIG`). Afterwards nothing of the run is left in shared memory.

mod cleanup;
mod plan;
mod supervise;

use std::path::PathBuf;
use std::time::Duration;

pub use cleanup::{cleanup_run, leftover_resources, run_resource_dirs};
pub use gprflow_stage::PROGRESS_TAG;
pub use plan::{ExternalTopic, Plan, plan};
pub use supervise::{LaunchEvent, LaunchObserver, LaunchReport, NodeOutcome, launch};

/// Name of the recorder node the launcher adds.
pub const RECORDER_NODE: &str = "__record";
const STDERR_TAIL_LINES: usize = 40;
const POLL: Duration = Duration::from_millis(20);

/// Errors of the launcher.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    /// The graph cannot run as asked.
    #[error("{0}")]
    Plan(String),
    /// A file or process operation failed.
    #[error("{what}: {source}")]
    Io {
        /// What we were doing.
        what: String,
        /// The error.
        source: std::io::Error,
    },
}

/// How to launch.
#[derive(Debug, Clone)]
pub struct LaunchOptions {
    /// The `gprflow` executable that runs built-in stages.
    pub exe: PathBuf,
    /// Record to this file (all topics unless the graph's `record:` names some).
    pub record: Option<PathBuf>,
    /// Run only this host's nodes.
    pub host: Option<String>,
    /// Frames each topic buffers per subscriber.
    pub buffer: usize,
    /// How long a publisher waits for its subscribers at start-up.
    pub handshake_timeout: Duration,
    /// With `--host`: how long the bridge waits for the other hosts to come up.
    pub remote_timeout: Duration,
    /// How long stopping processes get after SIGTERM before SIGKILL.
    pub stop_grace: Duration,
    /// Log filter handed to built-in stages (`--log`).
    pub log_filter: Option<String>,
    /// Run on this named bus instead of a bus of the run's own, so that processes outside
    /// the run (`gprflow replay`, `gprflow record`) see its topics.
    pub bus: Option<String>,
    /// Source nodes not started: their topics come from another process on the bus.
    pub external: Vec<String>,
    /// Record these topics (glob patterns) instead of those the graph's `record:` names.
    pub record_topics: Vec<String>,
}

impl LaunchOptions {
    /// Defaults for running `exe`'s stages.
    pub fn new(exe: PathBuf) -> Self {
        Self {
            exe,
            record: None,
            host: None,
            buffer: gprflow_bus::DEFAULT_BUFFER,
            handshake_timeout: Duration::from_secs(30),
            remote_timeout: Duration::from_secs(120),
            stop_grace: Duration::from_secs(5),
            log_filter: None,
            bus: None,
            external: Vec::new(),
            record_topics: Vec::new(),
        }
    }
}
