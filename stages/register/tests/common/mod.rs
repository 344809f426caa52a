//! What the register stage's integration tests share: the repository root, the ONNX Runtime
//! library and the fixtures' raw f32 files.

use std::path::{Path, PathBuf};

use gprflow_register::learned::{ONNXRUNTIME_ENV, ONNXRUNTIME_LIBRARY};

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The ONNX Runtime library, or a failure saying how to install it.
pub fn ort_library() -> PathBuf {
    let lib = match std::env::var_os(ONNXRUNTIME_ENV) {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => repo_root().join(".onnxruntime").join(ONNXRUNTIME_LIBRARY),
    };
    assert!(
        lib.is_file(),
        "ONNX Runtime library {} not found: run tools/scripts/ensure-onnxruntime.sh (or set {ONNXRUNTIME_ENV})",
        lib.display()
    );
    lib
}

/// A raw little-endian f32 file.
pub fn read_f32(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(bytes.len() % 4, 0, "{}", path.display());
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}
