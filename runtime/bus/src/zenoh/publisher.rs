//! The sending end of a zenoh topic: frames go out in envelopes, stay in the [`SendWindow`]
//! until acknowledged, and a ticker thread resends and sends the heartbeat.

use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use ::zenoh::Wait;
use ::zenoh::bytes::ZBytes;
use ::zenoh::qos::{CongestionControl, Priority};
use gprflow_msg as msg;

use super::envelope::{ACK_LEN, ENVELOPE, PUBLISHER_HEARTBEAT, u64_at, write_header};
use super::window::SendWindow;
use super::{HEARTBEAT, POLL, ZenohTransport, err, lock};
use crate::{BusError, FillFn, FrameHeader, FrameKind, Publisher, Result, TopicConfig};

struct PubShared {
    topic: String,
    state: Mutex<SendWindow<ZBytes>>,
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

    /// Waits up to [`POLL`] for the window to change (an ack arrived).
    fn wait_changed<'a>(&self, st: MutexGuard<'a, SendWindow<ZBytes>>) -> MutexGuard<'a, SendWindow<ZBytes>> {
        self.changed
            .wait_timeout(st, POLL)
            .unwrap_or_else(PoisonError::into_inner)
            .0
    }

    fn on_ack(&self, b: &[u8]) {
        if b.len() < ACK_LEN {
            return;
        }
        lock(&self.state).on_ack(b[0], u64_at(b, 8), u64_at(b, 16), Instant::now());
        self.changed.notify_all();
    }

    /// Resends what the subscriber lacks when it asked or nothing advanced for a while, and
    /// sends the publisher heartbeat.
    fn tick(&self, latest_only: bool, last_beat: &mut Instant) -> Result<()> {
        let now = Instant::now();
        let resend = lock(&self.state).due(now, latest_only);
        self.resent.fetch_add(resend.len() as u64, Ordering::Relaxed);
        for bytes in resend {
            self.put(bytes)?;
        }
        if now.duration_since(*last_beat) >= HEARTBEAT {
            *last_beat = now;
            let next = lock(&self.state).next_link();
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
    pub(super) fn new(t: &ZenohTransport, topic: &TopicConfig) -> Result<Self> {
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
            state: Mutex::new(SendWindow::default()),
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
            capacity: topic.buffer.clamp(1, super::MAX_IN_FLIGHT) as u64,
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
        while !st.gone() && !st.all_consumed() {
            if stop() {
                return Err(BusError::Shutdown);
            }
            let heard = st.last_heard().unwrap_or(started);
            if heard.elapsed() > self.link_timeout {
                return Err(self.link_down(&st, heard));
            }
            st = self.shared.wait_changed(st);
        }
        Ok(())
    }

    /// Frames sent more than once so far (the link lost them, or the other side was not
    /// subscribed yet).
    pub fn resent(&self) -> u64 {
        self.shared.resent.load(Ordering::Relaxed)
    }

    /// The error of a link silent since `heard`, with the frames not yet received.
    fn link_down(&self, st: &SendWindow<ZBytes>, heard: Instant) -> BusError {
        let (first, last) = st.undelivered();
        BusError::LinkDown {
            topic: self.shared.topic.clone(),
            waited: heard.elapsed(),
            first,
            last,
        }
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
        while !self.latest_only && !st.gone() && st.unconsumed() >= self.capacity {
            if self.stop.load(Ordering::Relaxed) {
                return Err(BusError::Shutdown);
            }
            if let Some(heard) = st.silent_for(Instant::now(), self.link_timeout) {
                return Err(self.link_down(&st, heard));
            }
            st = self.shared.wait_changed(st);
        }
        if st.gone() || !st.attached() {
            return Ok(0);
        }
        // the envelope names the link seq the window gives the frame
        write_header(&mut buf, st.next_link(), &header);
        let bytes = ZBytes::from(buf);
        st.send(header.seq, kind, bytes.clone(), lossless, Instant::now());
        drop(st);
        self.shared.put(bytes)?;
        Ok(1)
    }

    fn subscriber_count(&self) -> usize {
        let st = lock(&self.shared.state);
        usize::from(st.attached() && !st.gone())
    }
}
