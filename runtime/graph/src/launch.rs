//! The launcher: turns a validated [`Graph`] into one process per node, supervises them,
//! and cleans up.
//!
//! [`plan`] is pure: it wires every node's inputs and outputs to topics (`node/output`),
//! counts each topic's consumers (for the start-up handshake), adds the recorder, and gives
//! the run a unique iceoryx2 resource prefix. [`launch`] writes each node's [`NodeSpec`] to a
//! file, starts `gprflow stage <kind> --spec FILE` (or the user's executable with the same
//! argument), forwards their logs, and waits. When a process fails, the others are asked to
//! stop (SIGTERM, then SIGKILL after a grace period) and the failure is reported with the tail
//! of its stderr. Children die with the launcher (`PR_SET_PDEATHSIG`). Afterwards nothing
//! of the run is left in shared memory.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::bridge::{BRIDGE_NODE, BRIDGE_STAGE, BridgeParams, Direction, Route};
use crate::{Graph, NodeKind};
use gprflow_record::{RecordParams, RunMetadata};
pub use gprflow_stage::PROGRESS_TAG;
use gprflow_stage::{InputBinding, NodeSpec, OutputBinding};

/// Name of the recorder node the launcher adds.
pub const RECORDER_NODE: &str = "__record";
const STDERR_TAIL_LINES: usize = 40;
const POLL: Duration = Duration::from_millis(20);

/// Errors of the launcher.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    /// The graph cannot run as asked.
    #[error("{0}")]
    Plan(String),
    /// A file or process operation failed.
    #[error("{what}: {source}")]
    Io {
        /// What we were doing.
        what: String,
        /// The error.
        source: std::io::Error,
    },
}

/// How to launch.
#[derive(Debug, Clone)]
pub struct LaunchOptions {
    /// The `gprflow` executable that runs built-in stages.
    pub exe: PathBuf,
    /// Record to this file (all topics unless the graph's `record:` names some).
    pub record: Option<PathBuf>,
    /// Run only this host's nodes.
    pub host: Option<String>,
    /// Frames each topic buffers per subscriber.
    pub buffer: usize,
    /// How long a publisher waits for its subscribers at start-up.
    pub handshake_timeout: Duration,
    /// With `--host`: how long the bridge waits for the other hosts to come up.
    pub remote_timeout: Duration,
    /// How long stopping processes get after SIGTERM before SIGKILL.
    pub stop_grace: Duration,
    /// Log filter handed to built-in stages (`--log`).
    pub log_filter: Option<String>,
}

impl LaunchOptions {
    /// Defaults for running `exe`'s stages.
    pub fn new(exe: PathBuf) -> Self {
        Self {
            exe,
            record: None,
            host: None,
            buffer: 16,
            handshake_timeout: Duration::from_secs(30),
            remote_timeout: Duration::from_secs(120),
            stop_grace: Duration::from_secs(5),
            log_filter: None,
        }
    }
}

/// A run as planned: one spec per process.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Run identifier.
    pub run_id: String,
    /// iceoryx2 resource prefix of the run.
    pub prefix: String,
    /// Node specs with the executable that runs each.
    pub nodes: Vec<(NodeSpec, Option<String>)>,
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
    let prefix = format!("gf{run_id}_");
    let file = graph.file.display().to_string();
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
    let matches_record = |topic: &str| graph.record.is_none() || graph.record_matches(topic);
    let records = |topic: &str| recording && matches_record(topic);
    // with --host, a topic recorded on another host is sent there
    let recorded_on = |topic: &str| match this_host {
        Some(_) if graph.record.is_some() && graph.record_matches(topic) => record_host.as_deref(),
        _ => None,
    };

    let mut nodes = Vec::new();
    let mut recorded = Vec::new();
    let mut routes: Vec<Route> = Vec::new();
    for node in graph.nodes.iter().filter(|n| on_host(&n.name)) {
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
    Ok(Plan { run_id, prefix, nodes })
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

/// What the launcher tells its observer.
#[derive(Debug)]
pub enum LaunchEvent<'a> {
    /// A process started.
    Started {
        /// Node.
        node: &'a str,
        /// Process id.
        pid: u32,
    },
    /// A stage reported progress.
    Progress {
        /// Node.
        node: &'a str,
        /// Units done.
        done: u64,
        /// Units in total.
        total: u64,
    },
    /// A line a stage wrote to stderr.
    Log {
        /// Node.
        node: &'a str,
        /// The line.
        line: &'a str,
    },
    /// A process ended.
    Exited {
        /// Node.
        node: &'a str,
        /// How.
        status: &'a str,
    },
    /// Stopping every process (failure or interrupt).
    Stopping {
        /// Why.
        reason: &'a str,
    },
}

