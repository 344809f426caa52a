//! Where each key and value of a graph file is.
//!
//! One walk over the YAML parser's events builds a map from key path (`nodes`, `gain`,
//! `inputs`, `trace`) to the line and column of the key and of its value, for block and
//! flow style alike. The same walk finds YAML syntax errors and duplicate keys. The typed
//! deserialiser (serde-saphyr) then reads the file; this map turns its positions into key
//! paths and gives positions to the errors of the later validation pass.

use std::collections::HashMap;

use serde_saphyr::granit_parser::{Event, Marker, Parser};

use super::error::Position;

/// Keys from the top of the file down to one node; sequence items are named by index.
pub(crate) type KeyPath = Vec<String>;

/// Builds a [`KeyPath`] from its parts.
pub(crate) fn key_path(parts: &[&str]) -> KeyPath {
    parts.iter().map(|part| (*part).to_owned()).collect()
}

/// Positions of one YAML node.
#[derive(Debug, Clone, Copy)]
struct Entry {
    /// The mapping key naming it; `None` for sequence items and the top.
    key: Option<Position>,
    /// The value itself.
    value: Position,
}

/// What the walk found wrong.
#[derive(Debug)]
pub(crate) enum ScanProblem {
    /// Not YAML.
    Syntax {
        /// Where the parser stopped.
        position: Position,
        /// The parser's words.
        message: String,
    },
    /// A key twice in one mapping.
    DuplicateKey {
        /// Path of the second occurrence.
        path: KeyPath,
        /// The key.
        key: String,
        /// The second occurrence.
        at: Position,
        /// The first occurrence.
        first: Position,
    },
}

/// Key path -> positions of every node of the first YAML document of a file.
#[derive(Debug, Default)]
pub(crate) struct Positions {
    entries: HashMap<KeyPath, Entry>,
}

/// An open collection during the walk.
enum Frame {
    Map {
        path: KeyPath,
        /// Scalar keys seen so far, with their positions.
        seen: HashMap<String, Position>,
        /// The key whose value comes next; `None` while a key is expected.
        pending_key: Option<(String, Position)>,
    },
    Seq {
        path: KeyPath,
        next_index: usize,
    },
    /// Inside a collection used as a mapping key (`? [a, b]: x`): skipped.
    ComplexKey {
        depth: usize,
    },
}

/// What kind of YAML node an event starts.
enum NodeEvent<'e> {
    Scalar(&'e str),
    /// An alias: a leaf here, whatever it points to.
    Alias,
    Collection {
        is_map: bool,
    },
}

fn position(marker: &Marker) -> Position {
    Position {
        line: marker.line(),
        column: marker.col().saturating_add(1),
    }
}

impl Positions {
    /// Walks `text` once.
    ///
    /// # Errors
    /// The first syntax error or duplicate key.
    pub(crate) fn scan(text: &str) -> Result<Self, ScanProblem> {
        let mut walk = Walk::default();
        let mut documents = 0_usize;
        for item in Parser::new_from_str(text) {
            let (event, span) = item.map_err(|e| ScanProblem::Syntax {
                position: position(e.marker()),
                message: e.info(),
            })?;
            let at = position(&span.start);
            // Later documents are only checked for syntax; the deserialiser rejects them.
            if documents > 1 {
                continue;
            }
            match &event {
                Event::DocumentStart(..) => documents += 1,
                Event::Scalar(text, ..) => walk.node(NodeEvent::Scalar(text), at)?,
                Event::Alias(..) | Event::UnresolvedAlias(..) => walk.node(NodeEvent::Alias, at)?,
                Event::MappingStart(..) => walk.node(NodeEvent::Collection { is_map: true }, at)?,
                Event::SequenceStart(..) => walk.node(NodeEvent::Collection { is_map: false }, at)?,
                Event::MappingEnd | Event::SequenceEnd => walk.end(),
                _ => {}
            }
        }
        Ok(walk.positions)
    }

