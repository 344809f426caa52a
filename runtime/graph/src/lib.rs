//! Graph files: YAML pipelines, validated before any process starts.
//!
//! A graph file names its nodes (a stage kind or a user's executable each), wires outputs
//! to inputs, optionally places nodes on hosts and lists topics to record:
//!
//! ```yaml
//! name: toy
//! inputs: { count: "100" }                  # variables, overridable with --set count=5
//! nodes:
//!   gen:  { stage: toy_source, params: { count: "${count}" } }
//!   gain: { stage: toy_gain, inputs: { trace: gen/trace }, params: { gain: 2.0 } }
//! record: { topics: ["*"] }
//! ```
//!
//! [`load`] reads, parses and checks one: unknown fields, stages and parameters, inputs
//! wired to missing outputs or to another message type, duplicate names, nodes on no host,
//! cycles without a feedback input. Every [`GraphError`] names the file, line, column and
//! key path. [`json_schema`] gives the file format's JSON schema (checked in as
//! `graphs/graph.schema.json`, for editors).
//!
//! [`launch`] turns a checked graph into processes; [`bridge`] carries its topics across
//! hosts over zenoh.

pub mod bridge;
mod check;
mod error;
mod file;
pub mod launch;
mod model;
mod positions;
mod vars;

#[cfg(test)]
mod tests;

use std::path::Path;

pub use error::{GraphError, GraphErrorKind, Location, Position, UnknownErrorKind};
pub use file::RecordDecl;
pub use gprflow_bus::{TlsDecl, ZenohDecl, glob_matches};
pub use model::{Graph, Host, Input, Node, NodeKind};

use check::Source;
use positions::{Positions, ScanProblem};
use serde_saphyr::MessageFormatter as _;

use gprflow_stage::StageCatalog;

/// Reads, parses and checks the graph file at `path`.
///
/// `overrides` are the command line's `--set name=value` pairs; each must name a variable
/// declared under `inputs:`. Relative paths in the file are kept as written.
///
/// # Errors
/// [`GraphError::Io`] when the file cannot be read, else as [`parse`].
pub fn load(path: &Path, overrides: &[(String, String)], catalog: &StageCatalog) -> Result<Graph, GraphError> {
    let text = std::fs::read_to_string(path).map_err(|source| GraphError::Io {
        file: path.to_owned(),
        source,
    })?;
    parse(&text, path, overrides, catalog)
}

/// Parses and checks the graph in `text`, read from `file` (used in messages and kept in
/// the [`Graph`]).
///
/// # Errors
/// The first problem found, with its line, column and key path.
pub fn parse(
    text: &str,
    file: &Path,
    overrides: &[(String, String)],
    catalog: &StageCatalog,
) -> Result<Graph, GraphError> {
    let positions = Positions::scan(text).map_err(|problem| scan_error(file, problem))?;
    let source = Source {
        file,
        text,
        positions: &positions,
    };
    let decl: file::GraphFile = serde_saphyr::from_str(text).map_err(|e| structure_error(&source, &e))?;
    check::check(decl, &source, overrides, catalog)
}

/// The JSON schema of the graph file format, generated from the types that read it.
pub fn json_schema() -> schemars::Schema {
    schemars::schema_for!(file::GraphFile)
}

fn scan_error(file: &Path, problem: ScanProblem) -> GraphError {
    match problem {
        ScanProblem::Syntax { position, message } => GraphError::Syntax {
            at: location(file, Some(position), String::new()),
            message,
        },
        ScanProblem::DuplicateKey { path, key, at, first } => GraphError::DuplicateKey {
            at: location(file, Some(at), path.join(".")),
            key,
            first,
        },
    }
}

/// A deserialiser error: the file is YAML, but not a graph file.
fn structure_error(source: &Source<'_>, error: &serde_saphyr::Error) -> GraphError {
    let (at, message) = locate(source.file, source.positions, error);
    GraphError::Structure { at, message }
}

/// Where a YAML deserialiser error is (file, line, column, key path) and its message, for
/// any YAML file read with `serde_saphyr` (graph files, simulator scenarios).
pub fn locate_yaml_error(file: &Path, text: &str, error: &serde_saphyr::Error) -> (Box<Location>, String) {
    match Positions::scan(text) {
        Ok(positions) => locate(file, &positions, error),
        Err(problem) => match scan_error(file, problem) {
            GraphError::Syntax { at, message } => (at, message),
            other => (location(file, None, String::new()), other.to_string()),
        },
    }
}

/// Where the value at a dotted key path (`runs.0.trajectory.speed_mps`) is in a YAML text,
/// or the nearest enclosing node that is there; for errors found after deserialising.
pub fn locate_yaml_key(file: &Path, text: &str, key_path: &str) -> Box<Location> {
    let path: Vec<String> = key_path.split('.').map(str::to_owned).collect();
    let position = Positions::scan(text).ok().and_then(|p| p.value(&path));
    location(file, position, key_path.to_owned())
}

fn locate(file: &Path, positions: &Positions, error: &serde_saphyr::Error) -> (Box<Location>, String) {
    let error = error.without_snippet();
    let position = error
        .location()
        .filter(|location| location.line() > 0)
        .map(|location| Position {
            line: location.line() as usize,
            column: location.column() as usize,
        });
    let missing_field = matches!(error, serde_saphyr::Error::SerdeMissingField { .. });
    let key_path = position
        .and_then(|position| positions.path_at(position, missing_field))
        .map(|path| path.join("."))
        .unwrap_or_default();
    let message = serde_saphyr::DefaultMessageFormatter.format_message(error);
    // The message may quote the file: keep control characters out of terminals.
    let message = message.chars().map(|c| if c.is_control() { ' ' } else { c }).collect();
    (location(file, position, key_path), message)
}

fn location(file: &Path, position: Option<Position>, key_path: String) -> Box<Location> {
    Box::new(Location {
        file: file.to_owned(),
        position,
        key_path,
    })
}
