//! The runtime that runs one stage as one process: opens its topics, merges its inputs in
//! stamp order, calls the stage, and reports.
//!
//! ## Stamp-ordered merge
//! Each input keeps at most one pending data frame (its head) and a watermark: the
//! publisher's promise that nothing stamped earlier will follow. The runtime delivers the
//! head with the smallest stamp once every other input either has a later head or a
//! watermark past it; ties go to feedback inputs first, then to inputs in declaration
//! order. The delivery order therefore depends only on the stamps, never on timing.
//!
//! A feedback input with delay `d` takes part as if each of its messages were stamped
//! `stamp + d`: for an input stamped `t` the stage has seen every feedback message stamped
//! at or before `t - d`, and no newer one. Feedback inputs never hold back the stage's own
//! watermark and need not end for the stage to finish, so cycles closed through them
//! cannot deadlock.
//!
//! Before it blocks, a stage promises downstream the smallest stamp it may still deliver
//! (a watermark frame), so consumers of several topics never wait on a stage that has
//! nothing to say. Stages must stamp outputs no earlier than the input that caused them;
//! the [`Outbox`] rejects a stamp earlier than a promise already made.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use serde::{Deserialize, Serialize};

use super::{ParamError, Stage, parse_params};
use gprflow_bus::{self as bus, BusError, Delivery, Frame, Inbox, Outbox, TopicConfig, Transport};
use gprflow_msg::{CdrDecode, Message};

const WAIT_SLICE: Duration = Duration::from_millis(100);

/// Errors of a running stage.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// The bus failed.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// Bad parameters. (Not a `#[source]`: the message already says it, and a chain printer
    /// would say it twice.)
    #[error("params: {0}")]
    Params(ParamError),
    /// A port the stage asked for is not bound or has another type.
    #[error("port `{port}`: {reason}")]
    Port {
        /// Port name.
        port: String,
        /// What is wrong.
        reason: String,
    },
    /// A stage-specific failure: the stage's own error, whose cause chain (`source()`) is
    /// kept, or a message.
    #[error(transparent)]
    Failed(Box<dyn std::error::Error + Send + Sync + 'static>),
}

impl From<ParamError> for StageError {
    fn from(e: ParamError) -> Self {
        Self::Params(e)
    }
}

impl StageError {
    /// A stage-specific failure: an error (its cause chain kept) or a message (`String`,
    /// `&str`).
    pub fn failed(e: impl Into<Box<dyn std::error::Error + Send + Sync + 'static>>) -> Self {
        Self::Failed(e.into())
    }
}

/// One input of a node as the launcher wired it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputBinding {
    /// Input port name.
    pub name: String,
    /// Topic it reads (`node/output`).
    pub topic: String,
    /// Message type.
    pub msg_type: String,
    /// Feedback delay, when the input closes a cycle.
    #[serde(default)]
    pub feedback_delay_ns: Option<i64>,
    /// Topic settings, identical for every side of the topic.
    pub buffer: usize,
    /// Topic is latest-only.
    #[serde(default)]
    pub latest_only: bool,
}

/// One output of a node as the launcher wired it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputBinding {
    /// Output port name.
    pub name: String,
    /// Topic it writes (`node/output`).
    pub topic: String,
    /// Message type.
    pub msg_type: String,
    /// Subscribers to wait for before the first message.
    pub subscribers: usize,
    /// Subscribers that must be reached by every message (feedback consumers may leave
    /// first and are not counted).
    pub required_subscribers: usize,
    /// Topic settings, identical for every side of the topic.
    pub buffer: usize,
    /// Topic is latest-only.
    #[serde(default)]
    pub latest_only: bool,
}

/// Everything a stage process needs to know, written by the launcher as JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSpec {
    /// Run identifier.
    pub run_id: String,
    /// iceoryx2 resource prefix shared by every process of the run.
    pub prefix: String,
    /// Node name in the graph.
    pub node: String,
    /// Stage kind (or the executable for `exec:` nodes).
    pub stage: String,
    /// Parameters, variables already substituted.
    pub params: serde_json::Value,
    /// Wired inputs.
    pub inputs: Vec<InputBinding>,
    /// Wired outputs.
    pub outputs: Vec<OutputBinding>,
    /// How long to wait for subscribers at start-up, ms.
    pub handshake_timeout_ms: u64,
}

impl InputBinding {
    /// Topic settings of this input.
    pub fn topic_config(&self) -> TopicConfig {
        TopicConfig::new(&self.topic)
            .buffer(self.buffer)
            .latest_only(self.latest_only)
            .msg_type(&self.msg_type)
    }
}

