//! ONNX Runtime, loaded once per process from a library file ([`onnxruntime_library`] says
//! which), `libonnxruntime.so.1.31.1` as `tools/scripts/ensure-onnxruntime.sh` installs it.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

use crate::{Error, Result};

/// The ONNX Runtime library file this crate is built for.
pub const ONNXRUNTIME_LIBRARY: &str = "libonnxruntime.so.1.31.1";

/// Environment variable naming the ONNX Runtime library when no path is given.
pub const ONNXRUNTIME_ENV: &str = "GPRFLOW_ONNXRUNTIME";

/// The ONNX Runtime library to load, and where its path came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OnnxRuntimeLibrary {
    /// The library file (absolute).
    pub path: PathBuf,
    /// Where the path came from: `parameter`, `GPRFLOW_ONNXRUNTIME` or `default`.
    pub source: &'static str,
}

/// The ONNX Runtime library to load: `explicit` when given, else the file named by
/// `GPRFLOW_ONNXRUNTIME` when set, else `.onnxruntime/libonnxruntime.so.1.31.1` under the current
/// directory (where `tools/scripts/ensure-onnxruntime.sh` puts it in a checkout).
pub fn onnxruntime_library(explicit: Option<&Path>) -> OnnxRuntimeLibrary {
    let (path, source) = match explicit {
        Some(p) => (p.to_path_buf(), "parameter"),
        None => match std::env::var_os(ONNXRUNTIME_ENV) {
            Some(p) if !p.is_empty() => (PathBuf::from(p), ONNXRUNTIME_ENV),
            _ => (Path::new(".onnxruntime").join(ONNXRUNTIME_LIBRARY), "default"),
        },
    };
    let path = std::path::absolute(&path).unwrap_or(path);
    OnnxRuntimeLibrary { path, source }
}

/// The process's ONNX Runtime environment and the library it was loaded from.
static RUNTIME: Mutex<Option<(PathBuf, ort::environment::Environment)>> = Mutex::new(None);

/// Loads ONNX Runtime (once per process) and returns its environment.
pub(super) fn runtime(library: &OnnxRuntimeLibrary) -> Result<ort::environment::Environment> {
    let mut loaded = RUNTIME.lock().unwrap_or_else(PoisonError::into_inner);
    // the same file under another name is the same library
    let canonical = std::fs::canonicalize(&library.path).unwrap_or_else(|_| library.path.clone());
    if let Some((path, env)) = loaded.as_ref() {
        if *path != canonical {
            return Err(Error::OnnxRuntime {
                path: library.path.clone(),
                message: format!(
                    "ONNX Runtime is already loaded in this process from {}; one library per process",
                    path.display()
                ),
            });
        }
        return Ok(env.clone());
    }
    if !library.path.is_file() {
        return Err(Error::OnnxRuntime {
            path: library.path.clone(),
            message: format!("no such file (path from {})", library.source),
        });
    }
    let failed = |message: String| Error::OnnxRuntime {
        path: library.path.clone(),
        message,
    };
    let env = ort::init_from(&library.path)
        .map_err(|e| failed(e.to_string()))?
        .with_name("gprflow-register")
        .with_telemetry(false)
        .build()
        .map_err(|e| failed(e.to_string()))?;
    *loaded = Some((canonical, env.clone()));
    Ok(env)
}
