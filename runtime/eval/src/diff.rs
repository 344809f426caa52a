//! Comparing two recordings for regression: message counts per topic, the first message
//! that differs beyond tolerance (topic, seq, stamp, field path, both values), the largest
//! absolute and relative difference of every numeric field, and differences in the
//! recorded graph and parameters.
//!
//! Messages are compared in order per topic; identical payloads are skipped without
//! decoding, others are decoded to JSON and walked field by field. Array indices are
//! folded (`samples_i16[]`) in the per-field statistics and kept in the divergence path.

use std::collections::BTreeMap;

use serde::Serialize;
use serde_json::Value;

use gprflow_record::{RecordError, Recording};

/// Tolerances: a numeric difference passes when it is within `abs` or within `rel`
/// (relative to the larger magnitude).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Tolerance {
    /// Absolute tolerance.
    pub abs: f64,
    /// Relative tolerance.
    pub rel: f64,
}

/// Tolerances per topic and field, as a tolerance file gives them (YAML):
///
/// ```yaml
/// default: { abs: 0.0, rel: 0.0 }
/// rules:
///   - { topic: "/estimate/*", field: "world_from_body.pose.position.*", abs: 1.0e-6 }
///   - { topic: "/filter/submap", field: "pixels[]", rel: 1.0e-5 }
/// ```
///
/// The first rule whose `topic` and `field` globs (`*` matches anything) match a numeric field
/// applies, else `default`. Fields are named as in the report: array indices folded
/// (`pixels[]`), nested fields joined by `.`.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tolerances {
    /// Tolerance of fields no rule names (default exact).
    #[serde(default)]
    pub default: Tolerance,
    /// Rules, first match wins.
    #[serde(default)]
    pub rules: Vec<ToleranceRule>,
}

/// One rule of [`Tolerances`].
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToleranceRule {
    /// Topic glob (default `*`).
    #[serde(default = "any")]
    pub topic: String,
    /// Field glob over folded paths (default `*`).
    #[serde(default = "any")]
    pub field: String,
    /// Absolute tolerance (default 0).
    #[serde(default)]
    pub abs: f64,
    /// Relative tolerance (default 0).
    #[serde(default)]
    pub rel: f64,
}

fn any() -> String {
    "*".to_owned()
}

impl Tolerances {
    /// The same tolerance for every field.
    pub fn uniform(tol: Tolerance) -> Self {
        Self {
            default: tol,
            rules: Vec::new(),
        }
    }

    /// Reads a tolerance file; errors name the file (and the line, where the parser says).
    ///
    /// # Errors
    /// Unreadable file, YAML that is not a tolerance file, or a negative or non-finite value.
    pub fn from_file(path: &std::path::Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let t: Self = serde_saphyr::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        let bad = |v: f64| !(v.is_finite() && v >= 0.0);
        if bad(t.default.abs) || bad(t.default.rel) {
            return Err(format!(
                "{}: default: tolerances must be finite and >= 0",
                path.display()
            ));
        }
        if let Some(i) = t.rules.iter().position(|r| bad(r.abs) || bad(r.rel)) {
            return Err(format!(
                "{}: rules[{i}]: tolerances must be finite and >= 0",
                path.display()
            ));
        }
        Ok(t)
    }

    /// The tolerance of `field` (folded path) on `topic`.
    pub fn for_field(&self, topic: &str, field: &str) -> Tolerance {
        self.rules
            .iter()
            .find(|r| gprflow_bus::glob_matches(&r.topic, topic) && gprflow_bus::glob_matches(&r.field, field))
            .map_or(self.default, |r| Tolerance { abs: r.abs, rel: r.rel })
    }
}

impl Default for Tolerance {
    fn default() -> Self {
        Self { abs: 0.0, rel: 0.0 }
    }
}

/// Largest differences seen in one numeric field.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct FieldStats {
    /// Largest absolute difference.
    pub max_abs: f64,
    /// Largest relative difference.
    pub max_rel: f64,
    /// Values that differed at all.
    pub differing: u64,
    /// Values beyond tolerance.
    pub beyond_tolerance: u64,
}