impl OutputBinding {
    /// Topic settings of this output.
    pub fn topic_config(&self) -> TopicConfig {
        TopicConfig::new(&self.topic)
            .buffer(self.buffer)
            .latest_only(self.latest_only)
            .msg_type(&self.msg_type)
    }
}

/// Identifies one input of a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct InputId(pub usize);

/// A typed handle on one output of a stage.
#[derive(Debug)]
pub struct Output<M> {
    index: usize,
    _msg: std::marker::PhantomData<fn(&M)>,
}

impl<M> Clone for Output<M> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<M> Copy for Output<M> {}

impl<M> Output<M> {
    /// Index among the node's outputs.
    pub fn index(&self) -> usize {
        self.index
    }
}

/// The ports of a node, for a stage to look its handles up at creation.
#[derive(Debug)]
pub struct Ports {
    inputs: Vec<InputBinding>,
    outputs: Vec<OutputBinding>,
    node: String,
}

impl Ports {
    /// Ports of `spec`.
    pub fn new(spec: &NodeSpec) -> Self {
        Self {
            inputs: spec.inputs.clone(),
            outputs: spec.outputs.clone(),
            node: spec.node.clone(),
        }
    }

    /// Node name.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// The input named `name`, if wired.
    pub fn input(&self, name: &str) -> Option<InputId> {
        self.inputs.iter().position(|i| i.name == name).map(InputId)
    }

    /// Every wired input.
    pub fn inputs(&self) -> &[InputBinding] {
        &self.inputs
    }

    /// Every wired output.
    pub fn outputs(&self) -> &[OutputBinding] {
        &self.outputs
    }

    /// The output named `name`, checked to carry `M`.
    ///
    /// # Errors
    /// [`StageError::Port`] when missing or of another type.
    pub fn output<M: Message>(&self, name: &str) -> Result<Output<M>, StageError> {
        let index = self
            .outputs
            .iter()
            .position(|o| o.name == name)
            .ok_or_else(|| StageError::Port {
                port: name.to_owned(),
                reason: "not an output of this node".to_owned(),
            })?;
        if self.outputs[index].msg_type != M::TYPE_NAME {
            return Err(StageError::Port {
                port: name.to_owned(),
                reason: format!(
                    "wired as {}, the stage sends {}",
                    self.outputs[index].msg_type,
                    M::TYPE_NAME
                ),
            });
        }
        Ok(Output {
            index,
            _msg: std::marker::PhantomData,
        })
    }
}

/// One delivered input message.
#[derive(Debug)]
pub struct Input<'a> {
    /// Which input.
    pub id: InputId,
    binding: &'a InputBinding,
    frame: &'a Frame,
}

impl<'a> Input<'a> {
    /// Input port name.
    pub fn name(&self) -> &str {
        &self.binding.name
    }
    /// Topic.
    pub fn topic(&self) -> &str {
        &self.binding.topic
    }
    /// Message type name.
    pub fn msg_type(&self) -> &str {
        &self.binding.msg_type
    }
    /// Sequence number on the topic.
    pub fn seq(&self) -> u64 {
        self.frame.header.seq
    }
    /// Stamp, ns.
    pub fn stamp_ns(&self) -> i64 {
        self.frame.header.stamp_ns
    }
    /// The CDR payload, in place.
    pub fn payload(&self) -> &'a [u8] {
        self.frame.payload()
    }
    /// Decodes the payload (arrays are borrowed in place when aligned).
    ///
    /// # Errors
    /// [`BusError::Decode`] naming topic and seq.
    pub fn decode<M: CdrDecode<'a> + Message>(&self) -> Result<M, StageError> {
        Ok(bus::decode_frame(&self.binding.topic, self.frame)?)
    }
}

/// What a source stage says after producing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Produce {
    /// Call again.
    More,
    /// The source is exhausted.
    Done,
}

/// The outputs of a running stage.
#[derive(Debug)]
pub struct Outputs {
    outboxes: Vec<Outbox>,
}

impl Outputs {
    /// Sends `msg` on `port`.
    ///
    /// # Errors
    /// Bus errors.
    pub fn send<M: Message>(&mut self, port: Output<M>, msg: &M) -> Result<(), StageError> {
        self.outboxes[port.index].send(msg)?;
        Ok(())
    }

