//! zenoh transport: topics between machines.
//!
//! zenoh carries the bytes; this module adds what the bus promises on top of it, because a
//! zenoh `put` with nobody matching (a host not up yet, a link that is down and being
//! re-established) is dropped without a word:
//!
//! - Every frame travels in an envelope with a link sequence number. The subscriber takes
//!   them strictly in that order and drops anything else (duplicates, frames after a gap).
//! - The subscriber answers on a second key with acknowledgements: what it has received
//!   (`received`) and what its consumer has taken (`consumed`). It sends them as its consumer
//!   reads and as a heartbeat; it says `bye` when it is dropped.
//! - The publisher keeps every frame until it is acknowledged as received and resends from
//!   the first unacknowledged one (go-back-N) when the subscriber reports a gap or nothing
//!   advanced for a while. It lets at most `buffer` frames be ahead of `consumed`: a slow
//!   consumer on the other machine holds the publisher back exactly as iceoryx2 does locally
//!   (lossless back-pressure), and the subscriber's queue never overflows.
//! - Both sides send heartbeats; a side that hears nothing for the link timeout fails with
//!   [`BusError::LinkDown`], naming the topic and the data frames (by seq) not delivered.
//! - A latest-only topic is sent without a window and without resending data; its control
//!   frames (watermarks, end of stream) are repeated until acknowledged.
//!
//! One subscriber per topic key: the launcher gives every destination host its own key.

use std::collections::VecDeque;
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use ::zenoh::Wait;
use ::zenoh::bytes::ZBytes;
use ::zenoh::qos::{CongestionControl, Priority};

use super::{
    BusError, FillFn, Frame, FrameData, FrameHeader, FrameKind, Publisher, Result, Subscriber, TopicConfig, Transport,
};
use crate::ZenohDecl;
use gprflow_msg as msg;

/// Default of [`ZenohDecl::link_timeout_s`].
pub const DEFAULT_LINK_TIMEOUT: Duration = Duration::from_secs(60);
/// Heartbeat period of both sides.
const HEARTBEAT: Duration = Duration::from_millis(100);
/// Resend what is unacknowledged when nothing advanced for this long.
const RESEND_AFTER: Duration = Duration::from_millis(300);
const POLL: Duration = Duration::from_millis(20);

/// Envelope: link seq (8 bytes), then the frame header (24 bytes), then the payload.
const ENVELOPE: usize = 32;
/// Link seq of a publisher heartbeat (the header's `seq` field carries the next link seq).
const PUBLISHER_HEARTBEAT: u64 = u64::MAX;

/// Acknowledgement kinds (first byte of an ack).
const ACK: u8 = 0;
const ACK_GAP: u8 = 1;
const ACK_BYE: u8 = 2;
const ACK_LEN: usize = 24;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

fn err(topic: &str, what: impl std::fmt::Display) -> BusError {
    BusError::Transport {
        topic: topic.to_owned(),
        what: what.to_string(),
    }
}

fn write_header(out: &mut [u8], link: u64, header: &FrameHeader) {
    out[0..8].copy_from_slice(&link.to_le_bytes());
    out[8..16].copy_from_slice(&header.seq.to_le_bytes());
    out[16..24].copy_from_slice(&header.stamp_ns.to_le_bytes());
    out[24..28].copy_from_slice(&header.kind.to_le_bytes());
    out[28..32].copy_from_slice(&header.reserved.to_le_bytes());
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(w)
}

fn read_header(b: &[u8]) -> Option<(u64, FrameHeader)> {
    if b.len() < ENVELOPE {
        return None;
    }
    let mut kind = [0u8; 4];
    kind.copy_from_slice(&b[24..28]);
    let mut reserved = [0u8; 4];
    reserved.copy_from_slice(&b[28..32]);
    Some((
        u64_at(b, 0),
        FrameHeader {
            seq: u64_at(b, 8),
            stamp_ns: u64_at(b, 16) as i64,
            kind: u32::from_le_bytes(kind),
            reserved: u32::from_le_bytes(reserved),
        },
    ))
}