/// One topic in both recordings.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TopicDiff {
    /// Topic.
    pub topic: String,
    /// Message type in A (empty when absent).
    pub type_a: String,
    /// Message type in B.
    pub type_b: String,
    /// Messages in A.
    pub count_a: u64,
    /// Messages in B.
    pub count_b: u64,
    /// Messages whose payloads differ.
    pub differing_messages: u64,
    /// Numeric fields that differ: path -> statistics.
    pub fields: BTreeMap<String, FieldStats>,
    /// Fields that differ in structure or non-numeric value (counted).
    pub structural: BTreeMap<String, u64>,
}

/// The first difference beyond tolerance, in stamp order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Divergence {
    /// Topic.
    pub topic: String,
    /// Index of the message on its topic (0-based).
    pub index: u64,
    /// MCAP sequence number in A.
    pub seq: u32,
    /// Log time in A, ns.
    pub stamp_ns: u64,
    /// Field path (`samples_i16[17]`, `header.stamp.sec`; empty: the whole message).
    pub path: String,
    /// Value in A.
    pub a: Value,
    /// Value in B.
    pub b: Value,
}

/// Everything `diff` found.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DiffReport {
    /// Per topic, in name order.
    pub topics: Vec<TopicDiff>,
    /// The first difference beyond tolerance.
    pub first_divergence: Option<Divergence>,
    /// Metadata fields that differ: `record.key` -> (A, B).
    pub metadata: BTreeMap<String, (String, String)>,
    /// Attachments whose contents differ or exist in one recording only.
    pub attachments: Vec<String>,
    /// Whether the differences are a regression (counts, topics, types, or values beyond
    /// tolerance). Metadata and attachments are reported but do not count.
    pub regression: bool,
}

/// A recorded message: sequence, log time, payload.
type Stored = (u32, u64, Vec<u8>);

struct Side {
    /// Per topic: message type and messages in file order.
    messages: BTreeMap<String, (String, Vec<Stored>)>,
    metadata: BTreeMap<String, String>,
    attachments: BTreeMap<String, Vec<u8>>,
}

fn load(rec: &Recording) -> Side {
    let mut messages: BTreeMap<String, (String, Vec<Stored>)> = BTreeMap::new();
    let (extras, stopped) = rec.scan(|m| {
        messages
            .entry(m.topic.to_owned())
            .or_insert_with(|| (m.msg_type.to_owned(), Vec::new()))
            .1
            .push((m.sequence, m.log_time, m.data.to_vec()));
    });
    if let Some(reason) = stopped {
        tracing::warn!("{}: read stopped early: {reason}", rec.path().display());
    }
    let mut metadata = BTreeMap::new();
    for (name, fields) in extras.metadata {
        for (k, v) in fields {
            metadata.insert(format!("{name}.{k}"), v);
        }
    }
    Side {
        messages,
        metadata,
        attachments: extras.attachments.into_iter().collect(),
    }
}

/// Folds array indices out of a path: `a[3].b[0]` -> `a[].b[]`.
fn fold(path: &str) -> String {
    let mut out = String::with_capacity(path.len());
    let mut skipping = false;
    for c in path.chars() {
        match c {
            '[' => {
                skipping = true;
                out.push('[');
            }
            ']' => {
                skipping = false;
                out.push(']');
            }
            _ if skipping => {}
            _ => out.push(c),
        }
    }
    out
}

struct Walk<'a> {
    tol: &'a Tolerances,
    topic: &'a mut TopicDiff,
    first_beyond: Option<(String, Value, Value)>,
}

