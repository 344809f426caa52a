//! The validation pass: from the file as written ([`GraphFile`]) to a checked [`Graph`].
//!
//! Order of checks: command-line overrides; then per node its kind, variables, stage and
//! parameters; then per input its name, reference, feedback delay, source and type; then
//! required inputs, hosts and cycles. The first problem found is returned.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use serde_json::{Map, Value};

use super::error::{GraphError, Location, Position, list};
use super::file::{GraphFile, HostDecl, InputDecl, NodeDecl};
use super::model::{Graph, Host, Input, Node, NodeKind};
use super::positions::{Positions, key_path};
use super::vars::{self, VarProblem};
use gprflow_stage::{InputPorts, ParamError, PortSpec, StageCatalog, StageInfo};

/// Nanoseconds per second, for `feedback_delay_s`.
const NS_PER_S: f64 = 1e9;

/// The file being checked: its name and where its keys are.
pub(crate) struct Source<'a> {
    /// The file as named by the caller.
    pub file: &'a Path,
    /// Its text as read.
    pub text: &'a str,
    /// Where its keys and values are.
    pub positions: &'a Positions,
}

impl Source<'_> {
    /// Points at the key naming `path` (or the nearest enclosing one in the file).
    pub(crate) fn at_key(&self, path: &[String]) -> Box<Location> {
        self.location(path, self.positions.key(path))
    }

    /// Points at the value at `path` (or the nearest enclosing one in the file).
    pub(crate) fn at_value(&self, path: &[String]) -> Box<Location> {
        self.location(path, self.positions.value(path))
    }

    fn location(&self, path: &[String], position: Option<Position>) -> Box<Location> {
        Box::new(Location {
            file: self.file.to_owned(),
            position,
            key_path: path.join("."),
        })
    }
}

/// A node whose own declaration is checked; its inputs are not yet.
struct Draft<'c> {
    name: String,
    kind: NodeKind,
    /// The stage kind; `None` for `exec` nodes.
    stage: Option<&'c dyn StageInfo>,
    outputs: Vec<PortSpec>,
    params: Value,
}

/// Checks `decl` and builds the graph.
///
/// # Errors
/// The first problem found.
pub(crate) fn check(
    decl: GraphFile,
    source: &Source<'_>,
    overrides: &[(String, String)],
    catalog: &StageCatalog,
) -> Result<Graph, GraphError> {
    let vars = resolve_vars(&decl.inputs, overrides, source)?;

    let mut running = Vec::with_capacity(decl.nodes.0.len());
    let mut off = Vec::new();
    for (name, node) in &decl.nodes.0 {
        if runs(name, node, &vars, source)? {
            running.push((name, node));
        } else {
            off.push(name.as_str());
        }
    }

    let mut drafts = Vec::with_capacity(running.len());
    for (name, node) in &running {
        drafts.push(check_node(name, node, &vars, source, catalog)?);
    }

    let mut nodes = Vec::with_capacity(drafts.len());
    for (draft, (_, node)) in drafts.iter().zip(&running) {
        nodes.push(Node {
            inputs: check_inputs(draft, node, &drafts, &off, source)?,
            name: draft.name.clone(),
            kind: draft.kind.clone(),
            outputs: draft.outputs.clone(),
            params: draft.params.clone(),
        });
    }

    let hosts = match decl.hosts {
        Some(mut hosts) => {
            // nodes that do not run are on no host
            for (_, host) in &mut hosts.0 {
                host.nodes.retain(|n| !off.contains(&n.as_str()));
            }
            check_hosts(hosts.0, &nodes, &decl.name, source)?
        }
        None => Vec::new(),
    };
    if let Some(host) = decl.record.as_ref().and_then(|r| r.host.as_ref())
        && !hosts.iter().any(|h| &h.name == host)
    {
        return Err(GraphError::BadHost {
            at: source.at_value(&key_path(&["record", "host"])),
            host: host.clone(),
            message: format!(
                "`record.host` names no host (hosts are: {})",
                list(hosts.iter().map(|h| h.name.as_str()))
            ),
        });
    }
    check_cycles(&nodes, source)?;

    Ok(Graph {
        name: decl.name,
        file: source.file.to_owned(),
        text: source.text.to_owned(),
        vars,
        nodes,
        hosts,
        record: decl.record,
    })
}

/// The file's variables with the command-line overrides applied.
fn resolve_vars(
    defaults: &BTreeMap<String, String>,
    overrides: &[(String, String)],
    source: &Source<'_>,
) -> Result<BTreeMap<String, String>, GraphError> {
    let mut vars = defaults.clone();
    for (name, value) in overrides {
        match vars.get_mut(name) {
            Some(slot) => value.clone_into(slot),
            None => {
                return Err(GraphError::UnknownOverride {
                    at: source.at_key(&key_path(&["inputs"])),
                    name: name.clone(),
                    known: list(defaults.keys().map(String::as_str)),
                });
            }
        }
    }
    Ok(vars)
}

