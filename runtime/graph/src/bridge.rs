//! The bridge node: carries the topics that cross hosts between iceoryx2 and zenoh.
//!
//! The launcher of each host adds one bridge node (`__bridge`) when some of the host's
//! topics are read on another host or it reads some from another host. The bridge holds the
//! host's one zenoh session (the endpoints of the graph's `hosts.NAME.zenoh`) and relays
//! every crossing topic on its own thread:
//!
//! - out: an iceoryx2 subscriber of the local topic, a zenoh publisher keyed for the reading
//!   host (`gprflow/GRAPH/HOST/node/output`);
//! - in: a zenoh subscriber of the topic keyed for this host, an iceoryx2 publisher of the
//!   same topic for the local readers.
//!
//! Frames are relayed as they are (header, seq, stamp, watermarks, end of stream), so the
//! stages on either side see what they would see on one machine: the same sequence numbers,
//! the same stamp-ordered merge, end of stream that finishes the run by itself. Lossless
//! back-pressure and recovery from a link that goes down are the zenoh transport's
//! ([`gprflow_bus::zenoh`]).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::ZenohDecl;
use gprflow_bus::iox::IoxTransport;
use gprflow_bus::zenoh::{self as zbus, ZenohTransport};
use gprflow_bus::{self as bus, BusError, Frame, FrameKind, Publisher, Subscriber, TopicConfig, Transport};
use gprflow_stage::{NodeSpec, StageError};

/// Stage kind of the bridge node, as the launcher names it.
pub const BRIDGE_STAGE: &str = "bridge";
/// Node name of the bridge the launcher adds.
pub const BRIDGE_NODE: &str = "__bridge";

/// Parameters of the bridge node (written by the launcher).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BridgeParams {
    /// The graph's name (part of every key).
    pub graph: String,
    /// This host.
    pub host: String,
    /// This host's zenoh settings, certificate paths made absolute.
    pub zenoh: ZenohDecl,
    /// How long to wait for the other hosts to come up, ms.
    pub remote_timeout_ms: u64,
    /// The topics to relay.
    pub routes: Vec<Route>,
}

/// Which way a route goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// From this host's node to `peer`.
    Out,
    /// From `peer`'s node to this host's readers.
    In,
}

/// One topic crossing between this host and `peer`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Route {
    /// Topic, `node/output`.
    pub topic: String,
    /// Message type (logs; the type the local bus keeps with the topic).
    pub msg_type: String,
    /// Which way.
    pub direction: Direction,
    /// The other host.
    pub peer: String,
    /// Frames buffered per subscriber, the same on every side of the topic.
    pub buffer: usize,
    /// Latest-only topic.
    pub latest_only: bool,
    /// `in` routes: local readers to wait for at start-up.
    #[serde(default)]
    pub subscribers: usize,
    /// `in` routes: local readers every frame must reach.
    #[serde(default)]
    pub required_subscribers: usize,
}

impl Route {
    fn topic_config(&self) -> TopicConfig {
        TopicConfig::new(&self.topic)
            .buffer(self.buffer)
            .latest_only(self.latest_only)
            .msg_type(&self.msg_type)
    }

    fn describe(&self) -> String {
        match self.direction {
            Direction::Out => format!("`{}` to host `{}`", self.topic, self.peer),
            Direction::In => format!("`{}` from host `{}`", self.topic, self.peer),
        }
    }
}

/// What one route carried.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RouteReport {
    /// The route.
    pub route: String,
    /// Data frames relayed.
    pub frames: u64,
    /// Payload bytes relayed.
    pub bytes: u64,
    /// `out` routes: frames the zenoh side had to send again.
    pub resent: u64,
}

/// Runs the bridge node until every route has relayed end of stream (or one fails).
///
/// # Errors
/// Bad parameters, a zenoh session that cannot open, or the first route that failed, named.
pub fn run_bridge(spec: &NodeSpec, stop: &Arc<AtomicBool>) -> Result<Vec<RouteReport>, StageError> {
    let params: BridgeParams =
        serde_json::from_value(spec.params.clone()).map_err(|e| StageError::failed(format!("bridge params: {e}")))?;
    let session_prefix = zbus::key_prefix(&params.graph, &params.host).map_err(StageError::failed)?;
    let zenoh = ZenohTransport::open(&params.zenoh, &session_prefix, stop.clone())?;
    let handshake = Duration::from_millis(spec.handshake_timeout_ms);
    let remote = Duration::from_millis(params.remote_timeout_ms);
    tracing::info!(
        host = params.host,
        listen = ?params.zenoh.listen,
        connect = ?params.zenoh.connect,
        routes = params.routes.len(),
        "bridge up"
    );
    let threads: Vec<_> = params
        .routes
        .iter()
        .map(|route| {
            let route = route.clone();
            let prefix = match route.direction {
                Direction::Out => zbus::key_prefix(&params.graph, &route.peer),
                Direction::In => Ok(session_prefix.clone()),
            };
            let zenoh = prefix.map(|p| zenoh.with_prefix(&p));
            let (node, iox_prefix, stop) = (spec.node.clone(), spec.prefix.clone(), stop.clone());
            std::thread::Builder::new()
                .name(format!("bridge-{}", route.topic))
                .spawn(move || {
                    let result = zenoh.map_err(|what| BusError::Transport {
                        topic: route.topic.clone(),
                        what,
                    });
                    let result = result.and_then(|zenoh| {
                        let iox = IoxTransport::new(&node, &iox_prefix, stop.clone())?;
                        match route.direction {
                            Direction::Out => relay_out(&route, &iox, &zenoh, handshake, remote, &stop),
                            Direction::In => relay_in(&route, &iox, &zenoh, handshake, remote, &stop),
                        }
                    });
                    if result.as_ref().is_err_and(|e| !matches!(e, BusError::Shutdown)) {
                        // one route failing ends the run: the launcher stops the others
                        stop.store(true, Ordering::Relaxed);
                    }
                    (route, result)
                })
        })
        .collect::<Result<_, _>>()
        .map_err(|e| StageError::failed(format!("cannot start a bridge thread: {e}")))?;
    let mut reports = Vec::new();
    let mut failure = None;
    for thread in threads {
        let Ok((route, result)) = thread.join() else {
            failure.get_or_insert_with(|| "a bridge thread panicked".to_owned());
            continue;
        };
        match result {
            Ok(report) => {
                tracing::info!(
                    route = report.route,
                    frames = report.frames,
                    bytes = report.bytes,
                    resent = report.resent,
                    "relayed"
                );
                reports.push(report);
            }
            // the failing route is the one to report, not the ones it stopped
            Err(BusError::Shutdown) => {}
            Err(e) => {
                failure.get_or_insert_with(|| format!("route {}: {e}", route.describe()));
            }
        }
    }
    match failure {
        Some(f) => Err(StageError::failed(f)),
        None if stop.load(Ordering::Relaxed) && reports.len() < params.routes.len() => {
            Err(StageError::Bus(BusError::Shutdown))
        }
        None => Ok(reports),
    }
}

