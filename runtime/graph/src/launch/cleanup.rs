//! What a run leaves behind: iceoryx2's shared-memory files, found by the run's prefix and
//! removed.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

/// Where iceoryx2 keeps a run's files: shared memory and its node/service directory.
pub fn run_resource_dirs() -> Vec<PathBuf> {
    vec![PathBuf::from("/dev/shm"), PathBuf::from("/tmp/iceoryx2")]
}

/// Paths of resources left by the run with `prefix` (empty after a clean run).
pub fn leftover_resources(prefix: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for dir in run_resource_dirs() {
        collect_with_prefix(&dir, prefix, &mut found, 3);
    }
    found
}

fn collect_with_prefix(dir: &Path, prefix: &str, out: &mut Vec<PathBuf>, depth: u32) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let path = e.path();
        let name = e.file_name();
        if name.to_string_lossy().starts_with(prefix) {
            out.push(path);
        } else if depth > 0 && path.is_dir() {
            collect_with_prefix(&path, prefix, out, depth - 1);
        }
    }
}

/// Removes what processes of the run with `prefix` left behind: first through iceoryx2's
/// own dead-node cleanup, then any file still carrying the run's prefix (the prefix is
/// unique to the run, so nothing else is touched). iceoryx2 keeps one global management
/// segment per prefix on purpose; it is removed silently. Returns what else had to be
/// removed: resources of processes that did not exit cleanly.
pub fn cleanup_run(prefix: &str) -> Vec<String> {
    let stop = Arc::new(AtomicBool::new(false));
    if let Ok(t) = gprflow_bus::iox::IoxTransport::new("gprflow_cleanup", prefix, stop) {
        t.cleanup_dead_nodes();
    }
    let mut removed = Vec::new();
    for path in leftover_resources(prefix) {
        let gone = if path.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        // a node's own directory (named by node id) is left empty: remove it too
        if let Some(parent) = path
            .parent()
            .filter(|p| p.parent().is_some_and(|g| g.ends_with("nodes")))
        {
            let _ = std::fs::remove_dir(parent);
        }
        let expected = path.extension().is_some_and(|e| e == "global_mgmt");
        if gone.is_ok() && !expected {
            removed.push(path.display().to_string());
        }
    }
    removed
}