    /// Position of the key naming `path` (of the value for sequence items and the top),
    /// or of the nearest enclosing node present in the file.
    pub(crate) fn key(&self, path: &[String]) -> Option<Position> {
        self.nearest(path).map(|entry| entry.key.unwrap_or(entry.value))
    }

    /// Position of the value at `path`, or of the nearest enclosing node present in the file.
    pub(crate) fn value(&self, path: &[String]) -> Option<Position> {
        self.nearest(path).map(|entry| entry.value)
    }

    /// The path of the key or value at exactly `at`: turns a deserialiser's position into a
    /// key path. A block mapping starts where its first key does: `container` picks the
    /// mapping (for "missing field" errors), else the key.
    pub(crate) fn path_at(&self, at: Position, container: bool) -> Option<&KeyPath> {
        let keys = self
            .entries
            .iter()
            .filter(|(_, entry)| entry.key == Some(at))
            .map(|(path, _)| path);
        let values = self
            .entries
            .iter()
            .filter(|(_, entry)| entry.value == at)
            .map(|(path, _)| path);
        if container {
            values.min_by_key(|path| path.len())
        } else {
            keys.chain(values).max_by_key(|path| path.len())
        }
    }

    fn nearest(&self, path: &[String]) -> Option<&Entry> {
        (0..=path.len()).rev().find_map(|len| self.entries.get(&path[..len]))
    }
}

/// State of the walk over one document.
#[derive(Default)]
struct Walk {
    stack: Vec<Frame>,
    positions: Positions,
}

impl Walk {
    /// A node starts: a key, a value, or the top.
    fn node(&mut self, node: NodeEvent<'_>, at: Position) -> Result<(), ScanProblem> {
        let child = match self.stack.last_mut() {
            None => Some((KeyPath::new(), None)),
            Some(Frame::ComplexKey { depth }) => {
                if matches!(node, NodeEvent::Collection { .. }) {
                    *depth += 1;
                }
                return Ok(());
            }
            Some(Frame::Seq { path, next_index }) => {
                let mut child = path.clone();
                child.push(next_index.to_string());
                *next_index += 1;
                Some((child, None))
            }
            Some(Frame::Map {
                path,
                seen,
                pending_key,
            }) => match pending_key.take() {
                Some((key, key_at)) => {
                    let mut child = path.clone();
                    child.push(key);
                    Some((child, Some(key_at)))
                }
                None => {
                    // This node is a key.
                    match node {
                        NodeEvent::Scalar(key) => {
                            if let Some(first) = seen.get(key) {
                                let mut dup = path.clone();
                                dup.push(key.to_owned());
                                return Err(ScanProblem::DuplicateKey {
                                    path: dup,
                                    key: key.to_owned(),
                                    at,
                                    first: *first,
                                });
                            }
                            seen.insert(key.to_owned(), at);
                            *pending_key = Some((key.to_owned(), at));
                        }
                        NodeEvent::Alias => *pending_key = Some(("*".to_owned(), at)),
                        NodeEvent::Collection { .. } => {
                            *pending_key = Some(("?".to_owned(), at));
                            self.stack.push(Frame::ComplexKey { depth: 1 });
                        }
                    }
                    None
                }
            },
        };
        if let Some((path, key)) = child {
            self.positions
                .entries
                .entry(path.clone())
                .or_insert(Entry { key, value: at });
            if let NodeEvent::Collection { is_map } = node {
                self.stack.push(if is_map {
                    Frame::Map {
                        path,
                        seen: HashMap::new(),
                        pending_key: None,
                    }
                } else {
                    Frame::Seq { path, next_index: 0 }
                });
            }
        }
        Ok(())
    }

    /// A collection ends.
    fn end(&mut self) {
        if let Some(Frame::ComplexKey { depth }) = self.stack.last_mut() {
            *depth = depth.saturating_sub(1);
            if *depth > 0 {
                return;
            }
        }
        self.stack.pop();
    }
}