fn copy_into(
    payload: &[u8],
) -> impl FnMut(gprflow_msg::PayloadWriter<'_>) -> Result<gprflow_msg::Written, gprflow_msg::MsgError> + '_ {
    move |mut out| {
        out.put(payload)?;
        out.finish()
    }
}

/// Takes the next frame from `sub`, waiting while there is none.
fn next_frame(sub: &mut dyn Subscriber, stop: &dyn Fn() -> bool) -> Result<Frame, BusError> {
    loop {
        if let Some(frame) = sub.try_receive()? {
            return Ok(frame);
        }
        if stop() {
            return Err(BusError::Shutdown);
        }
        sub.wait(Duration::from_millis(50))?;
    }
}

/// Passes every frame from `from` to `to` as it is, through end of stream; each must reach
/// `required` subscribers.
fn relay(
    route: &Route,
    from: &mut dyn Subscriber,
    to: &mut dyn Publisher,
    required: usize,
    stopped: &dyn Fn() -> bool,
) -> Result<RouteReport, BusError> {
    let mut report = RouteReport {
        route: route.describe(),
        frames: 0,
        bytes: 0,
        resent: 0,
    };
    loop {
        let frame = next_frame(from, stopped)?;
        let payload = frame.payload();
        let reached = to.send_with(frame.header, payload.len(), &mut copy_into(payload))?;
        if reached < required {
            return Err(BusError::SubscriberLost {
                topic: route.topic.clone(),
                seq: frame.header.seq,
                reached,
                expected: required,
            });
        }
        match frame.kind() {
            Some(FrameKind::Data) => {
                report.frames += 1;
                report.bytes += payload.len() as u64;
            }
            Some(FrameKind::EndOfStream) => return Ok(report),
            _ => {}
        }
    }
}

fn relay_out(
    route: &Route,
    iox: &IoxTransport,
    zenoh: &ZenohTransport,
    handshake: Duration,
    remote: Duration,
    stop: &AtomicBool,
) -> Result<RouteReport, BusError> {
    let stopped = || stop.load(Ordering::Relaxed);
    let config = route.topic_config();
    let mut local = iox.subscriber(&config)?;
    local.attach(handshake, &stopped)?;
    let mut out = zenoh.zenoh_publisher(&config)?;
    let started = Instant::now();
    bus::wait_for_subscribers(&out, 1, remote, &stopped).map_err(|e| match e {
        BusError::HandshakeTimeout { .. } => BusError::Transport {
            topic: route.topic.clone(),
            what: format!(
                "host `{}` did not subscribe within {:?}: is `gprflow launch --host {}` running and reachable, and allowed (`tls`, `allow`)?",
                route.peer,
                started.elapsed(),
                route.peer
            ),
        },
        other => other,
    })?;
    let mut report = relay(route, local.as_mut(), &mut out, 1, &stopped)?;
    drop(local);
    // everything must be taken on the other side before the only copy goes away
    out.drain(&stopped)?;
    report.resent = out.resent();
    Ok(report)
}

fn relay_in(
    route: &Route,
    iox: &IoxTransport,
    zenoh: &ZenohTransport,
    handshake: Duration,
    remote: Duration,
    stop: &AtomicBool,
) -> Result<RouteReport, BusError> {
    let stopped = || stop.load(Ordering::Relaxed);
    let config = route.topic_config();
    // the local publisher first: local readers attach to it while the other host comes up
    let mut local = iox.publisher(&config)?;
    let mut remote_in = zenoh.zenoh_subscriber(&config)?;
    remote_in.attach(remote, &stopped).map_err(|e| match e {
        BusError::HandshakeTimeout { waited, .. } => BusError::Transport {
            topic: route.topic.clone(),
            what: format!(
                "host `{}` did not publish within {waited:?}: is `gprflow launch --host {}` running and reachable, and allowed (`tls`, `allow`)?",
                route.peer, route.peer
            ),
        },
        other => other,
    })?;
    bus::wait_for_subscribers(local.as_ref(), route.subscribers, handshake, &stopped)?;
    let report = relay(
        route,
        &mut remote_in,
        local.as_mut(),
        route.required_subscribers,
        &stopped,
    )?;
    // the payloads live in this process's shared memory until the readers are done
    while local.subscriber_count() > 0 && !stopped() {
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(remote_in);
    Ok(report)
}