fn ack_bytes(kind: u8, received: u64, consumed: u64) -> Vec<u8> {
    let mut b = vec![0u8; ACK_LEN];
    b[0] = kind;
    b[8..16].copy_from_slice(&received.to_le_bytes());
    b[16..24].copy_from_slice(&consumed.to_le_bytes());
    b
}

/// The key prefix of the topics a graph sends to `host`: `gprflow/GRAPH/HOST`.
///
/// # Errors
/// A graph or host name that cannot be part of a zenoh key.
pub fn key_prefix(graph: &str, host: &str) -> std::result::Result<String, String> {
    for (what, name) in [("graph name", graph), ("host name", host)] {
        if name.is_empty() || name.contains(['/', '*', '$', '?', '#', ' ']) {
            return Err(format!(
                "{what} `{name}` cannot be part of a zenoh key (no `/ * $ ? #` or spaces)"
            ));
        }
    }
    Ok(format!("gprflow/{graph}/{host}"))
}

/// Checks a host section without touching files or the network: mode, endpoints, lease,
/// link timeout, and that `allow` comes with `tls`.
///
/// # Errors
/// The first problem, in words.
pub fn check_settings(decl: &ZenohDecl) -> std::result::Result<(), String> {
    let mode = decl.mode.as_deref().unwrap_or("peer");
    if !matches!(mode, "peer" | "client" | "router") {
        return Err(format!("zenoh mode `{mode}`: expected peer, client or router"));
    }
    for endpoint in decl.listen.iter().chain(&decl.connect) {
        check_endpoint(endpoint, decl.tls.is_some())?;
    }
    if let Some(lease) = decl.lease_ms
        && lease < 100
    {
        return Err(format!("lease_ms {lease}: at least 100"));
    }
    if let Some(s) = decl.link_timeout_s
        && !(s.is_finite() && s > 0.0)
    {
        return Err(format!("link_timeout_s {s}: must be a positive number of seconds"));
    }
    if !decl.allow.is_empty() && decl.tls.is_none() {
        return Err("`allow` names certificate common names, which needs `tls`".to_owned());
    }
    Ok(())
}

/// The zenoh configuration of a host section: only the endpoints it names, multicast
/// scouting and gossip off unless asked, the admin space off, mutual TLS and access control
/// when configured.
///
/// # Errors
/// A bad setting (see [`check_settings`]) or a missing certificate file, in words.
pub fn config(decl: &ZenohDecl) -> std::result::Result<::zenoh::Config, String> {
    check_settings(decl)?;
    let mut c = ::zenoh::Config::default();
    let mut set = |key: &str, value: serde_json::Value| {
        c.insert_json5(key, &value.to_string())
            .map_err(|e| format!("zenoh setting `{key}` = {value}: {e}"))
    };
    set("mode", decl.mode.as_deref().unwrap_or("peer").into())?;
    set("listen/endpoints", serde_json::json!(decl.listen))?;
    set("connect/endpoints", serde_json::json!(decl.connect))?;
    set("scouting/multicast/enabled", decl.scouting.into())?;
    set("scouting/gossip/enabled", decl.scouting.into())?;
    set("adminspace/enabled", false.into())?;
    if let Some(lease) = decl.lease_ms {
        set("transport/link/tx/lease", lease.into())?;
    }
    if let Some(tls) = &decl.tls {
        for (what, path) in [
            ("root_ca", &tls.root_ca),
            ("certificate", &tls.certificate),
            ("private_key", &tls.private_key),
        ] {
            if !std::path::Path::new(path).is_file() {
                return Err(format!("tls.{what}: {path}: no such file"));
            }
        }
        set("transport/link/tls/root_ca_certificate", tls.root_ca.as_str().into())?;
        set("transport/link/tls/listen_certificate", tls.certificate.as_str().into())?;
        set("transport/link/tls/listen_private_key", tls.private_key.as_str().into())?;
        set(
            "transport/link/tls/connect_certificate",
            tls.certificate.as_str().into(),
        )?;
        set(
            "transport/link/tls/connect_private_key",
            tls.private_key.as_str().into(),
        )?;
        set("transport/link/tls/enable_mtls", true.into())?;
        set("transport/link/tls/verify_name_on_connect", true.into())?;
    }
    if !decl.allow.is_empty() {
        set(
            "access_control",
            serde_json::json!({
                "enabled": true,
                "default_permission": "deny",
                "rules": [{
                    "id": "gprflow_topics",
                    "key_exprs": ["gprflow/**"],
                    "messages": ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                                 "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                    "flows": ["egress", "ingress"],
                    "permission": "allow",
                }],
                "subjects": [{ "id": "allowed_hosts", "cert_common_names": decl.allow }],
                "policies": [{ "rules": ["gprflow_topics"], "subjects": ["allowed_hosts"] }],
            }),
        )?;
    }
    Ok(c)
}