    /// Sends an encoded payload on output `index` (replay, bridges).
    ///
    /// # Errors
    /// Bus errors, or an index out of range.
    pub fn send_bytes(&mut self, index: usize, stamp_ns: i64, payload: &[u8]) -> Result<(), StageError> {
        let outbox = self.outboxes.get_mut(index).ok_or_else(|| StageError::Port {
            port: index.to_string(),
            reason: "no such output".to_owned(),
        })?;
        outbox.send_bytes(stamp_ns, payload)?;
        Ok(())
    }

    /// Promises on every output that nothing stamped before `stamp_ns` will follow. Sources
    /// whose messages come in stamp order call it as time advances, so that a consumer merging
    /// an idle output (a topic with one message at the start) with a busy one never waits on
    /// the idle one until end of stream.
    ///
    /// # Errors
    /// Bus errors.
    pub fn promise(&mut self, stamp_ns: i64) -> Result<(), StageError> {
        self.advance_watermarks(stamp_ns)?;
        Ok(())
    }

    /// The newest stamp sent or promised on `port`: a message stamped before it is refused
    /// (what a stage that holds data back until [`Stage::finish`] checks there).
    #[must_use]
    pub fn watermark_ns<M: Message>(&self, port: Output<M>) -> i64 {
        self.outboxes[port.index].watermark_ns()
    }

    /// Data frames sent on all outputs so far.
    fn sent(&self) -> u64 {
        self.outboxes.iter().map(Outbox::sent).sum()
    }

    fn advance_watermarks(&mut self, stamp_ns: i64) -> Result<(), BusError> {
        for o in &mut self.outboxes {
            o.advance_watermark(stamp_ns)?;
        }
        Ok(())
    }

    fn end(&mut self) -> Result<(), BusError> {
        for o in &mut self.outboxes {
            o.end()?;
        }
        Ok(())
    }
}

/// What a node did, reported at exit.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunReport {
    /// Node name.
    pub node: String,
    /// Messages received per input topic.
    pub received: Vec<(String, u64)>,
    /// Frames dropped per latest-only input topic.
    pub dropped: Vec<(String, u64)>,
    /// Messages sent per output topic.
    pub sent: Vec<(String, u64)>,
    /// Callback time percentiles, microseconds: p50, p99, max.
    pub callback_us: [u64; 3],
    /// Input messages skipped because they did not decode.
    pub decode_errors: u64,
    /// Wall time, seconds.
    pub wall_s: f64,
    /// CPU time of the process (user + system), seconds.
    #[serde(default)]
    pub cpu_s: f64,
    /// Peak resident set size of the process, bytes.
    #[serde(default)]
    pub peak_rss_bytes: u64,
    /// Stopped by a signal before the end of its inputs.
    pub interrupted: bool,
}

/// CPU time (user + system, s) and peak resident set size (bytes) of this process so far;
/// zeros where the system does not say.
pub fn process_usage() -> (f64, u64) {
    use nix::sys::resource::{UsageWho, getrusage};
    let Ok(u) = getrusage(UsageWho::RUSAGE_SELF) else {
        return (0.0, 0);
    };
    let secs = |t: nix::sys::time::TimeVal| t.tv_sec() as f64 + t.tv_usec() as f64 * 1e-6;
    // ru_maxrss is in KiB on Linux
    let rss = u64::try_from(u.max_rss()).unwrap_or(0).saturating_mul(1024);
    (secs(u.user_time()) + secs(u.system_time()), rss)
}

/// Registers SIGINT and SIGTERM: the returned flag turns true on either.
///
/// # Errors
/// When the handlers cannot be installed.
pub fn bind_signals() -> std::io::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, stop.clone())?;
    }
    Ok(stop)
}

struct InputState {
    inbox: Inbox,
    delay_ns: Option<i64>,
    head: Option<Frame>,
    /// Feedback inputs only: data frames read ahead of the head (payloads copied out of the
    /// transport). A feedback input drains its inbox on every fill, so its producer, which
    /// is downstream of this stage, never blocks on it: with a bounded topic buffer a
    /// blocked feedback producer closes a wait cycle (it waits on this stage's buffer, this
    /// stage waits on its primary inputs, which wait on a source that waits on the producer).
    backlog: VecDeque<Frame>,
    /// Effective watermark (feedback delay added).
    watermark: i64,
}

impl InputState {
    fn effective(&self, stamp: i64) -> i64 {
        stamp.saturating_add(self.delay_ns.unwrap_or(0))
    }

    fn is_feedback(&self) -> bool {
        self.delay_ns.is_some()
    }

