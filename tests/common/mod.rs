//! Helpers shared by the end-to-end test binaries (`e2e` and `distributed`, test targets
//! of gprflow-cli): the `gprflow` binary cargo built for them, the repository they run it in,
//! its output, the Python peer venv, and counts read from stage logs.

// Each test binary uses its own share of these.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The simulated basement run the localisation tests read.
pub const BASEMENT: &str = "recordings/sim/basement-forward_backward.mcap";

/// The `gprflow` binary cargo built for these tests.
pub const GPRFLOW: &str = env!("CARGO_BIN_EXE_gprflow");

/// The repository root, where the tests run `gprflow` (graph files name paths from there).
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Runs `gprflow ARGS` in the repository root to its end.
pub fn gprflow(args: &[&str]) -> Output {
    Command::new(GPRFLOW)
        .current_dir(repo())
        .args(args)
        .output()
        .expect("gprflow runs")
}

/// What a finished command wrote to stderr.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The number after `key=` in a stage's log (its last mention), e.g. the register stage's
/// `stretched=` count.
pub fn logged_count(log: &str, key: &str) -> Option<u64> {
    let pattern = format!(" {key}=");
    let at = log.rfind(&pattern)? + pattern.len();
    let digits: String = log[at..].chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// `program` in the Python peer venv (`tools/peer/setup-venv.sh` makes it): `python`,
/// `evo_ape`, `evo_rpe`.
pub fn peer_venv(program: &str) -> PathBuf {
    repo().join(".venv-peers/bin").join(program)
}
