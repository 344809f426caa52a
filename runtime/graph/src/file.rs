//! The graph file format as written: typed serde structs, one per YAML mapping, from which
//! the JSON schema is generated. Nothing here is checked beyond its shape; see `check`.

use std::collections::BTreeMap;
use std::fmt;
use std::marker::PhantomData;

use schemars::JsonSchema;
use serde::Deserialize;
use serde::de::{self, Deserializer, MapAccess, Visitor};

use gprflow_bus::ZenohDecl;

/// A gprflow graph file: a pipeline of stages wired output to input, with optional
/// placement on machines and a list of topics to record.
#[derive(Debug, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "gprflow graph file")]
pub(crate) struct GraphFile {
    /// Name of the pipeline.
    pub name: String,
    /// Variables, with their default values: `${name}` in any string of a node's `params`
    /// or `exec` is replaced by the value; `gprflow launch --set name=value` overrides it.
    #[serde(default)]
    pub inputs: BTreeMap<String, String>,
    /// The nodes, by name: each runs one stage (`stage:`) or one executable (`exec:`).
    #[schemars(with = "BTreeMap<String, NodeDecl>")]
    pub nodes: OrderedMap<NodeDecl>,
    /// Placement of nodes on machines, by host name. When present, every node must be on
    /// exactly one host.
    #[schemars(with = "Option<BTreeMap<String, HostDecl>>")]
    pub hosts: Option<OrderedMap<HostDecl>>,
    /// Topics to record.
    pub record: Option<RecordDecl>,
}

/// One node: exactly one of `stage` or `exec`.
#[derive(Debug, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(extend("oneOf" = [{ "required": ["stage"] }, { "required": ["exec"] }]))]
pub(crate) struct NodeDecl {
    /// Stage kind that this node runs (`gprflow stages` lists them).
    pub stage: Option<String>,
    /// A user's executable that speaks the gprflow bus; it declares its `outputs` and accepts
    /// any inputs. Kept as written: the launcher resolves relative paths.
    pub exec: Option<String>,
    /// Inputs by input-port name: `node/output`, or the long form with `from`.
    #[serde(default)]
    pub inputs: BTreeMap<String, InputDecl>,
    /// Outputs of an `exec` node, by name: the message type (`gprflow_msgs/msg/Trace`).
    /// Stage nodes declare their own outputs.
    #[schemars(with = "Option<BTreeMap<String, String>>")]
    pub outputs: Option<OrderedMap<String>>,
    /// Parameters of the stage; see the stage's own schema.
    pub params: Option<serde_json::Map<String, serde_json::Value>>,
    /// Whether the node runs: `true` or `false`, usually a variable (`when: "${foxglove}"`).
    /// A node that does not run is left out of the graph, and no other node may read from it.
    pub when: Option<String>,
}

/// Where an input comes from.
#[derive(Debug, JsonSchema)]
#[schemars(untagged)]
pub(crate) enum InputDecl {
    /// `node/output`.
    Short(String),
    /// The long form.
    Long(LongInputDecl),
}

/// An input in long form.
#[derive(Debug, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct LongInputDecl {
    /// `node/output`.
    pub from: String,
    /// Marks a feedback input (one that closes a cycle): for input stamp t the stage uses
    /// the newest message stamped at or before t - delay. Seconds, positive.
    pub feedback_delay_s: Option<f64>,
    /// Keep only the newest message when the consumer falls behind (drops are counted);
    /// the default is lossless back-pressure.
    #[serde(default)]
    pub latest_only: bool,
}

impl<'de> Deserialize<'de> for InputDecl {
    /// A string is the short form, a mapping the long form; errors inside the long form keep
    /// their field names (an untagged enum would hide them).
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct InputVisitor;

        impl<'de> Visitor<'de> for InputVisitor {
            type Value = InputDecl;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("`node/output` or a mapping `{ from: node/output, ... }`")
            }

            fn visit_str<E: de::Error>(self, reference: &str) -> Result<InputDecl, E> {
                Ok(InputDecl::Short(reference.to_owned()))
            }

            fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<InputDecl, A::Error> {
                LongInputDecl::deserialize(de::value::MapAccessDeserializer::new(map)).map(InputDecl::Long)
            }
        }

        deserializer.deserialize_any(InputVisitor)
    }
}

/// One machine.
#[derive(Debug, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct HostDecl {
    /// The nodes that run on this host.
    pub nodes: Vec<String>,
    /// How this host's zenoh session reaches the others.
    #[serde(default)]
    pub zenoh: ZenohDecl,
}

/// What to record.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RecordDecl {
    /// Topics to record: glob patterns over `node/output`, where `*` matches any text
    /// (`"*"` records everything, `"dsp/*"` every output of `dsp`).
    pub topics: Vec<String>,
    /// With `hosts:`, the host whose launcher writes the recording (`--record FILE`); the
    /// other hosts send it the recorded topics. Default: the first host.
    pub host: Option<String>,
}

/// A YAML mapping whose entries keep the order of the file.
#[derive(Debug)]
pub(crate) struct OrderedMap<V>(pub Vec<(String, V)>);

impl<V> Default for OrderedMap<V> {
    fn default() -> Self {
        Self(Vec::new())
    }
}

impl<'de, V: Deserialize<'de>> Deserialize<'de> for OrderedMap<V> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct MapVisitor<V>(PhantomData<V>);

        impl<'de, V: Deserialize<'de>> Visitor<'de> for MapVisitor<V> {
            type Value = OrderedMap<V>;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a mapping")
            }

            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
                let mut entries = Vec::new();
                while let Some(entry) = map.next_entry()? {
                    entries.push(entry);
                }
                Ok(OrderedMap(entries))
            }
        }

        deserializer.deserialize_map(MapVisitor(PhantomData))
    }
}