    /// Reads until a data frame is pending or nothing more is queued (a feedback input:
    /// everything queued).
    fn fill(&mut self) -> Result<(), BusError> {
        let feedback = self.is_feedback();
        while (feedback || self.head.is_none()) && !self.inbox.ended() {
            match self.inbox.try_next()? {
                Some(Delivery::Data(frame)) => {
                    self.watermark = self.watermark.max(self.effective(frame.header.stamp_ns));
                    if feedback {
                        self.backlog.push_back(frame.detach());
                    } else {
                        self.head = Some(frame);
                    }
                }
                Some(Delivery::Watermark(w)) => self.watermark = self.watermark.max(self.effective(w)),
                Some(Delivery::EndOfStream) => self.watermark = i64::MAX,
                None => break,
            }
        }
        if self.head.is_none() {
            self.head = self.backlog.pop_front();
        }
        Ok(())
    }

    /// Tie-break rank: feedback before primary, then declaration order.
    fn rank(&self, index: usize) -> (u8, usize) {
        (u8::from(!self.is_feedback()), index)
    }
}

enum Step {
    Deliver(usize),
    Wait(usize),
    Finish,
}

/// Chooses what the merge does next (pure: no I/O).
fn next_step(inputs: &[InputState]) -> Step {
    let candidate = inputs
        .iter()
        .enumerate()
        .filter_map(|(i, s)| {
            s.head
                .as_ref()
                .map(|f| ((s.effective(f.header.stamp_ns), s.rank(i)), i))
        })
        .min();
    let primary_done = inputs
        .iter()
        .all(|s| s.is_feedback() || (s.inbox.ended() && s.head.is_none()));
    if primary_done {
        return Step::Finish;
    }
    match candidate {
        Some(((stamp, rank), i)) => {
            for (j, s) in inputs.iter().enumerate() {
                if j == i || s.head.is_some() || s.inbox.ended() {
                    continue;
                }
                let safe = s.watermark > stamp || (s.watermark == stamp && s.rank(j) > rank);
                if !safe {
                    return Step::Wait(j);
                }
            }
            Step::Deliver(i)
        }
        None => {
            // Nothing pending: wait on a primary input that has not ended.
            let j = inputs
                .iter()
                .position(|s| !s.is_feedback() && !s.inbox.ended())
                .unwrap_or(0);
            Step::Wait(j)
        }
    }
}

/// The smallest stamp the stage may still deliver from a primary input: what it can
/// promise downstream before blocking.
fn pending_watermark(inputs: &[InputState]) -> i64 {
    inputs
        .iter()
        .filter(|s| !s.is_feedback())
        .map(|s| s.head.as_ref().map_or(s.watermark, |f| f.header.stamp_ns))
        .min()
        .unwrap_or(i64::MAX)
}

