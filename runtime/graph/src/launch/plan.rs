//! Planning a run: the graph wired into one [`NodeSpec`] per process (all of it, or one
//! host's share), the recorder, and the bridge where topics cross hosts. Pure: nothing starts.

use std::time::Duration;

use gprflow_record::{RecordParams, RunMetadata};
use gprflow_stage::{InputBinding, NodeSpec, OutputBinding};

use super::{LaunchError, LaunchOptions, RECORDER_NODE};
use crate::bridge::{BRIDGE_NODE, BRIDGE_STAGE, BridgeParams, Direction, Route};
use crate::{Graph, NodeKind};

/// A run as planned: one spec per process.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Run identifier.
    pub run_id: String,
    /// iceoryx2 resource prefix of the run.
    pub prefix: String,
    /// Node specs with the executable that runs each.
    pub nodes: Vec<(NodeSpec, Option<String>)>,
    /// The run is on a named bus that other processes share (`--bus`).
    pub shared_bus: bool,
    /// Topics of `--external` nodes: published from outside the run, read inside it.
    pub external: Vec<ExternalTopic>,
}

/// A topic that a process outside the run publishes (`--external`).
#[derive(Debug, Clone)]
pub struct ExternalTopic {
    /// Topic settings, as the run's readers open it.
    pub config: gprflow_bus::TopicConfig,
    /// Readers in the run: the outside publisher waits for them.
    pub readers: usize,
}

fn new_run_id() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let mut x = (nanos as u64) ^ (u64::from(std::process::id()) << 32);
    // splitmix64 finaliser: spreads the bits so that close start times differ everywhere
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    format!("{:08x}", (x ^ (x >> 31)) as u32)
}