impl Walk<'_> {
    fn structural(&mut self, path: &str, a: &Value, b: &Value) {
        *self.topic.structural.entry(fold(path)).or_default() += 1;
        if self.first_beyond.is_none() {
            self.first_beyond = Some((path.to_owned(), a.clone(), b.clone()));
        }
    }

    fn walk(&mut self, path: &str, a: &Value, b: &Value) {
        match (a, b) {
            (Value::Number(x), Value::Number(y)) => {
                let (Some(x), Some(y)) = (x.as_f64(), y.as_f64()) else {
                    return self.structural(path, a, b);
                };
                if x == y {
                    return;
                }
                let abs = (x - y).abs();
                let rel = abs / x.abs().max(y.abs());
                let field = fold(path);
                let tol = self.tol.for_field(&self.topic.topic, &field);
                let stats = self.topic.fields.entry(field).or_default();
                stats.differing += 1;
                stats.max_abs = stats.max_abs.max(abs);
                stats.max_rel = stats.max_rel.max(rel);
                if abs > tol.abs && rel > tol.rel {
                    stats.beyond_tolerance += 1;
                    if self.first_beyond.is_none() {
                        self.first_beyond = Some((path.to_owned(), a.clone(), b.clone()));
                    }
                }
            }
            (Value::Object(x), Value::Object(y)) => {
                for (k, va) in x {
                    let p = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    match y.get(k) {
                        Some(vb) => self.walk(&p, va, vb),
                        None => self.structural(&p, va, &Value::Null),
                    }
                }
                for (k, vb) in y {
                    if !x.contains_key(k) {
                        let p = if path.is_empty() {
                            k.clone()
                        } else {
                            format!("{path}.{k}")
                        };
                        self.structural(&p, &Value::Null, vb);
                    }
                }
            }
            (Value::Array(x), Value::Array(y)) => {
                if x.len() != y.len() {
                    self.structural(
                        &format!("{path}.len"),
                        &Value::from(x.len() as u64),
                        &Value::from(y.len() as u64),
                    );
                }
                for (i, (va, vb)) in x.iter().zip(y).enumerate() {
                    self.walk(&format!("{path}[{i}]"), va, vb);
                }
            }
            _ if a == b => {}
            _ => self.structural(path, a, b),
        }
    }
}

/// Compares recordings `a` and `b`.
///
/// # Errors
/// None beyond what opening did; kept fallible for corrupt files found while reading.
pub fn diff(a: &Recording, b: &Recording, tol: Tolerance) -> Result<DiffReport, RecordError> {
    diff_with(a, b, &Tolerances::uniform(tol))
}

