//! The receiving end of a zenoh topic: frames are taken strictly in link order, gaps are
//! reported, and acknowledgements (and a heartbeat) tell the publisher what arrived.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use ::zenoh::Wait;
use ::zenoh::bytes::ZBytes;
use ::zenoh::qos::{CongestionControl, Priority};

use super::envelope::{ACK, ACK_BYE, ACK_GAP, ENVELOPE, PUBLISHER_HEARTBEAT, ack_bytes, read_header};
use super::{HEARTBEAT, RESEND_AFTER, ZenohTransport, err, lock};
use crate::{BusError, Frame, FrameData, FrameHeader, FrameKind, Result, Subscriber, TopicConfig};

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
    pub(super) fn new(t: &ZenohTransport, topic: &TopicConfig) -> Result<Self> {
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