/// Receives [`LaunchEvent`]s (progress bars, logs).
pub trait LaunchObserver {
    /// One event.
    fn event(&mut self, event: LaunchEvent<'_>);
}

/// How one process ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeOutcome {
    /// Node.
    pub node: String,
    /// Exit code, when it exited.
    pub code: Option<i32>,
    /// Signal, when one killed it.
    pub signal: Option<i32>,
    /// Last lines of its stderr.
    pub stderr_tail: Vec<String>,
    /// Stopped by the launcher (after another failure or an interrupt).
    pub stopped_by_launcher: bool,
}

impl NodeOutcome {
    /// Exited with code 0.
    pub fn succeeded(&self) -> bool {
        self.code == Some(0)
    }

    /// Human description of how it ended.
    pub fn describe(&self) -> String {
        match (self.code, self.signal) {
            (Some(c), _) => format!("exit code {c}"),
            (None, Some(s)) => format!("killed by signal {s}"),
            (None, None) => "unknown".to_owned(),
        }
    }
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct LaunchReport {
    /// Run identifier.
    pub run_id: String,
    /// Every process, in graph order.
    pub nodes: Vec<NodeOutcome>,
    /// Interrupted by SIGINT/SIGTERM.
    pub interrupted: bool,
    /// The first process that failed on its own.
    pub first_failure: Option<String>,
    /// Shared-memory files of the run removed after the processes ended (left by killed
    /// processes).
    pub cleaned_up: Vec<String>,
    /// Wall time.
    pub wall: Duration,
}

impl LaunchReport {
    /// Every process succeeded and nobody interrupted the run.
    pub fn succeeded(&self) -> bool {
        !self.interrupted && self.first_failure.is_none() && self.nodes.iter().all(NodeOutcome::succeeded)
    }
}

struct Running {
    node: String,
    child: Child,
    tail: Arc<Mutex<VecDeque<String>>>,
    reader: Option<std::thread::JoinHandle<()>>,
    status: Option<ExitStatus>,
    stopped_by_launcher: bool,
}

enum Line {
    Log(usize, String),
    Progress(usize, u64, u64),
}

fn spawn(
    spec: &NodeSpec,
    exec: Option<&str>,
    spec_file: &Path,
    opts: &LaunchOptions,
    index: usize,
    lines: SyncSender<Line>,
) -> Result<Running, LaunchError> {
    let mut cmd = match exec {
        Some(e) => Command::new(e),
        None => {
            let mut c = Command::new(&opts.exe);
            c.arg("stage").arg(&spec.stage);
            if let Some(filter) = &opts.log_filter {
                c.arg("--log").arg(filter);
            }
            c
        }
    };
    cmd.arg("--spec")
        .arg(spec_file)
        .stdin(Stdio::null())
        .stdout(Stdio::inherit())
        .stderr(Stdio::piped());
    // SAFETY: the closure runs between fork and exec and only calls prctl, which is
    // async-signal-safe.
    unsafe {
        cmd.pre_exec(|| {
            nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM).map_err(std::io::Error::from)
        });
    }
    let what = match exec {
        Some(e) => format!("node `{}`: cannot start `{e}`", spec.node),
        None => format!("node `{}`: cannot start `{}`", spec.node, opts.exe.display()),
    };
    let mut child = cmd.spawn().map_err(|source| LaunchError::Io { what, source })?;
    let tail = Arc::new(Mutex::new(VecDeque::with_capacity(STDERR_TAIL_LINES)));
    let reader = child.stderr.take().map(|stderr| {
        let tail = tail.clone();
        std::thread::Builder::new()
            .name(format!("stderr-{}", spec.node))
            .spawn(move || forward_stderr(stderr, index, &tail, &lines))
    });
    let reader = match reader {
        Some(Ok(handle)) => Some(handle),
        Some(Err(source)) => {
            return Err(LaunchError::Io {
                what: "cannot start a log reader thread".to_owned(),
                source,
            });
        }
        None => None,
    };
    Ok(Running {
        node: spec.node.clone(),
        child,
        tail,
        reader,
        status: None,
        stopped_by_launcher: false,
    })
}