/// Runs stage `S` as node `spec` on `transport` until its inputs end (or the source is
/// done) or `stop` turns true.
///
/// # Errors
/// Parameter, port, bus and stage errors.
pub fn run_node<S: Stage>(
    spec: &NodeSpec,
    transport: &dyn Transport,
    stop: &Arc<AtomicBool>,
) -> Result<RunReport, StageError> {
    let started = Instant::now();
    let params = parse_params::<S::Params>(&spec.params)?;
    S::check_params(&params)?;
    let stopped = || stop.load(Ordering::Relaxed);

    // Subscribers first, so that every publisher of the run finds its consumers.
    let mut inputs = Vec::with_capacity(spec.inputs.len());
    for b in &spec.inputs {
        inputs.push(InputState {
            inbox: Inbox::new(transport.subscriber(&b.topic_config())?, b.latest_only),
            delay_ns: b.feedback_delay_ns,
            head: None,
            backlog: VecDeque::new(),
            watermark: i64::MIN,
        });
    }
    let mut outboxes = Vec::with_capacity(spec.outputs.len());
    for b in &spec.outputs {
        outboxes.push(Outbox::new(
            transport.publisher(&b.topic_config())?,
            &b.msg_type,
            b.required_subscribers,
        ));
    }
    let handshake = Duration::from_millis(spec.handshake_timeout_ms);
    for s in &mut inputs {
        s.inbox.attach(handshake, &stopped)?;
    }
    for (o, b) in outboxes.iter().zip(&spec.outputs) {
        bus::wait_for_subscribers(o.publisher(), b.subscribers, handshake, &stopped)?;
    }
    let mut out = Outputs { outboxes };
    let ports = Ports::new(spec);
    let mut stage = S::create(params, &ports)?;
    let mut latency = Histogram::<u64>::new(3).map_err(StageError::failed)?;
    let mut record = |t: Instant| {
        let us = u64::try_from(t.elapsed().as_micros()).unwrap_or(u64::MAX);
        let _ = latency.record(us);
    };

    let mut decode_errors = 0u64;
    if inputs.is_empty() {
        while !stopped() {
            let t = Instant::now();
            let status = match stage.produce(&mut out) {
                Ok(status) => status,
                // On a stop, the consumers (stopped by the same signal) may be gone before
                // this stage sees its flag: a send that fails then is not a failure.
                Err(e) if stopped() => {
                    tracing::debug!(node = %spec.node, "stopped while sending: {e}");
                    break;
                }
                Err(e) => return Err(e),
            };
            record(t);
            if status == Produce::Done {
                break;
            }
        }
    } else {
        loop {
            if stopped() {
                break;
            }
            for s in &mut inputs {
                s.fill()?;
            }
            match next_step(&inputs) {
                Step::Deliver(i) => {
                    let Some(frame) = inputs[i].head.take() else { continue };
                    let t = Instant::now();
                    let sent = out.sent();
                    let handled = stage.on_message(
                        Input {
                            id: InputId(i),
                            binding: &spec.inputs[i],
                            frame: &frame,
                        },
                        &mut out,
                    );
                    match handled {
                        // A payload that does not decode is counted and reported; the
                        // stream goes on.
                        Err(StageError::Bus(e @ BusError::Decode { .. })) => {
                            tracing::warn!(node = %spec.node, "skipped: {e}");
                            decode_errors += 1;
                        }
                        Err(e) if stopped() => {
                            tracing::debug!(node = %spec.node, "stopped while handling a message: {e}");
                            break;
                        }
                        other => other?,
                    }
                    // A stage that sends on one output moves the others' watermarks along
                    // too: a consumer merging a busy output with a rare one (states with
                    // trajectory snapshots) would otherwise wait on the rare one while the
                    // busy one's queue fills, and a stage that never runs out of input (a
                    // replay as fast as it goes) never makes the promise it makes when idle.
                    if out.sent() > sent {
                        out.advance_watermarks(pending_watermark(&inputs))?;
                    }
                    record(t);
                }
                Step::Wait(j) => {
                    out.advance_watermarks(pending_watermark(&inputs))?;
                    inputs[j].inbox.wait(WAIT_SLICE)?;
                }
                Step::Finish => break,
            }
        }
    }

    let interrupted = stopped();
    stage.finish(&mut out)?;
    match out.end() {
        Ok(()) => {}
        Err(e) if interrupted => tracing::debug!(node = %spec.node, "end of stream not delivered after stop: {e}"),
        Err(e) => return Err(e.into()),
    }
    drop(stage);
    let received = inputs
        .iter()
        .map(|s| (s.inbox.topic().to_owned(), s.inbox.stats().received))
        .collect();
    let dropped = inputs
        .iter()
        .filter(|s| s.inbox.stats().dropped > 0)
        .map(|s| (s.inbox.topic().to_owned(), s.inbox.stats().dropped))
        .collect();
    // Unsubscribe before waiting for our own consumers: in a feedback loop they are our
    // producers, and each would otherwise wait out the handshake for the other.
    drop(inputs);
    for o in &out.outboxes {
        if !o.linger(handshake, &stopped) && !stopped() {
            tracing::warn!(
                topic = o.topic(),
                "consumers still attached {handshake:?} after end of stream"
            );
        }
    }

    let (cpu_s, peak_rss_bytes) = process_usage();
    let report = RunReport {
        node: spec.node.clone(),
        received,
        dropped,
        sent: out.outboxes.iter().map(|o| (o.topic().to_owned(), o.sent())).collect(),
        callback_us: [
            latency.value_at_quantile(0.5),
            latency.value_at_quantile(0.99),
            latency.max(),
        ],
        decode_errors,
        wall_s: started.elapsed().as_secs_f64(),
        cpu_s,
        peak_rss_bytes,
        interrupted,
    };
    tracing::info!(
        node = %report.node,
        received = ?report.received,
        sent = ?report.sent,
        dropped = ?report.dropped,
        decode_errors = report.decode_errors,
        callback_p50_us = report.callback_us[0],
        callback_p99_us = report.callback_us[1],
        callback_max_us = report.callback_us[2],
        wall_s = format!("{:.3}", report.wall_s),
        cpu_s = format!("{:.3}", report.cpu_s),
        peak_rss_mib = report.peak_rss_bytes >> 20,
        interrupted,
        "stage finished"
    );
    Ok(report)
}

#[cfg(test)]
mod tests;