/// Wires `graph` into node specs: all of it, or with `--host` the host's share, plus the
/// recorder and, where topics cross hosts, the bridge.
///
/// # Errors
/// [`LaunchError::Plan`] when the host is unknown, recording is asked on the wrong host, or
/// the host's zenoh settings cannot work.
pub fn plan(graph: &Graph, opts: &LaunchOptions) -> Result<Plan, LaunchError> {
    let run_id = new_run_id();
    let file = graph.file.display().to_string();
    let prefix = match &opts.bus {
        Some(name) => gprflow_bus::iox::bus_prefix(name).map_err(|e| LaunchError::Plan(format!("--bus: {e}")))?,
        None => format!("gf{run_id}_"),
    };
    check_external(graph, opts)?;
    if !opts.record_topics.is_empty() && opts.host.is_some() {
        return Err(LaunchError::Plan(format!(
            "{file}: --record-topics: not with --host (the graph's `record:` says what each host records)"
        )));
    }
    let external = |node: &str| opts.external.iter().any(|n| n == node);
    let host_of = |node: &str| {
        graph
            .hosts
            .iter()
            .find(|host| host.nodes.iter().any(|n| n == node))
            .map(|host| host.name.as_str())
    };
    let this_host = match &opts.host {
        None => None,
        Some(h) => Some(graph.hosts.iter().find(|host| &host.name == h).ok_or_else(|| {
            let known: Vec<&str> = graph.hosts.iter().map(|h| h.name.as_str()).collect();
            LaunchError::Plan(format!("{file}: no host `{h}` (hosts: {})", known.join(", ")))
        })?),
    };
    let on_host = |node: &str| this_host.is_none_or(|h| host_of(node) == Some(h.name.as_str()));
    // where the recording is written: with `--host`, one host records what `record:` names
    let record_host = graph
        .record
        .as_ref()
        .and_then(|r| r.host.clone())
        .or_else(|| graph.hosts.first().map(|h| h.name.clone()));
    let recording = match this_host {
        None => opts.record.is_some(),
        Some(host) => {
            let records_here = graph.record.is_some() && record_host.as_deref() == Some(host.name.as_str());
            match (&opts.record, records_here) {
                (Some(_), true) | (None, false) => {}
                (None, true) => {
                    return Err(LaunchError::Plan(format!(
                        "{file}: host `{}` writes the recording (`record:`); give it --record FILE",
                        host.name
                    )));
                }
                (Some(_), false) if graph.record.is_none() => {
                    return Err(LaunchError::Plan(format!(
                        "{file}: with --host, what is recorded must be in the graph: add `record: {{ topics: [\"*\"] }}`"
                    )));
                }
                (Some(_), false) => {
                    return Err(LaunchError::Plan(format!(
                        "{file}: host `{}` writes the recording, not `{}` (record.host)",
                        record_host.as_deref().unwrap_or("?"),
                        host.name
                    )));
                }
            }
            records_here
        }
    };
    // `record:` in the graph selects topics; recording happens when a file is given
    let matches_record = |topic: &str| {
        if opts.record_topics.is_empty() {
            graph.record.is_none() || graph.record_matches(topic)
        } else {
            opts.record_topics.iter().any(|g| gprflow_bus::glob_matches(g, topic))
        }
    };
    let records = |topic: &str| recording && matches_record(topic);
    // with --host, a topic recorded on another host is sent there
    let recorded_on = |topic: &str| match this_host {
        Some(_) if graph.record.is_some() && graph.record_matches(topic) => record_host.as_deref(),
        _ => None,
    };

    let mut nodes = Vec::new();
    let mut recorded = Vec::new();
    let mut routes: Vec<Route> = Vec::new();
    let mut external_topics = Vec::new();
    for node in graph.nodes.iter().filter(|n| external(&n.name)) {
        for port in &node.outputs {
            let topic = format!("{}/{}", node.name, port.name);
            let latest_only = topic_latest_only(graph, &node.name, &port.name);
            let record = records(&topic);
            if record {
                recorded.push((topic.clone(), port.msg_type.clone(), latest_only));
            }
            let (local, _) = local_readers(graph, &node.name, &port.name, &on_host);
            external_topics.push(ExternalTopic {
                config: gprflow_bus::TopicConfig::new(&topic)
                    .buffer(opts.buffer)
                    .latest_only(latest_only)
                    .msg_type(&port.msg_type),
                readers: local + usize::from(record),
            });
        }
    }
    for node in graph.nodes.iter().filter(|n| on_host(&n.name) && !external(&n.name)) {
        let mut inputs = Vec::new();
        for input in &node.inputs {
            let topic = input.topic();
            let latest_only = topic_latest_only(graph, &input.from_node, &input.from_output);
            if !on_host(&input.from_node)
                && let (Some(_), Some(from)) = (this_host, host_of(&input.from_node))
                && !routes.iter().any(|r| r.topic == topic && r.direction == Direction::In)
            {
                let (subscribers, required) = local_readers(graph, &input.from_node, &input.from_output, &on_host);
                let record = usize::from(records(&topic));
                routes.push(Route {
                    topic: topic.clone(),
                    msg_type: input.msg_type.clone(),
                    direction: Direction::In,
                    peer: from.to_owned(),
                    buffer: opts.buffer,
                    latest_only,
                    subscribers: subscribers + record,
                    required_subscribers: required + record,
                });
            }
            inputs.push(InputBinding {
                name: input.name.clone(),
                latest_only,
                topic,
                msg_type: input.msg_type.clone(),
                feedback_delay_ns: input.feedback_delay_ns,
                buffer: opts.buffer,
            });
        }
        let mut outputs = Vec::new();
        for port in &node.outputs {
            let topic = format!("{}/{}", node.name, port.name);
            let consumers = graph.consumers(&node.name, &port.name);
            let latest_only = consumers.iter().any(|(_, i)| i.latest_only);
            let record = records(&topic);
            let (local, required_local) = local_readers(graph, &node.name, &port.name, &on_host);
            // every other host that reads it (or records it) gets it through the bridge
            let mut peers: Vec<&str> = consumers
                .iter()
                .filter(|(c, _)| !on_host(&c.name))
                .filter_map(|(c, _)| host_of(&c.name))
                .chain(recorded_on(&topic).filter(|h| this_host.is_some_and(|t| t.name != *h)))
                .collect();
            peers.sort_unstable();
            peers.dedup();
            for peer in &peers {
                routes.push(Route {
                    topic: topic.clone(),
                    msg_type: port.msg_type.clone(),
                    direction: Direction::Out,
                    peer: (*peer).to_owned(),
                    buffer: opts.buffer,
                    latest_only,
                    subscribers: 0,
                    required_subscribers: 0,
                });
            }
            if record {
                recorded.push((topic.clone(), port.msg_type.clone(), latest_only));
            }
            outputs.push(OutputBinding {
                name: port.name.clone(),
                latest_only,
                topic,
                msg_type: port.msg_type.clone(),
                subscribers: local + usize::from(record) + peers.len(),
                required_subscribers: required_local + usize::from(record) + peers.len(),
                buffer: opts.buffer,
            });
        }
        let (stage, exec) = match &node.kind {
            NodeKind::Stage(s) => (s.clone(), None),
            NodeKind::Exec(e) => (e.clone(), Some(e.clone())),
        };
        nodes.push((
            NodeSpec {
                run_id: run_id.clone(),
                prefix: prefix.clone(),
                node: node.name.clone(),
                stage,
                params: node.params.clone(),
                inputs,
                outputs,
                handshake_timeout_ms: millis(opts.handshake_timeout),
            },
            exec,
        ));
    }
    // the recording host also records topics that no node of its own reads
    if let Some(host) = this_host.filter(|_| recording) {
        for (topic, msg_type) in graph.topics() {
            let (from_node, from_output) = topic.split_once('/').unwrap_or((&topic, ""));
            if on_host(from_node) || !matches_record(&topic) {
                continue;
            }
            if !routes.iter().any(|r| r.topic == topic && r.direction == Direction::In) {
                let (subscribers, required) = local_readers(graph, from_node, from_output, &on_host);
                routes.push(Route {
                    topic: topic.clone(),
                    msg_type: msg_type.clone(),
                    direction: Direction::In,
                    peer: host_of(from_node).unwrap_or(&host.name).to_owned(),
                    buffer: opts.buffer,
                    latest_only: topic_latest_only(graph, from_node, from_output),
                    subscribers: subscribers + 1,
                    required_subscribers: required + 1,
                });
            }
            recorded.push((
                topic.clone(),
                msg_type,
                topic_latest_only(graph, from_node, from_output),
            ));
        }
    }

    if let Some(path) = opts.record.as_ref().filter(|_| !recorded.is_empty() && recording) {
        let nodes_json = serde_json::to_string_pretty(
            &graph
                .nodes
                .iter()
                .map(|n| (n.name.clone(), n.params.clone()))
                .collect::<std::collections::BTreeMap<_, _>>(),
        )
        .unwrap_or_default();
        let run = RunMetadata {
            run_id: run_id.clone(),
            graph_name: graph.name.clone(),
            graph_file: graph.file.display().to_string(),
            graph_text: graph.text.clone(),
            nodes_json,
            ..RunMetadata::this_build()
        };
        let params = serde_json::json!({ "path": path.display().to_string(), "run": run });
        // check that it parses as the record stage's params
        let _: RecordParams = serde_json::from_value(params.clone()).map_err(|e| LaunchError::Plan(e.to_string()))?;
        nodes.push((
            NodeSpec {
                run_id: run_id.clone(),
                prefix: prefix.clone(),
                node: RECORDER_NODE.to_owned(),
                stage: "record".to_owned(),
                params,
                inputs: recorded
                    .into_iter()
                    .map(|(topic, msg_type, latest_only)| InputBinding {
                        name: topic.clone(),
                        topic,
                        msg_type,
                        feedback_delay_ns: None,
                        buffer: opts.buffer,
                        latest_only,
                    })
                    .collect(),
                outputs: Vec::new(),
                handshake_timeout_ms: millis(opts.handshake_timeout),
            },
            None,
        ));
    }
    if let Some(host) = this_host.filter(|_| !routes.is_empty()) {
        nodes.push((bridge_spec(graph, host, routes, &run_id, &prefix, opts)?, None));
    }
    Ok(Plan {
        run_id,
        prefix,
        nodes,
        shared_bus: opts.bus.is_some(),
        external: external_topics,
    })
}

