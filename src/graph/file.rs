//! The graph file format as written: typed serde structs, one per YAML mapping, from which
//! the JSON schema is generated. Nothing here is checked beyond its shape; see `check`.

use std::collections::BTreeMap;
use std::fmt;
use std::marker::PhantomData;

use schemars::JsonSchema;
use serde::Deserialize;
use serde::de::{self, Deserializer, MapAccess, Visitor};

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
    /// Stage kind that this node runs (`gprflow stage --list` names them).
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

/// Zenoh settings of one host: how its bridge reaches the other hosts. Nothing is listened
/// on or connected to that is not named here, and multicast scouting is off unless asked.
#[derive(Debug, Clone, Default, PartialEq, Deserialize, serde::Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ZenohDecl {
    /// Endpoints to listen on, each an address of this host (`tcp/10.0.0.1:7447`,
    /// `tls/robot.local:7447`). None by default: a host that only connects opens no port.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Endpoints of other hosts to connect to (`tcp/10.0.0.1:7447`).
    #[serde(default)]
    pub connect: Vec<String>,
    /// Zenoh mode: `peer` (the default), `client` or `router`.
    pub mode: Option<String>,
    /// Find other hosts by UDP multicast scouting (and gossip) as well; off by default.
    #[serde(default)]
    pub scouting: bool,
    /// Zenoh link lease in milliseconds: a link silent this long is closed (zenoh's default
    /// 10000). The bridge reconnects and resends what was not delivered.
    pub lease_ms: Option<u64>,
    /// How long the bridge waits for word from the other side of a topic (a link that is
    /// down) before it fails, naming the topic and the frames not delivered; default 60.
    pub link_timeout_s: Option<f64>,
    /// Mutual TLS: use `tls/` endpoints; every host presents a certificate signed by `root_ca`.
    pub tls: Option<TlsDecl>,
    /// Certificate common names of the hosts allowed to exchange gprflow topics with this one
    /// (zenoh access control, everything else denied); needs `tls`. Empty: any host whose
    /// certificate the root CA signed.
    #[serde(default)]
    pub allow: Vec<String>,
}

/// Certificate files of one host (PEM).
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize, serde::Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TlsDecl {
    /// The certificate authority that signed every host's certificate.
    pub root_ca: String,
    /// This host's certificate; its subject names must include the address others connect to.
    pub certificate: String,
    /// This host's private key.
    pub private_key: String,
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