fn check_endpoint(endpoint: &str, tls: bool) -> std::result::Result<(), String> {
    let Some((proto, address)) = endpoint.split_once('/') else {
        return Err(format!(
            "endpoint `{endpoint}`: expected PROTOCOL/ADDRESS:PORT (tcp/10.0.0.1:7447)"
        ));
    };
    match proto {
        "tcp" => {}
        "tls" if tls => {}
        "tls" => {
            return Err(format!(
                "endpoint `{endpoint}`: a tls/ endpoint needs the host's `tls:` certificates"
            ));
        }
        _ => {
            return Err(format!(
                "endpoint `{endpoint}`: protocol `{proto}` is not built in (tcp, tls)"
            ));
        }
    }
    let address = address.split('#').next().unwrap_or(address);
    if address
        .rsplit_once(':')
        .is_none_or(|(_, port)| port.parse::<u16>().is_err())
    {
        return Err(format!("endpoint `{endpoint}`: expected ADDRESS:PORT after `{proto}/`"));
    }
    Ok(())
}

/// The zenoh transport of one process: one zenoh session; topic `node/output` travels on
/// the keys `PREFIX/node/output/d` (frames) and `PREFIX/node/output/a` (acknowledgements).
#[derive(Clone)]
pub struct ZenohTransport {
    session: ::zenoh::Session,
    key_prefix: String,
    link_timeout: Duration,
    stop: Arc<AtomicBool>,
}

impl std::fmt::Debug for ZenohTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohTransport")
            .field("key_prefix", &self.key_prefix)
            .finish_non_exhaustive()
    }
}

impl ZenohTransport {
    /// Opens a session as `decl` says; topics are keyed under `key_prefix`.
    ///
    /// # Errors
    /// A bad setting or a session that cannot open (an endpoint that cannot be bound).
    pub fn open(decl: &ZenohDecl, key_prefix: &str, stop: Arc<AtomicBool>) -> Result<Self> {
        let config = config(decl).map_err(|what| err(key_prefix, what))?;
        let session = ::zenoh::open(config)
            .wait()
            .map_err(|e| err(key_prefix, format!("cannot open the zenoh session: {e}")))?;
        let link_timeout = decl
            .link_timeout_s
            .map_or(DEFAULT_LINK_TIMEOUT, Duration::from_secs_f64);
        Ok(Self {
            session,
            key_prefix: key_prefix.trim_end_matches('/').to_owned(),
            link_timeout,
            stop,
        })
    }

    /// The same session, with topics keyed under another prefix.
    #[must_use]
    pub fn with_prefix(&self, key_prefix: &str) -> Self {
        Self {
            key_prefix: key_prefix.trim_end_matches('/').to_owned(),
            ..self.clone()
        }
    }