/// Turns a substitution problem at `path` into an error.
fn var_error(
    problem: VarProblem,
    path: &[String],
    text: &str,
    vars: &BTreeMap<String, String>,
    source: &Source<'_>,
) -> GraphError {
    let at = source.at_value(path);
    match problem {
        VarProblem::Unknown(name) => GraphError::UnknownVariable {
            at,
            name,
            known: list(vars.keys().map(String::as_str)),
        },
        VarProblem::Unclosed => GraphError::UnclosedVariable {
            at,
            text: text.to_owned(),
        },
    }
}

/// Whether a node runs: its `when`, with variables substituted, is `true` (or absent) or
/// `false`.
fn runs(name: &str, node: &NodeDecl, vars: &BTreeMap<String, String>, source: &Source<'_>) -> Result<bool, GraphError> {
    let Some(when) = &node.when else {
        return Ok(true);
    };
    let path = key_path(&["nodes", name, "when"]);
    let value = vars::substitute(when, vars).map_err(|problem| var_error(problem, &path, when, vars, source))?;
    match value.trim() {
        "true" => Ok(true),
        "false" => Ok(false),
        other => Err(GraphError::Structure {
            at: source.at_value(&path),
            message: format!("`when` must be true or false, not `{other}`"),
        }),
    }
}

/// Checks one node's own declaration: kind, variables, stage and parameters.
fn check_node<'c>(
    name: &str,
    node: &NodeDecl,
    vars: &BTreeMap<String, String>,
    source: &Source<'_>,
    catalog: &'c StageCatalog,
) -> Result<Draft<'c>, GraphError> {
    let here = |parts: &[&str]| {
        let mut path = key_path(&["nodes", name]);
        path.extend(parts.iter().map(|part| (*part).to_owned()));
        path
    };

    // `/` separates node from output in references (`gen/trace`).
    if name.is_empty() || name.contains('/') {
        return Err(GraphError::Structure {
            at: source.at_key(&here(&[])),
            message: format!("node name `{name}` must be non-empty and without `/`"),
        });
    }

    let mut params = Value::Object(node.params.clone().unwrap_or_default());
    vars::substitute_value(&mut params, vars).map_err(|(below, problem)| {
        let text = string_at(node.params.as_ref(), &below);
        let mut path = here(&["params"]);
        path.extend(below);
        var_error(problem, &path, &text, vars, source)
    })?;

    let (kind, stage, outputs) = match (&node.stage, &node.exec) {
        (Some(stage_name), None) => {
            if node.outputs.is_some() {
                return Err(GraphError::Structure {
                    at: source.at_key(&here(&["outputs"])),
                    message: format!("`outputs` is for `exec` nodes; stage `{stage_name}` declares its own"),
                });
            }
            let stage = catalog.get(stage_name).ok_or_else(|| GraphError::UnknownStage {
                at: source.at_value(&here(&["stage"])),
                stage: stage_name.clone(),
                known: list(catalog.iter().map(|stage| stage.name())),
            })?;
            // Points at the offending key, or at `params` when the stage names none.
            let bad_param = |error: ParamError| {
                let mut path = here(&["params"]);
                path.extend(error.path);
                GraphError::BadParam {
                    at: source.at_key(&path),
                    stage: stage_name.clone(),
                    message: error.message,
                }
            };
            stage.check_params(&params).map_err(bad_param)?;
            let outputs = stage.outputs(&params).map_err(bad_param)?;
            (NodeKind::Stage(stage_name.clone()), Some(stage), outputs)
        }
        (None, Some(exec)) => {
            let exec = vars::substitute(exec, vars)
                .map_err(|problem| var_error(problem, &here(&["exec"]), exec, vars, source))?;
            let outputs = node
                .outputs
                .iter()
                .flat_map(|outputs| &outputs.0)
                .map(|(name, msg_type)| PortSpec::new(name, msg_type))
                .collect();
            (NodeKind::Exec(exec), None, outputs)
        }
        (Some(_), Some(_)) => {
            return Err(GraphError::Structure {
                at: source.at_key(&here(&["exec"])),
                message: "a node has `stage:` or `exec:`, not both".to_owned(),
            });
        }
        (None, None) => {
            return Err(GraphError::Structure {
                at: source.at_key(&here(&[])),
                message: format!("node `{name}` needs `stage:` (a stage kind) or `exec:` (an executable)"),
            });
        }
    };

    Ok(Draft {
        name: name.to_owned(),
        kind,
        stage,
        outputs,
        params,
    })
}