fn forward_stderr(
    stderr: std::process::ChildStderr,
    index: usize,
    tail: &Mutex<VecDeque<String>>,
    lines: &SyncSender<Line>,
) {
    for line in BufReader::new(stderr).lines() {
        let Ok(line) = line else { break };
        if let Some(rest) = line.strip_prefix(PROGRESS_TAG) {
            let mut nums = rest.split_whitespace().filter_map(|n| n.parse::<u64>().ok());
            if let (Some(done), Some(total)) = (nums.next(), nums.next()) {
                let _ = lines.send(Line::Progress(index, done, total));
            }
            continue;
        }
        {
            let mut t = tail.lock().unwrap_or_else(PoisonError::into_inner);
            if t.len() == STDERR_TAIL_LINES {
                t.pop_front();
            }
            t.push_back(line.clone());
        }
        let _ = lines.send(Line::Log(index, line));
    }
}

fn signal(child: &Child, sig: nix::sys::signal::Signal) {
    if let Ok(pid) = i32::try_from(child.id()) {
        let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), sig);
    }
}

fn drain(rx: &Receiver<Line>, running: &[Running], observer: &mut dyn LaunchObserver) {
    while let Ok(line) = rx.try_recv() {
        match line {
            Line::Log(i, l) => observer.event(LaunchEvent::Log {
                node: &running[i].node,
                line: &l,
            }),
            Line::Progress(i, done, total) => observer.event(LaunchEvent::Progress {
                node: &running[i].node,
                done,
                total,
            }),
        }
    }
}

/// Runs `plan` to the end, or until a process fails or `stop` turns true.
///
/// # Errors
/// [`LaunchError::Io`] when a spec file cannot be written or a process cannot start (the
/// ones already started are stopped first).
pub fn launch(
    plan: &Plan,
    opts: &LaunchOptions,
    stop: &Arc<AtomicBool>,
    observer: &mut dyn LaunchObserver,
) -> Result<LaunchReport, LaunchError> {
    let started = Instant::now();
    let dir = std::env::temp_dir().join(format!("gprflow-{}", plan.run_id));
    std::fs::create_dir_all(&dir).map_err(|source| LaunchError::Io {
        what: format!("cannot create {}", dir.display()),
        source,
    })?;
    let (tx, rx) = sync_channel::<Line>(4096);
    let mut running: Vec<Running> = Vec::new();
    let mut start_error = None;
    for (i, (spec, exec)) in plan.nodes.iter().enumerate() {
        let file = dir.join(format!("{}.json", spec.node));
        let written = serde_json::to_vec_pretty(spec)
            .map_err(std::io::Error::other)
            .and_then(|json| std::fs::write(&file, json));
        if let Err(source) = written {
            start_error = Some(LaunchError::Io {
                what: format!("cannot write {}", file.display()),
                source,
            });
            break;
        }
        match spawn(spec, exec.as_deref(), &file, opts, i, tx.clone()) {
            Ok(r) => {
                observer.event(LaunchEvent::Started {
                    node: &spec.node,
                    pid: r.child.id(),
                });
                running.push(r);
            }
            Err(e) => {
                start_error = Some(e);
                break;
            }
        }
    }
    drop(tx);

    let mut first_failure = None;
    let mut interrupted = false;
    let mut stopping_since: Option<Instant> = None;
    let mut killed = false;
    if start_error.is_some() {
        stopping_since = Some(Instant::now());
        for r in &mut running {
            r.stopped_by_launcher = true;
            signal(&r.child, nix::sys::signal::Signal::SIGTERM);
        }
    }
    while running.iter().any(|r| r.status.is_none()) {
        drain(&rx, &running, observer);
        for r in &mut running {
            if r.status.is_some() {
                continue;
            }
            if let Ok(Some(status)) = r.child.try_wait() {
                r.status = Some(status);
                let outcome = describe_status(status);
                observer.event(LaunchEvent::Exited {
                    node: &r.node,
                    status: &outcome,
                });
                if !status.success() && stopping_since.is_none() && first_failure.is_none() {
                    first_failure = Some(r.node.clone());
                }
            }
        }
        let want_stop = first_failure.is_some() || stop.load(Ordering::Relaxed);
        if want_stop && stopping_since.is_none() {
            interrupted = first_failure.is_none();
            let reason = match &first_failure {
                Some(n) => format!("node `{n}` failed"),
                None => "interrupted".to_owned(),
            };
            observer.event(LaunchEvent::Stopping { reason: &reason });
            stopping_since = Some(Instant::now());
            for r in running.iter_mut().filter(|r| r.status.is_none()) {
                r.stopped_by_launcher = true;
                signal(&r.child, nix::sys::signal::Signal::SIGTERM);
            }
        }
        if let Some(since) = stopping_since
            && !killed
            && since.elapsed() > opts.stop_grace
        {
            killed = true;
            for r in running.iter().filter(|r| r.status.is_none()) {
                signal(&r.child, nix::sys::signal::Signal::SIGKILL);
            }
        }
        std::thread::sleep(POLL);
    }
    for r in &mut running {
        if let Some(h) = r.reader.take() {
            let _ = h.join();
        }
    }
    drain(&rx, &running, observer);
    let cleaned_up = cleanup_run(&plan.prefix);
    let _ = std::fs::remove_dir_all(&dir);
    if let Some(e) = start_error {
        return Err(e);
    }
    Ok(LaunchReport {
        run_id: plan.run_id.clone(),
        nodes: running
            .iter()
            .map(|r| NodeOutcome {
                node: r.node.clone(),
                code: r.status.and_then(|s| s.code()),
                signal: r.status.and_then(|s| s.signal()),
                stderr_tail: r
                    .tail
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .iter()
                    .cloned()
                    .collect(),
                stopped_by_launcher: r.stopped_by_launcher,
            })
            .collect(),
        interrupted,
        first_failure,
        cleaned_up,
        wall: started.elapsed(),
    })
}

