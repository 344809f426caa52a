//! A checked graph, as the launcher uses it.

use std::collections::BTreeMap;
use std::path::PathBuf;

use gprflow_bus::{ZenohDecl, glob_matches};

use super::file::RecordDecl;
use gprflow_stage::PortSpec;

/// A graph file, parsed and checked: every input is wired to an existing output of the same
/// message type, every cycle has a feedback input, variables are substituted.
#[derive(Debug, Clone, PartialEq)]
pub struct Graph {
    /// Name of the pipeline.
    pub name: String,
    /// The file it was read from, as named by the caller.
    pub file: PathBuf,
    /// The file's text as read (recorded alongside runs).
    pub text: String,
    /// Every variable with its value: the file's default or the command-line override.
    pub vars: BTreeMap<String, String>,
    /// Nodes in file order.
    pub nodes: Vec<Node>,
    /// Hosts in file order; empty when the file places no nodes.
    pub hosts: Vec<Host>,
    /// Topics to record, when the file asks for a recording.
    pub record: Option<RecordDecl>,
}

/// One node of a graph.
#[derive(Debug, Clone, PartialEq)]
pub struct Node {
    /// Its name, unique in the graph.
    pub name: String,
    /// What it runs.
    pub kind: NodeKind,
    /// Its wired inputs, sorted by input name.
    pub inputs: Vec<Input>,
    /// Its outputs: the stage's for these params, or those an `exec` node declares.
    pub outputs: Vec<PortSpec>,
    /// Parameters with variables substituted; always a JSON object.
    pub params: serde_json::Value,
}

/// What a node runs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NodeKind {
    /// A stage kind of the catalog, by name.
    Stage(String),
    /// A user's executable, as written in the file (relative paths unresolved).
    Exec(String),
}

/// One wired input.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Input {
    /// Input port name.
    pub name: String,
    /// Node it reads from.
    pub from_node: String,
    /// Output of that node.
    pub from_output: String,
    /// Message type (the same on both ends).
    pub msg_type: String,
    /// For a feedback input: the delay, in nanoseconds (positive).
    pub feedback_delay_ns: Option<i64>,
    /// Keep only the newest message when the consumer falls behind.
    pub latest_only: bool,
}

impl Input {
    /// The topic this input reads, `node/output`.
    pub fn topic(&self) -> String {
        format!("{}/{}", self.from_node, self.from_output)
    }
}

/// One machine and the nodes it runs.
#[derive(Debug, Clone, PartialEq)]
pub struct Host {
    /// Host name as written in the file (`--host NAME` selects it).
    pub name: String,
    /// Its nodes, in the order listed.
    pub nodes: Vec<String>,
    /// Its zenoh settings.
    pub zenoh: ZenohDecl,
}

impl Graph {
    /// The node named `name`.
    pub fn node(&self, name: &str) -> Option<&Node> {
        self.nodes.iter().find(|node| node.name == name)
    }

    /// Every output of every node as (`node/output`, message type), in file order.
    pub fn topics(&self) -> Vec<(String, String)> {
        self.nodes
            .iter()
            .flat_map(|node| {
                node.outputs
                    .iter()
                    .map(move |port| (format!("{}/{}", node.name, port.name), port.msg_type.clone()))
            })
            .collect()
    }

    /// The nodes reading `node`'s `output`, with the input that reads it.
    pub fn consumers(&self, node: &str, output: &str) -> Vec<(&Node, &Input)> {
        self.nodes
            .iter()
            .flat_map(|consumer| consumer.inputs.iter().map(move |input| (consumer, input)))
            .filter(|(_, input)| input.from_node == node && input.from_output == output)
            .collect()
    }

    /// Whether `topic` (`node/output`) is to be recorded: it matches one of the `record:`
    /// patterns. Always false when the file has no `record:`.
    pub fn record_matches(&self, topic: &str) -> bool {
        self.record
            .as_ref()
            .is_some_and(|record| record.topics.iter().any(|pattern| glob_matches(pattern, topic)))
    }
}