/// The string at `path` inside `params` as written, for error messages.
fn string_at(params: Option<&Map<String, Value>>, path: &[String]) -> String {
    let Some((first, rest)) = path.split_first() else {
        return String::new();
    };
    let mut value = params.and_then(|map| map.get(first));
    for key in rest {
        value = value.and_then(|v| match v {
            Value::Object(map) => map.get(key),
            Value::Array(items) => key.parse::<usize>().ok().and_then(|index| items.get(index)),
            _ => None,
        });
    }
    match value {
        Some(Value::String(text)) => text.clone(),
        Some(other) => other.to_string(),
        None => String::new(),
    }
}

/// Checks and resolves the inputs of one node.
fn check_inputs(
    draft: &Draft<'_>,
    node: &NodeDecl,
    drafts: &[Draft<'_>],
    off: &[&str],
    source: &Source<'_>,
) -> Result<Vec<Input>, GraphError> {
    // The stage and its inputs, when it declares a fixed set (exec nodes and `Any` take any).
    let fixed = draft.stage.and_then(|stage| match stage.inputs() {
        InputPorts::Fixed(specs) => Some((stage, specs)),
        InputPorts::Any => None,
    });
    let here = |parts: &[&str]| {
        let mut path = key_path(&["nodes", &draft.name, "inputs"]);
        path.extend(parts.iter().map(|part| (*part).to_owned()));
        path
    };

    let mut inputs = Vec::with_capacity(node.inputs.len());
    for (input_name, input) in &node.inputs {
        // The type this input takes, when the stage says.
        let expected = match &fixed {
            Some((stage, specs)) => {
                let spec = specs.iter().find(|spec| &spec.port.name == input_name).ok_or_else(|| {
                    GraphError::UnknownInput {
                        at: source.at_key(&here(&[input_name])),
                        stage: stage.name().to_owned(),
                        input: input_name.clone(),
                        known: list(specs.iter().map(|spec| spec.port.name.as_str())),
                    }
                })?;
                Some(spec.port.msg_type.as_str())
            }
            None => None,
        };

        let (reference, reference_path, feedback_delay_s, latest_only) = match input {
            InputDecl::Short(reference) => (reference, here(&[input_name]), None, false),
            InputDecl::Long(long) => (
                &long.from,
                here(&[input_name, "from"]),
                long.feedback_delay_s,
                long.latest_only,
            ),
        };
        let (from_node, from_output) = reference
            .split_once('/')
            .filter(|(node, output)| !node.is_empty() && !output.is_empty())
            .ok_or_else(|| GraphError::BadReference {
                at: source.at_value(&reference_path),
                reference: reference.clone(),
            })?;
        let feedback_delay_ns = feedback_delay_s
            .map(|seconds| {
                feedback_delay_ns(seconds).ok_or_else(|| GraphError::BadFeedbackDelay {
                    at: source.at_value(&here(&[input_name, "feedback_delay_s"])),
                    value: seconds,
                })
            })
            .transpose()?;

        if off.contains(&from_node) {
            return Err(GraphError::Structure {
                at: source.at_value(&reference_path),
                message: format!("`{reference}` comes from node `{from_node}`, whose `when` is false"),
            });
        }
        let producer = drafts
            .iter()
            .find(|d| d.name == from_node)
            .ok_or_else(|| GraphError::NoSuchNode {
                at: source.at_value(&reference_path),
                node: from_node.to_owned(),
                known: list(drafts.iter().map(|d| d.name.as_str())),
            })?;
        let output = producer
            .outputs
            .iter()
            .find(|port| port.name == from_output)
            .ok_or_else(|| GraphError::NoSuchOutput {
                at: source.at_value(&reference_path),
                node: from_node.to_owned(),
                output: from_output.to_owned(),
                known: list(producer.outputs.iter().map(|port| port.name.as_str())),
            })?;
        if let Some(expected) = expected
            && expected != output.msg_type
        {
            return Err(GraphError::TypeMismatch {
                at: source.at_value(&reference_path),
                input: input_name.clone(),
                expected: expected.to_owned(),
                from: reference.clone(),
                actual: output.msg_type.clone(),
            });
        }

        inputs.push(Input {
            name: input_name.clone(),
            from_node: from_node.to_owned(),
            from_output: from_output.to_owned(),
            msg_type: output.msg_type.clone(),
            feedback_delay_ns,
            latest_only,
        });
    }

    if let Some((stage, specs)) = &fixed
        && let Some(missing) = specs
            .iter()
            .find(|spec| !spec.optional && !node.inputs.contains_key(&spec.port.name))
    {
        return Err(GraphError::MissingInput {
            at: source.at_key(&here(&[])),
            stage: stage.name().to_owned(),
            input: missing.port.name.clone(),
            msg_type: missing.port.msg_type.clone(),
        });
    }
    Ok(inputs)
}

/// `seconds` in whole nanoseconds, when positive, finite and at least 1 ns.
fn feedback_delay_ns(seconds: f64) -> Option<i64> {
    let ns = (seconds * NS_PER_S).round();
    // `i64::MAX as f64` rounds up to 2^63, itself out of range: compare strictly.
    let in_range = ns >= 1.0 && ns < i64::MAX as f64;
    in_range.then_some(ns as i64)
}

/// Checks the placement of nodes on hosts.
fn check_hosts(
    decls: Vec<(String, HostDecl)>,
    nodes: &[Node],
    graph_name: &str,
    source: &Source<'_>,
) -> Result<Vec<Host>, GraphError> {
    let mut placed: HashMap<&str, &str> = HashMap::new();
    for (host, decl) in &decls {
        // everything but the certificate files, which the launcher of that host checks
        let checked =
            gprflow_bus::zenoh::check_settings(&decl.zenoh).and(gprflow_bus::zenoh::key_prefix(graph_name, host));
        if let Err(message) = checked {
            return Err(GraphError::BadHost {
                at: source.at_value(&key_path(&["hosts", host])),
                host: host.clone(),
                message,
            });
        }
        for (index, node) in decl.nodes.iter().enumerate() {
            let at = || source.at_value(&key_path(&["hosts", host, "nodes", &index.to_string()]));
            if !nodes.iter().any(|n| &n.name == node) {
                return Err(GraphError::UnknownHostNode {
                    at: at(),
                    host: host.clone(),
                    node: node.clone(),
                    known: list(nodes.iter().map(|n| n.name.as_str())),
                });
            }
            if let Some(first_host) = placed.insert(node, host) {
                return Err(GraphError::NodeOnTwoHosts {
                    at: at(),
                    node: node.clone(),
                    first_host: first_host.to_owned(),
                });
            }
        }
    }
    if let Some(node) = nodes.iter().find(|n| !placed.contains_key(n.name.as_str())) {
        return Err(GraphError::NodeOnNoHost {
            at: source.at_key(&key_path(&["nodes", &node.name])),
            node: node.name.clone(),
            hosts: list(decls.iter().map(|(host, _)| host.as_str())),
        });
    }
    Ok(decls
        .into_iter()
        .map(|(name, decl)| Host {
            name,
            nodes: decl.nodes,
            zenoh: decl.zenoh,
        })
        .collect())
}

/// Finds a cycle of non-feedback inputs (a deadlock), depth first in file order.
fn check_cycles(nodes: &[Node], source: &Source<'_>) -> Result<(), GraphError> {
    let index: HashMap<&str, usize> = nodes.iter().enumerate().map(|(i, n)| (n.name.as_str(), i)).collect();
    // For each node, the non-feedback inputs it reads: (producer index, input).
    let reads: Vec<Vec<(usize, &Input)>> = nodes
        .iter()
        .map(|node| {
            node.inputs
                .iter()
                .filter(|input| input.feedback_delay_ns.is_none())
                .filter_map(|input| index.get(input.from_node.as_str()).map(|&i| (i, input)))
                .collect()
        })
        .collect();

    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        OnPath,
        Done,
    }
    let mut marks = vec![Mark::New; nodes.len()];
    for start in 0..nodes.len() {
        if marks[start] != Mark::New {
            continue;
        }
        // The current path: each node reads the next; with the next edge to follow.
        let mut path: Vec<(usize, usize)> = vec![(start, 0)];
        marks[start] = Mark::OnPath;
        while let Some(top) = path.last_mut() {
            let consumer = top.0;
            let Some(&(producer, input)) = reads[consumer].get(top.1) else {
                marks[consumer] = Mark::Done;
                path.pop();
                continue;
            };
            top.1 += 1;
            match marks[producer] {
                Mark::Done => {}
                Mark::New => {
                    marks[producer] = Mark::OnPath;
                    path.push((producer, 0));
                }
                Mark::OnPath => {
                    // producer -> consumer -> ... -> producer, in the direction data flows.
                    let from = path.iter().position(|&(n, _)| n == producer).unwrap_or(0);
                    let mut cycle: Vec<&str> = vec![nodes[producer].name.as_str()];
                    cycle.extend(path[from..].iter().rev().map(|&(n, _)| nodes[n].name.as_str()));
                    let consumer_name = &nodes[consumer].name;
                    return Err(GraphError::Cycle {
                        at: source.at_value(&key_path(&["nodes", consumer_name, "inputs", &input.name])),
                        cycle: cycle.join(" -> "),
                    });
                }
            }
        }
    }
    Ok(())
}