    fn keys(&self, topic: &str) -> Result<(::zenoh::key_expr::KeyExpr<'static>, ::zenoh::key_expr::KeyExpr<'static>)> {
        let make = |suffix: &str| {
            ::zenoh::key_expr::KeyExpr::try_from(format!("{}/{topic}/{suffix}", self.key_prefix))
                .map_err(|e| err(topic, format!("not usable as a zenoh key: {e}")))
        };
        Ok((make("d")?, make("a")?))
    }
}

impl ZenohTransport {
    /// A publisher of `topic`, with the zenoh-only [`ZenohPublisher::drain`].
    ///
    /// # Errors
    /// zenoh errors.
    pub fn zenoh_publisher(&self, topic: &TopicConfig) -> Result<ZenohPublisher> {
        ZenohPublisher::new(self, topic)
    }

    /// A subscriber of `topic`.
    ///
    /// # Errors
    /// zenoh errors.
    pub fn zenoh_subscriber(&self, topic: &TopicConfig) -> Result<ZenohSubscriber> {
        ZenohSubscriber::new(self, topic)
    }
}

impl Transport for ZenohTransport {
    fn publisher(&self, topic: &TopicConfig) -> Result<Box<dyn Publisher>> {
        ZenohPublisher::new(self, topic).map(|p| Box::new(p) as Box<dyn Publisher>)
    }

    fn subscriber(&self, topic: &TopicConfig) -> Result<Box<dyn Subscriber>> {
        ZenohSubscriber::new(self, topic).map(|s| Box::new(s) as Box<dyn Subscriber>)
    }
}

/// One frame sent and not yet acknowledged as received.
struct Pending {
    link: u64,
    seq: u64,
    kind: FrameKind,
    bytes: ZBytes,
}

#[derive(Default)]
struct PubState {
    window: VecDeque<Pending>,
    next_link: u64,
    /// The subscriber has every frame below this link seq.
    received: u64,
    /// Its consumer has taken every frame below this link seq.
    consumed: u64,
    attached: bool,
    gone: bool,
    last_heard: Option<Instant>,
    last_progress: Option<Instant>,
    resend_now: bool,
}

struct PubShared {
    topic: String,
    state: Mutex<PubState>,
    changed: Condvar,
    /// Serialises puts so that frames leave in link order.
    put_lock: Mutex<::zenoh::pubsub::Publisher<'static>>,
    closed: AtomicBool,
    /// Frames sent again (after a gap report or a stall).
    resent: std::sync::atomic::AtomicU64,
}

impl PubShared {
    fn put(&self, bytes: ZBytes) -> Result<()> {
        lock(&self.put_lock)
            .put(bytes)
            .wait()
            .map_err(|e| err(&self.topic, format!("zenoh put: {e}")))
    }

    fn on_ack(&self, b: &[u8]) {
        if b.len() < ACK_LEN {
            return;
        }
        let (received, consumed) = (u64_at(b, 8), u64_at(b, 16));
        let mut st = lock(&self.state);
        let now = Instant::now();
        match b[0] {
            ACK_BYE => st.gone = true,
            kind => {
                st.attached = true;
                st.last_heard = Some(now);
                if received > st.received {
                    st.received = received.min(st.next_link);
                    st.last_progress = Some(now);
                    while st.window.front().is_some_and(|p| p.link < st.received) {
                        st.window.pop_front();
                    }
                }
                st.consumed = st.consumed.max(consumed.min(st.received));
                if kind == ACK_GAP {
                    st.resend_now = true;
                }
            }
        }
        drop(st);
        self.changed.notify_all();
    }