/// Compares recordings `a` and `b` with tolerances per topic and field.
///
/// # Errors
/// As [`diff`].
pub fn diff_with(a: &Recording, b: &Recording, tol: &Tolerances) -> Result<DiffReport, RecordError> {
    let (sa, sb) = (load(a), load(b));
    let mut report = DiffReport::default();
    let mut topics: Vec<&String> = sa.messages.keys().chain(sb.messages.keys()).collect();
    topics.sort();
    topics.dedup();
    let mut firsts: Vec<Divergence> = Vec::new();
    for topic in topics {
        let empty = (String::new(), Vec::new());
        let (ta, ma) = sa.messages.get(topic).unwrap_or(&empty);
        let (tb, mb) = sb.messages.get(topic).unwrap_or(&empty);
        let mut td = TopicDiff {
            topic: topic.clone(),
            type_a: ta.clone(),
            type_b: tb.clone(),
            count_a: ma.len() as u64,
            count_b: mb.len() as u64,
            ..TopicDiff::default()
        };
        if ta != tb || ma.len() != mb.len() {
            report.regression = true;
        }
        if ta == tb {
            for (i, ((seq, stamp, pa), (_, _, pb))) in ma.iter().zip(mb).enumerate() {
                if pa == pb {
                    continue;
                }
                td.differing_messages += 1;
                let (ja, jb) = (
                    gprflow_msg::decode_to_json(ta, pa).unwrap_or_else(|e| Value::String(format!("undecodable: {e}"))),
                    gprflow_msg::decode_to_json(tb, pb).unwrap_or_else(|e| Value::String(format!("undecodable: {e}"))),
                );
                let mut walk = Walk {
                    tol,
                    topic: &mut td,
                    first_beyond: None,
                };
                walk.walk("", &ja, &jb);
                if let Some((path, va, vb)) = walk.first_beyond {
                    report.regression = true;
                    if firsts.iter().all(|d| d.topic != *topic) {
                        firsts.push(Divergence {
                            topic: topic.clone(),
                            index: i as u64,
                            seq: *seq,
                            stamp_ns: *stamp,
                            path,
                            a: va,
                            b: vb,
                        });
                    }
                }
            }
        }
        report.topics.push(td);
    }
    report.first_divergence = firsts.into_iter().min_by_key(|d| (d.stamp_ns, d.topic.clone()));
    let keys: std::collections::BTreeSet<&String> = sa.metadata.keys().chain(sb.metadata.keys()).collect();
    for k in keys {
        let (va, vb) = (sa.metadata.get(k), sb.metadata.get(k));
        if va != vb {
            report.metadata.insert(
                k.clone(),
                (va.cloned().unwrap_or_default(), vb.cloned().unwrap_or_default()),
            );
        }
    }
    let names: std::collections::BTreeSet<&String> = sa.attachments.keys().chain(sb.attachments.keys()).collect();
    for n in names {
        if sa.attachments.get(n) != sb.attachments.get(n) {
            report.attachments.push(n.clone());
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn walk(a: Value, b: Value, tol: Tolerance) -> (TopicDiff, Option<(String, Value, Value)>) {
        walk_with(a, b, &Tolerances::uniform(tol), "/t")
    }

    fn walk_with(a: Value, b: Value, tol: &Tolerances, topic: &str) -> (TopicDiff, Option<(String, Value, Value)>) {
        let mut td = TopicDiff {
            topic: topic.to_owned(),
            ..TopicDiff::default()
        };
        let mut w = Walk {
            tol,
            topic: &mut td,
            first_beyond: None,
        };
        w.walk("", &a, &b);
        let first = w.first_beyond.take();
        (td, first)
    }

    #[test]
    fn numeric_fields_are_compared_with_tolerance_and_paths() {
        let a = json!({"header": {"seq": 1}, "samples": [1.0, 2.0, 3.0], "name": "x"});
        let b = json!({"header": {"seq": 1}, "samples": [1.0, 2.5, 3.0000001], "name": "x"});
        let (td, first) = walk(a.clone(), b.clone(), Tolerance { abs: 1e-3, rel: 0.0 });
        let s = td.fields["samples[]"];
        assert_eq!((s.differing, s.beyond_tolerance), (2, 1));
        assert!((s.max_abs - 0.5).abs() < 1e-12 && (s.max_rel - 0.2).abs() < 1e-12);
        assert_eq!(first.map(|f| f.0), Some("samples[1]".to_owned()));
        let (_, first) = walk(a, b, Tolerance { abs: 1.0, rel: 0.0 });
        assert!(first.is_none());
    }

    #[test]
    fn structure_and_strings_always_count() {
        let (td, first) = walk(
            json!({"a": [1, 2], "s": "x"}),
            json!({"a": [1], "s": "y"}),
            Tolerance { abs: 1e9, rel: 1.0 },
        );
        assert_eq!(td.structural.get("a.len"), Some(&1));
        assert_eq!(td.structural.get("s"), Some(&1));
        assert_eq!(first.map(|f| f.0), Some("a.len".to_owned()));
    }

    #[test]
    fn a_tolerance_file_sets_tolerances_per_topic_and_field() {
        let dir = std::env::temp_dir().join(format!("gprflow-tol-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("tempdir");
        let file = dir.join("tol.yaml");
        std::fs::write(
            &file,
            "default: { abs: 0.0 }\nrules:\n  - { topic: \"/est*\", field: \"samples[]\", abs: 0.6 }\n",
        )
        .expect("write");
        let t = Tolerances::from_file(&file).expect("a tolerance file");
        let a = json!({"samples": [1.0, 2.0], "x": 1.0});
        let b = json!({"samples": [1.0, 2.5], "x": 1.0});
        // the rule covers samples on /estimate: within tolerance
        let (td, first) = walk_with(a.clone(), b.clone(), &t, "/estimate/state");
        assert_eq!(td.fields["samples[]"].beyond_tolerance, 0);
        assert!(first.is_none());
        // another topic takes the exact default
        let (_, first) = walk_with(a.clone(), b.clone(), &t, "/other");
        assert_eq!(first.map(|f| f.0), Some("samples[1]".to_owned()));
        // a field the rule does not name takes the default too
        let c = json!({"samples": [1.0, 2.0], "x": 1.1});
        let (_, first) = walk_with(a, c, &t, "/estimate/state");
        assert_eq!(first.map(|f| f.0), Some("x".to_owned()));
        // errors name the file
        std::fs::write(&file, "rules:\n  - { topic: \"*\", abs: -1 }\n").expect("write");
        let e = Tolerances::from_file(&file).expect_err("negative");
        assert!(e.contains("tol.yaml: rules[0]"), "{e}");
        std::fs::write(&file, "rulez: []\n").expect("write");
        let e = Tolerances::from_file(&file).expect_err("unknown key");
        assert!(e.contains("tol.yaml") && e.contains("rulez"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