/// `--external` names source nodes of the graph, on a named bus, without `--host`.
fn check_external(graph: &Graph, opts: &LaunchOptions) -> Result<(), LaunchError> {
    let file = graph.file.display();
    for name in &opts.external {
        let Some(node) = graph.nodes.iter().find(|n| &n.name == name) else {
            let known: Vec<&str> = graph.nodes.iter().map(|n| n.name.as_str()).collect();
            return Err(LaunchError::Plan(format!(
                "{file}: --external `{name}`: no such node (nodes: {})",
                known.join(", ")
            )));
        };
        if !node.inputs.is_empty() {
            return Err(LaunchError::Plan(format!(
                "{file}: --external `{name}`: only source nodes (no inputs) can come from outside the run; `{name}` reads {}",
                node.inputs.iter().map(|i| i.topic()).collect::<Vec<_>>().join(", ")
            )));
        }
        if opts.bus.is_none() {
            return Err(LaunchError::Plan(format!(
                "{file}: --external `{name}`: give the named bus its topics come on (--bus NAME)"
            )));
        }
        if opts.host.is_some() {
            return Err(LaunchError::Plan(format!(
                "{file}: --external `{name}`: not with --host (run the graph on one machine)"
            )));
        }
    }
    Ok(())
}

fn millis(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// Readers of `node/output` on this host: all of them, and those that are not feedback.
fn local_readers(graph: &Graph, node: &str, output: &str, on_host: &dyn Fn(&str) -> bool) -> (usize, usize) {
    let local: Vec<_> = graph
        .consumers(node, output)
        .into_iter()
        .filter(|(c, _)| on_host(&c.name))
        .collect();
    let required = local.iter().filter(|(_, i)| i.feedback_delay_ns.is_none()).count();
    (local.len(), required)
}

/// The bridge node of `host`: its zenoh settings (checked now, certificate paths made
/// absolute) and the routes.
fn bridge_spec(
    graph: &Graph,
    host: &crate::Host,
    routes: Vec<Route>,
    run_id: &str,
    prefix: &str,
    opts: &LaunchOptions,
) -> Result<NodeSpec, LaunchError> {
    let file = graph.file.display();
    let mut zenoh = host.zenoh.clone();
    if let Some(tls) = &mut zenoh.tls {
        for path in [&mut tls.root_ca, &mut tls.certificate, &mut tls.private_key] {
            if let Ok(abs) = std::path::absolute(&*path) {
                *path = abs.display().to_string();
            }
        }
    }
    gprflow_bus::zenoh::config(&zenoh)
        .map_err(|e| LaunchError::Plan(format!("{file}: hosts.{}.zenoh: {e}", host.name)))?;
    if zenoh.listen.is_empty() && zenoh.connect.is_empty() && !zenoh.scouting {
        return Err(LaunchError::Plan(format!(
            "{file}: hosts.{}.zenoh: topics cross to other hosts but the host neither listens nor connects (give `listen:` or `connect:`)",
            host.name
        )));
    }
    let params = BridgeParams {
        graph: graph.name.clone(),
        host: host.name.clone(),
        zenoh,
        remote_timeout_ms: millis(opts.remote_timeout),
        routes,
    };
    Ok(NodeSpec {
        run_id: run_id.to_owned(),
        prefix: prefix.to_owned(),
        node: BRIDGE_NODE.to_owned(),
        stage: BRIDGE_STAGE.to_owned(),
        params: serde_json::to_value(&params).map_err(|e| LaunchError::Plan(e.to_string()))?,
        inputs: Vec::new(),
        outputs: Vec::new(),
        handshake_timeout_ms: millis(opts.handshake_timeout),
    })
}

/// A topic is latest-only when any consumer asks for it (a topic-level setting of the bus).
fn topic_latest_only(graph: &Graph, node: &str, output: &str) -> bool {
    graph.consumers(node, output).iter().any(|(_, i)| i.latest_only)
}