    /// Resends what the subscriber lacks when it asked or nothing advanced for a while, and
    /// sends the publisher heartbeat.
    fn tick(&self, latest_only: bool, last_beat: &mut Instant) -> Result<()> {
        let now = Instant::now();
        let resend: Vec<ZBytes> = {
            let mut st = lock(&self.state);
            let stalled = st.last_progress.is_none_or(|t| now.duration_since(t) > RESEND_AFTER);
            let outstanding = st.window.iter().any(|p| p.link >= st.received);
            if outstanding && (st.resend_now || stalled) && !st.gone {
                st.resend_now = false;
                st.last_progress = Some(now);
                st.window
                    .iter()
                    .filter(|p| p.link >= st.received && (!latest_only || p.kind != FrameKind::Data))
                    .map(|p| p.bytes.clone())
                    .collect()
            } else {
                Vec::new()
            }
        };
        self.resent.fetch_add(resend.len() as u64, Ordering::Relaxed);
        for bytes in resend {
            self.put(bytes)?;
        }
        if now.duration_since(*last_beat) >= HEARTBEAT {
            *last_beat = now;
            let next = lock(&self.state).next_link;
            let mut beat = vec![0u8; ENVELOPE];
            write_header(
                &mut beat,
                PUBLISHER_HEARTBEAT,
                &FrameHeader::control(FrameKind::Watermark, next, 0),
            );
            self.put(beat.into())?;
        }
        Ok(())
    }
}

/// The sending end of a zenoh topic (see the module documentation).
pub struct ZenohPublisher {
    shared: Arc<PubShared>,
    latest_only: bool,
    capacity: u64,
    link_timeout: Duration,
    stop: Arc<AtomicBool>,
    _acks: ::zenoh::pubsub::Subscriber<()>,
    ticker: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for ZenohPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohPublisher")
            .field("topic", &self.shared.topic)
            .finish_non_exhaustive()
    }
}

impl ZenohPublisher {
    fn new(t: &ZenohTransport, topic: &TopicConfig) -> Result<Self> {
        let (data_key, ack_key) = t.keys(&topic.name)?;
        let publisher = t
            .session
            .declare_publisher(data_key)
            .congestion_control(CongestionControl::Block)
            .priority(Priority::Data)
            .wait()
            .map_err(|e| err(&topic.name, format!("zenoh publisher: {e}")))?;
        let shared = Arc::new(PubShared {
            topic: topic.name.clone(),
            state: Mutex::new(PubState::default()),
            changed: Condvar::new(),
            put_lock: Mutex::new(publisher),
            closed: AtomicBool::new(false),
            resent: std::sync::atomic::AtomicU64::new(0),
        });
        let on_ack = shared.clone();
        let acks = t
            .session
            .declare_subscriber(ack_key)
            .callback(move |sample| on_ack.on_ack(&sample.payload().to_bytes()))
            .wait()
            .map_err(|e| err(&topic.name, format!("zenoh ack subscriber: {e}")))?;
        let ticking = shared.clone();
        let latest_only = topic.latest_only;
        let ticker = std::thread::Builder::new()
            .name(format!("zenoh-pub-{}", topic.name))
            .spawn(move || {
                let mut last_beat = Instant::now() - HEARTBEAT;
                while !ticking.closed.load(Ordering::Relaxed) {
                    if let Err(e) = ticking.tick(latest_only, &mut last_beat) {
                        tracing::warn!("{e}");
                    }
                    std::thread::sleep(POLL);
                }
            })
            .map_err(|e| err(&topic.name, format!("cannot start the resend thread: {e}")))?;
        Ok(Self {
            shared,
            latest_only: topic.latest_only,
            capacity: topic.buffer.max(1) as u64,
            link_timeout: t.link_timeout,
            stop: t.stop.clone(),
            _acks: acks,
            ticker: Some(ticker),
        })
    }