fn describe_status(status: ExitStatus) -> String {
    match (status.code(), status.signal()) {
        (Some(c), _) => format!("exit code {c}"),
        (None, Some(s)) => format!("killed by signal {s}"),
        _ => "ended".to_owned(),
    }
}

/// Where iceoryx2 keeps a run's files: shared memory and its node/service directory.
pub fn run_resource_dirs() -> Vec<PathBuf> {
    vec![PathBuf::from("/dev/shm"), PathBuf::from("/tmp/iceoryx2")]
}

/// Paths of resources left by the run with `prefix` (empty after a clean run).
pub fn leftover_resources(prefix: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for dir in run_resource_dirs() {
        collect_with_prefix(&dir, prefix, &mut found, 3);
    }
    found
}

fn collect_with_prefix(dir: &Path, prefix: &str, out: &mut Vec<PathBuf>, depth: u32) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let path = e.path();
        let name = e.file_name();
        if name.to_string_lossy().starts_with(prefix) {
            out.push(path);
        } else if depth > 0 && path.is_dir() {
            collect_with_prefix(&path, prefix, out, depth - 1);
        }
    }
}

/// Removes what processes of the run with `prefix` left behind: first through iceoryx2's
/// own dead-node cleanup, then any file still carrying the run's prefix (the prefix is
/// unique to the run, so nothing else is touched). iceoryx2 keeps one global management
/// segment per prefix on purpose; it is removed silently. Returns what else had to be
/// removed: resources of processes that did not exit cleanly.
pub fn cleanup_run(prefix: &str) -> Vec<String> {
    let stop = Arc::new(AtomicBool::new(false));
    if let Ok(t) = gprflow_bus::iox::IoxTransport::new("gprflow_cleanup", prefix, stop) {
        t.cleanup_dead_nodes();
    }
    let mut removed = Vec::new();
    for path in leftover_resources(prefix) {
        let gone = if path.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        // a node's own directory (named by node id) is left empty: remove it too
        if let Some(parent) = path
            .parent()
            .filter(|p| p.parent().is_some_and(|g| g.ends_with("nodes")))
        {
            let _ = std::fs::remove_dir(parent);
        }
        let expected = path.extension().is_some_and(|e| e == "global_mgmt");
        if gone.is_ok() && !expected {
            removed.push(path.display().to_string());
        }
    }
    removed
}
