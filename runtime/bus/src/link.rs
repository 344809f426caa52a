//! How one host's zenoh session reaches the others: the settings a graph file gives per host
//! (`hosts.NAME.zenoh`), kept here beside the transport that uses them so that the graph
//! file format depends on the bus and never the other way.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Zenoh settings of one host: how its bridge reaches the other hosts. Nothing is listened
/// on or connected to that is not named here, and multicast scouting is off unless asked.
#[derive(Debug, Clone, Default, PartialEq, Deserialize, Serialize, JsonSchema)]
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
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TlsDecl {
    /// The certificate authority that signed every host's certificate.
    pub root_ca: String,
    /// This host's certificate; its subject names must include the address others connect to.
    pub certificate: String,
    /// This host's private key.
    pub private_key: String,
}