    /// Waits until the subscriber's consumer has taken every frame sent (or the subscriber
    /// left): a publisher must not go away before, since it is the only one that can resend.
    ///
    /// # Errors
    /// [`BusError::LinkDown`] when the other side is silent for the link timeout;
    /// [`BusError::Shutdown`] when `stop` turns true.
    pub fn drain(&self, stop: &dyn Fn() -> bool) -> Result<()> {
        let mut st = lock(&self.shared.state);
        let started = Instant::now();
        while !st.gone && st.consumed < st.next_link {
            if stop() {
                return Err(BusError::Shutdown);
            }
            let heard = st.last_heard.unwrap_or(started);
            if heard.elapsed() > self.link_timeout {
                return Err(self.link_down(&st, heard));
            }
            st = self
                .shared
                .changed
                .wait_timeout(st, POLL)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        Ok(())
    }

    /// Frames sent more than once so far (the link lost them, or the other side was not
    /// subscribed yet).
    pub fn resent(&self) -> u64 {
        self.shared.resent.load(Ordering::Relaxed)
    }

    /// The error of a link silent since `heard`, with the frames not yet received.
    fn link_down(&self, st: &PubState, heard: Instant) -> BusError {
        let (first, last) = Self::undelivered(st);
        BusError::LinkDown {
            topic: self.shared.topic.clone(),
            waited: heard.elapsed(),
            first,
            last,
        }
    }

    /// The data seqs of the frames not yet received, as `first..last` (one past).
    fn undelivered(st: &PubState) -> (u64, u64) {
        let data = st.window.iter().filter(|p| p.link >= st.received);
        let first = data.clone().map(|p| p.seq).min().unwrap_or(0);
        let last = data
            .map(|p| p.seq + u64::from(p.kind == FrameKind::Data))
            .max()
            .unwrap_or(first);
        (first, last)
    }
}

impl Drop for ZenohPublisher {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::Relaxed);
        if let Some(t) = self.ticker.take() {
            let _ = t.join();
        }
    }
}

impl Publisher for ZenohPublisher {
    fn topic(&self) -> &str {
        &self.shared.topic
    }

    fn send_with(&mut self, header: FrameHeader, len: usize, fill: &mut FillFn<'_>) -> Result<usize> {
        let topic = &self.shared.topic;
        let mut buf: Vec<u8> = Vec::with_capacity(ENVELOPE + len);
        buf.resize(ENVELOPE, 0);
        let spare: &mut [MaybeUninit<u8>] = &mut buf.spare_capacity_mut()[..len];
        msg::fill_payload(spare, fill).map_err(|source| BusError::Encode {
            topic: topic.clone(),
            source,
        })?;
        // SAFETY: `fill_payload` returned Ok: `fill` handed back the token of this very
        // buffer, which only a writer that wrote each of its `len` bytes makes (after the
        // envelope).
        unsafe { buf.set_len(ENVELOPE + len) };
        let kind = header.kind().unwrap_or(FrameKind::Data);
        let lossless = !self.latest_only || kind != FrameKind::Data;
        let mut st = lock(&self.shared.state);
        // a lossless frame waits for room: at most `capacity` frames ahead of the consumer
        while !self.latest_only && !st.gone && st.next_link - st.consumed >= self.capacity {
            if self.stop.load(Ordering::Relaxed) {
                return Err(BusError::Shutdown);
            }
            if let Some(heard) = st.last_heard
                && heard.elapsed() > self.link_timeout
            {
                return Err(self.link_down(&st, heard));
            }
            st = self
                .shared
                .changed
                .wait_timeout(st, POLL)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        if st.gone || !st.attached {
            return Ok(0);
        }
        let link = st.next_link;
        st.next_link += 1;
        write_header(&mut buf, link, &header);
        let bytes = ZBytes::from(buf);
        if lossless {
            if st.window.is_empty() {
                st.last_progress = Some(Instant::now());
            }
            st.window.push_back(Pending {
                link,
                seq: header.seq,
                kind,
                bytes: bytes.clone(),
            });
        }
        drop(st);
        self.shared.put(bytes)?;
        Ok(1)
    }

    fn subscriber_count(&self) -> usize {
        let st = lock(&self.shared.state);
        usize::from(st.attached && !st.gone)
    }
}

#[derive(Default)]
struct SubState {
    /// Received frames with their link seqs and headers, still in zenoh's buffers: the
    /// payload is copied out once, on the consumer's thread ([`Subscriber::try_receive`]),
    /// not on zenoh's receive thread.
    queue: VecDeque<(u64, FrameHeader, ZBytes)>,
    /// Every frame below this link seq has been received.
    received: u64,
    /// The consumer has taken every frame below this link seq.
    consumed: u64,
    last_heard: Option<Instant>,
    last_gap_ack: Option<Instant>,
    /// Data seq of the last frame taken, for error messages.
    last_seq: Option<u64>,
}

struct SubShared {
    topic: String,
    capacity: usize,
    latest_only: bool,
    state: Mutex<SubState>,
    changed: Condvar,
    acks: ::zenoh::pubsub::Publisher<'static>,
    closed: AtomicBool,
}

impl SubShared {
    fn ack(&self, kind: u8, received: u64, consumed: u64) {
        if let Err(e) = self.acks.put(ack_bytes(kind, received, consumed)).wait() {
            tracing::warn!("topic `{}`: zenoh ack: {e}", self.topic);
        }
    }

    fn on_frame(&self, bytes: ZBytes) {
        // only the envelope is read here (a large frame arrives in fragments)
        let mut envelope = [0u8; ENVELOPE];
        if std::io::Read::read_exact(&mut bytes.reader(), &mut envelope).is_err() {
            return;
        }
        let Some((link, header)) = read_header(&envelope) else {
            return;
        };
        let now = Instant::now();
        let mut st = lock(&self.state);
        st.last_heard = Some(now);
        let gap = if link == PUBLISHER_HEARTBEAT {
            // `seq` carries the publisher's next link seq: frames beyond ours were lost
            header.seq > st.received
        } else if link < st.received {
            false // a duplicate of something received
        } else if self.latest_only {
            // data may be skipped; keep the newest `capacity` frames
            if st.queue.len() == self.capacity {
                st.queue.pop_front();
            }
            st.queue.push_back((link, header, bytes));
            st.received = link + 1;
            false
        } else if link == st.received && st.queue.len() < self.capacity {
            st.queue.push_back((link, header, bytes));
            st.received += 1;
            false
        } else {
            true // a gap before it, or no room (the publisher's window says there is)
        };
        let ask = gap && st.last_gap_ack.is_none_or(|t| now.duration_since(t) > RESEND_AFTER / 3);
        if ask {
            st.last_gap_ack = Some(now);
        }
        let (received, consumed) = (st.received, st.consumed);
        drop(st);
        self.changed.notify_all();
        if ask {
            self.ack(ACK_GAP, received, consumed);
        }
    }
}

/// The frame in `bytes` (envelope first), its payload copied out of zenoh's buffers once.
fn frame_of(header: FrameHeader, bytes: &ZBytes) -> Frame {
    let len = bytes.len().saturating_sub(ENVELOPE);
    if len == 0 {
        return Frame {
            header,
            data: FrameData::Empty,
        };
    }
    let mut payload = Vec::with_capacity(len);
    let mut reader = bytes.reader();
    let mut envelope = [0u8; ENVELOPE];
    // reading from memory zenoh holds cannot fail short of the length it reported
    let _ = std::io::Read::read_exact(&mut reader, &mut envelope);
    let _ = std::io::Read::read_to_end(&mut reader, &mut payload);
    Frame {
        header,
        data: FrameData::Owned(payload),
    }
}

/// The receiving end of a zenoh topic.
pub struct ZenohSubscriber {
    shared: Arc<SubShared>,
    link_timeout: Duration,
    _frames: ::zenoh::pubsub::Subscriber<()>,
    beater: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for ZenohSubscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohSubscriber")
            .field("topic", &self.shared.topic)
            .finish_non_exhaustive()
    }
}

impl ZenohSubscriber {
    fn new(t: &ZenohTransport, topic: &TopicConfig) -> Result<Self> {
        let (data_key, ack_key) = t.keys(&topic.name)?;
        let acks = t
            .session
            .declare_publisher(ack_key)
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::InteractiveHigh)
            .wait()
            .map_err(|e| err(&topic.name, format!("zenoh ack publisher: {e}")))?;
        let shared = Arc::new(SubShared {
            topic: topic.name.clone(),
            capacity: topic.buffer.max(1),
            latest_only: topic.latest_only,
            state: Mutex::new(SubState::default()),
            changed: Condvar::new(),
            acks,
            closed: AtomicBool::new(false),
        });
        let on_frame = shared.clone();
        let frames = t
            .session
            .declare_subscriber(data_key)
            .callback(move |sample| on_frame.on_frame(sample.payload().clone()))
            .wait()
            .map_err(|e| err(&topic.name, format!("zenoh subscriber: {e}")))?;
        let beating = shared.clone();
        let beater = std::thread::Builder::new()
            .name(format!("zenoh-sub-{}", topic.name))
            .spawn(move || {
                while !beating.closed.load(Ordering::Relaxed) {
                    let (received, consumed) = {
                        let st = lock(&beating.state);
                        (st.received, st.consumed)
                    };
                    beating.ack(ACK, received, consumed);
                    std::thread::sleep(HEARTBEAT);
                }
            })
            .map_err(|e| err(&topic.name, format!("cannot start the heartbeat thread: {e}")))?;
        Ok(Self {
            shared,
            link_timeout: t.link_timeout,
            _frames: frames,
            beater: Some(beater),
        })
    }
}

impl Drop for ZenohSubscriber {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::Relaxed);
        if let Some(b) = self.beater.take() {
            let _ = b.join();
        }
        let (received, consumed) = {
            let st = lock(&self.shared.state);
            (st.received, st.consumed)
        };
        // acks may be dropped under congestion: say it a few times
        for _ in 0..3 {
            self.shared.ack(ACK_BYE, received, consumed);
        }
    }
}

impl Subscriber for ZenohSubscriber {
    fn topic(&self) -> &str {
        &self.shared.topic
    }

    fn try_receive(&mut self) -> Result<Option<Frame>> {
        let mut st = lock(&self.shared.state);
        let Some((link, header, bytes)) = st.queue.pop_front() else {
            if let Some(heard) = st.last_heard
                && heard.elapsed() > self.link_timeout
            {
                let next = st.last_seq.map_or(0, |s| s + 1);
                return Err(BusError::LinkDown {
                    topic: self.shared.topic.clone(),
                    waited: heard.elapsed(),
                    first: next,
                    last: next,
                });
            }
            return Ok(None);
        };
        st.consumed = link + 1;
        if header.kind() == Some(FrameKind::Data) {
            st.last_seq = Some(header.seq);
        }
        let (received, consumed, empty) = (st.received, st.consumed, st.queue.is_empty());
        drop(st);
        let frame = frame_of(header, &bytes);
        // tell the publisher there is room: when half the buffer was taken or all of it
        if empty || consumed % (self.shared.capacity as u64 / 2).max(1) == 0 {
            self.shared.ack(ACK, received, consumed);
        }
        Ok(Some(frame))
    }

    fn wait(&mut self, timeout: Duration) -> Result<()> {
        let st = lock(&self.shared.state);
        if st.queue.is_empty() {
            let _ = self
                .shared
                .changed
                .wait_timeout(st, timeout)
                .unwrap_or_else(PoisonError::into_inner);
        }
        Ok(())
    }

    fn attach(&mut self, timeout: Duration, stop: &dyn Fn() -> bool) -> Result<()> {
        // the other side is there once its acknowledgement subscriber matches ours
        let start = Instant::now();
        loop {
            let matching = self
                .shared
                .acks
                .matching_status()
                .wait()
                .map_err(|e| err(&self.shared.topic, format!("zenoh matching status: {e}")))?
                .matching();
            if matching || lock(&self.shared.state).last_heard.is_some() {
                return Ok(());
            }
            if stop() {
                return Err(BusError::Shutdown);
            }
            if start.elapsed() > timeout {
                return Err(BusError::HandshakeTimeout {
                    topic: self.shared.topic.clone(),
                    connected: 0,
                    expected: 1,
                    waited: start.elapsed(),
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}
