//! The bus: typed topics between processes.
//!
//! A [`Transport`] creates [`Publisher`]s and [`Subscriber`]s of raw frames: a
//! [`FrameHeader`] (kind, per-topic sequence number, stamp) beside a CDR payload.
//! Implementations: [`iox::IoxTransport`] (iceoryx2 shared memory between processes on one
//! machine, zero copy, event-driven wake-up) and [`inproc::InProcess`] (threads of one
//! process, for tests). Both pass the same conformance suite (`tests/transport_conformance.rs`
//! runs it against each).
//!
//! Contracts every transport keeps:
//! - Lossless by default: a publisher waits while a subscriber's buffer is full.
//! - A topic marked `latest_only` never blocks its publisher; old frames are overwritten and
//!   the subscriber counts them as drops from the sequence gaps.
//! - Frames arrive in publication order; [`Inbox`] checks sequence numbers and reports gaps.

mod glob;
pub mod inproc;
pub mod iox;
mod link;
#[cfg(feature = "zenoh")]
pub mod zenoh;

pub use glob::glob_matches;
pub use link::{TlsDecl, ZenohDecl};

use std::time::Duration;

use iceoryx2::prelude::ZeroCopySend;

use gprflow_msg::{self as msg, CdrDecode, Message, MsgError, PayloadWriter, Written};

/// What a frame carries.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameKind {
    /// A message payload.
    #[default]
    Data = 0,
    /// No payload: the publisher will send nothing stamped before `stamp_ns` any more.
    Watermark = 1,
    /// No payload: the publisher will send nothing more at all.
    EndOfStream = 2,
}

impl FrameKind {
    fn from_u32(v: u32) -> Option<Self> {
        match v {
            0 => Some(Self::Data),
            1 => Some(Self::Watermark),
            2 => Some(Self::EndOfStream),
            _ => None,
        }
    }
}

/// Travels beside every payload (the iceoryx2 user header; the MCAP message header).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
pub struct FrameHeader {
    /// Per-topic sequence number of data frames, from 0, without gaps.
    pub seq: u64,
    /// Sensor time of the message (data), or the watermark (watermark/end of stream), ns.
    pub stamp_ns: i64,
    /// [`FrameKind`] as its integer value.
    pub kind: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

impl FrameHeader {
    /// A data frame header.
    pub fn data(seq: u64, stamp_ns: i64) -> Self {
        Self {
            seq,
            stamp_ns,
            kind: FrameKind::Data as u32,
            reserved: 0,
        }
    }

    /// A control frame (watermark or end of stream); `seq` is the next data seq.
    pub fn control(kind: FrameKind, next_seq: u64, stamp_ns: i64) -> Self {
        Self {
            seq: next_seq,
            stamp_ns,
            kind: kind as u32,
            reserved: 0,
        }
    }

    /// The frame kind, or `None` for a corrupt header.
    pub fn kind(&self) -> Option<FrameKind> {
        FrameKind::from_u32(self.kind)
    }
}

/// Errors of the bus.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    /// The transport could not create or open something.
    #[error("topic `{topic}`: {what}")]
    Transport {
        /// Topic concerned.
        topic: String,
        /// What failed, with the transport's own message.
        what: String,
    },
    /// A publisher found fewer subscribers than expected: a consumer is gone.
    #[error(
        "topic `{topic}` seq {seq}: delivered to {reached} of {expected} subscribers (a consumer exited or crashed)"
    )]
    SubscriberLost {
        /// Topic concerned.
        topic: String,
        /// Sequence number of the frame.
        seq: u64,
        /// Subscribers reached.
        reached: usize,
        /// Subscribers expected.
        expected: usize,
    },
    /// Expected subscribers did not connect in time.
    #[error("topic `{topic}`: {connected} of {expected} subscribers connected after {waited:?}")]
    HandshakeTimeout {
        /// Topic concerned.
        topic: String,
        /// Subscribers connected.
        connected: usize,
        /// Subscribers expected.
        expected: usize,
        /// How long we waited.
        waited: Duration,
    },
    /// Sequence numbers jumped on a lossless topic.
    #[error("topic `{topic}`: frames lost, seq {first}..{last} never arrived")]
    SeqGap {
        /// Topic concerned.
        topic: String,
        /// First missing seq.
        first: u64,
        /// One past the last missing seq.
        last: u64,
    },
    /// A header with an unknown kind.
    #[error("topic `{topic}` seq {seq}: corrupt frame header (kind {kind})")]
    CorruptHeader {
        /// Topic concerned.
        topic: String,
        /// Sequence number in the header.
        seq: u64,
        /// The unknown kind.
        kind: u32,
    },
    /// A payload that does not decode as the topic's type.
    #[error("topic `{topic}` seq {seq}: cannot decode {msg_type}: {source}")]
    Decode {
        /// Topic concerned.
        topic: String,
        /// Sequence number.
        seq: u64,
        /// Expected type.
        msg_type: &'static str,
        /// The decoding error.
        source: MsgError,
    },
    /// Encoding failed.
    #[error("topic `{topic}`: {source}")]
    Encode {
        /// Topic concerned.
        topic: String,
        /// The encoding error.
        source: MsgError,
    },
    /// A message stamped before what the topic already promised (an earlier message or a
    /// watermark): consumers merging by stamp would see time go backwards.
    #[error("topic `{topic}` seq {seq}: stamp {stamp_ns} ns is before {watermark_ns} ns already sent on this topic")]
    StampBackwards {
        /// Topic concerned.
        topic: String,
        /// Sequence number the message would have had.
        seq: u64,
        /// Its stamp.
        stamp_ns: i64,
        /// The topic's watermark.
        watermark_ns: i64,
    },
    /// Nothing was heard from the other end of a topic across machines for the link timeout.
    #[error(
        "topic `{topic}`: no word from the other host for {waited:?} (link down); data frames seq {first}..{last} not delivered"
    )]
    LinkDown {
        /// Topic concerned.
        topic: String,
        /// How long it was silent.
        waited: Duration,
        /// First data seq not delivered.
        first: u64,
        /// One past the last data seq not delivered (equal to `first`: none known).
        last: u64,
    },
    /// Shutdown was requested while waiting.
    #[error("shutdown requested")]
    Shutdown,
}

/// Result of bus operations.
pub type Result<T, E = BusError> = std::result::Result<T, E>;

/// Frames each topic buffers per subscriber in a launched graph (`gprflow launch --buffer`).
///
/// A publisher waits while a subscriber's buffer is full, so the buffer is how long a busy
/// stage may fall behind before it holds up the stages upstream, and with them every other
/// stage they feed. At 256 frames the IMU (200 Hz) buffers 1.3 s of sensor time: the
/// localisation graph replaying the 20.9-minute basement recording as fast as it goes (about
/// 30x real time) took 44 s with 16 frames, 36 s with 128, 35 with 256 and 32 with 512, the
/// ingest process peaking at 22, 50, 84 and 150 MiB (7 Dec 2026).
pub const DEFAULT_BUFFER: usize = 256;

/// How a topic is set up. Every side that opens a topic must use the same settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicConfig {
    /// Topic name, `node/output`.
    pub name: String,
    /// Frames a subscriber can queue before the publisher waits (or, latest-only, overwrites).
    pub buffer: usize,
    /// Overwrite instead of waiting; drops are counted by the subscriber.
    pub latest_only: bool,
    /// Payload size the first shared-memory segment is sized for; larger loans grow it.
    pub initial_payload_bytes: usize,
    /// Message type, when known: iceoryx2 keeps it with the topic, so that a process outside
    /// the run (`gprflow record`, `gprflow replay`) can find the topic's type, and a side that
    /// opens the topic with another type is refused.
    pub msg_type: Option<String>,
}

impl TopicConfig {
    /// A lossless topic with a 16-frame buffer.
    pub fn new(name: &str) -> Self {
        Self {
            name: name.to_owned(),
            buffer: 16,
            latest_only: false,
            initial_payload_bytes: 4096,
            msg_type: None,
        }
    }

    /// Sets the message type (builder style).
    #[must_use]
    pub fn msg_type(mut self, msg_type: &str) -> Self {
        self.msg_type = Some(msg_type.to_owned());
        self
    }

    /// Sets the buffer depth (builder style).
    #[must_use]
    pub fn buffer(mut self, frames: usize) -> Self {
        self.buffer = frames.max(1);
        self
    }

    /// Marks the topic latest-only (builder style).
    #[must_use]
    pub fn latest_only(mut self, value: bool) -> Self {
        self.latest_only = value;
        self
    }

    /// Sets the initial payload size (builder style).
    #[must_use]
    pub fn initial_payload_bytes(mut self, bytes: usize) -> Self {
        self.initial_payload_bytes = bytes.max(64);
        self
    }
}

/// Fills a loaned buffer through a [`PayloadWriter`] and hands back its [`Written`] token,
/// which only a writer that wrote every byte gives: the transport sends nothing else.
pub type FillFn<'f> = dyn FnMut(PayloadWriter<'_>) -> std::result::Result<Written, MsgError> + 'f;

/// Creates the two ends of topics.
pub trait Transport {
    /// Opens (creating if needed) `topic` for publishing.
    ///
    /// # Errors
    /// The transport's error.
    fn publisher(&self, topic: &TopicConfig) -> Result<Box<dyn Publisher>>;
    /// Opens (creating if needed) `topic` for subscribing.
    ///
    /// # Errors
    /// The transport's error.
    fn subscriber(&self, topic: &TopicConfig) -> Result<Box<dyn Subscriber>>;
}

/// The sending end of a topic.
pub trait Publisher {
    /// Topic name.
    fn topic(&self) -> &str;
    /// Loans a `len`-byte buffer (shared memory where the transport has it), lets `fill`
    /// write it, and sends it with `header` once `fill` returned that buffer's token
    /// ([`msg::fill_payload`] checks it). Waits while a lossless subscriber is full.
    /// Returns the number of subscribers reached.
    ///
    /// # Errors
    /// Transport errors, or the error of `fill`.
    fn send_with(&mut self, header: FrameHeader, len: usize, fill: &mut FillFn<'_>) -> Result<usize>;
    /// Subscribers currently connected.
    fn subscriber_count(&self) -> usize;
}

/// The receiving end of a topic.
pub trait Subscriber {
    /// Topic name.
    fn topic(&self) -> &str;
    /// The next frame, if one is queued.
    ///
    /// # Errors
    /// Transport errors.
    fn try_receive(&mut self) -> Result<Option<Frame>>;
    /// Blocks until a frame may be available or `timeout` passes. Spurious wake-ups are
    /// allowed; callers loop over `try_receive`.
    ///
    /// # Errors
    /// Transport errors.
    fn wait(&mut self, timeout: Duration) -> Result<()>;
    /// Waits for the topic's publisher and attaches to it; only then does the publisher's
    /// [`Publisher::subscriber_count`] count this subscriber. Call once before the run.
    ///
    /// # Errors
    /// [`BusError::HandshakeTimeout`], [`BusError::Shutdown`] or transport errors.
    fn attach(&mut self, _timeout: Duration, _stop: &dyn Fn() -> bool) -> Result<()> {
        Ok(())
    }
    /// Connects to the topic's publisher without announcing this subscriber as a reader it
    /// waits for: an observer that joins a running topic (`gprflow record`) and must not let
    /// a publisher start before the readers it is waiting for have attached. Returns false
    /// while the topic has no publisher.
    ///
    /// # Errors
    /// Transport errors.
    fn observe(&mut self) -> Result<bool> {
        Ok(true)
    }
}

/// A received frame. Its payload stays where the transport put it (shared memory for
/// iceoryx2) until the frame is dropped.
#[derive(Debug)]
pub struct Frame {
    /// Kind, seq and stamp.
    pub header: FrameHeader,
    data: FrameData,
}

enum FrameData {
    Iox(iox::IoxSample),
    Shared(std::sync::Arc<[u8]>),
    /// Copied out of the zenoh transport's buffers.
    #[cfg_attr(not(feature = "zenoh"), allow(dead_code))]
    Owned(Vec<u8>),
    Empty,
}

impl std::fmt::Debug for FrameData {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} bytes", self.bytes().len())
    }
}

impl FrameData {
    fn bytes(&self) -> &[u8] {
        match self {
            Self::Iox(s) => s.payload(),
            Self::Shared(b) => b,
            Self::Owned(b) => b,
            Self::Empty => &[],
        }
    }
}

impl Frame {
    /// The CDR payload (empty for control frames).
    pub fn payload(&self) -> &[u8] {
        self.data.bytes()
    }

    /// The same frame with its payload copied out of the transport's memory (an iceoryx2
    /// sample goes back to its publisher): for frames kept longer than the topic's buffer.
    pub fn detach(self) -> Frame {
        match self.data {
            FrameData::Iox(ref sample) => Frame {
                header: self.header,
                data: FrameData::Shared(std::sync::Arc::from(sample.payload())),
            },
            _ => self,
        }
    }

    /// The kind; corrupt headers are reported by [`Inbox`].
    pub fn kind(&self) -> Option<FrameKind> {
        self.header.kind()
    }
}

/// Waits until `publisher` has at least `expected` subscribers, so that nothing published
/// afterwards is lost to a subscriber that has not attached yet.
///
/// # Errors
/// [`BusError::HandshakeTimeout`], or [`BusError::Shutdown`] when `stop` turns true.
pub fn wait_for_subscribers(
    publisher: &dyn Publisher,
    expected: usize,
    timeout: Duration,
    stop: &dyn Fn() -> bool,
) -> Result<()> {
    let start = std::time::Instant::now();
    while publisher.subscriber_count() < expected {
        if stop() {
            return Err(BusError::Shutdown);
        }
        if start.elapsed() > timeout {
            return Err(BusError::HandshakeTimeout {
                topic: publisher.topic().to_owned(),
                connected: publisher.subscriber_count(),
                expected,
                waited: start.elapsed(),
            });
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok(())
}

/// A typed sending end: numbers data frames, sends watermarks and end of stream, and checks
/// that every expected subscriber is reached.
pub struct Outbox {
    publisher: Box<dyn Publisher>,
    msg_type: String,
    next_seq: u64,
    expected_subscribers: usize,
    watermark_ns: i64,
    ended: bool,
    sent: u64,
}

impl std::fmt::Debug for Outbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Outbox")
            .field("topic", &self.publisher.topic())
            .field("next_seq", &self.next_seq)
            .finish_non_exhaustive()
    }
}

impl Outbox {
    /// Wraps a publisher of `msg_type` frames that `expected_subscribers` consumers read.
    pub fn new(publisher: Box<dyn Publisher>, msg_type: &str, expected_subscribers: usize) -> Self {
        Self {
            publisher,
            msg_type: msg_type.to_owned(),
            next_seq: 0,
            expected_subscribers,
            watermark_ns: i64::MIN,
            ended: false,
            sent: 0,
        }
    }

    /// Topic name.
    pub fn topic(&self) -> &str {
        self.publisher.topic()
    }

    /// Declared message type.
    pub fn msg_type(&self) -> &str {
        &self.msg_type
    }

    /// Data frames sent.
    pub fn sent(&self) -> u64 {
        self.sent
    }

    /// The newest stamp sent or promised ([`Outbox::advance_watermark`]): nothing stamped
    /// before it can be sent any more.
    pub fn watermark_ns(&self) -> i64 {
        self.watermark_ns
    }

    /// The underlying publisher (for handshakes).
    pub fn publisher(&self) -> &dyn Publisher {
        self.publisher.as_ref()
    }

    /// Encodes `msg` straight into the loaned buffer and sends it.
    ///
    /// # Errors
    /// Encoding or transport errors; [`BusError::SubscriberLost`] when a consumer is gone.
    pub fn send<M: Message>(&mut self, msg: &M) -> Result<u64> {
        let stamp = msg.stamp_ns();
        let len = msg::encoded_len(msg);
        self.send_encoded(stamp, len, &mut |out| msg::encode_into(msg, out))
    }

    /// Sends an already encoded payload (replay, bridges).
    ///
    /// # Errors
    /// As [`Outbox::send`].
    pub fn send_bytes(&mut self, stamp_ns: i64, payload: &[u8]) -> Result<u64> {
        self.send_encoded(stamp_ns, payload.len(), &mut |mut out| {
            out.put(payload)?;
            out.finish()
        })
    }

    fn send_encoded(&mut self, stamp_ns: i64, len: usize, fill: &mut FillFn<'_>) -> Result<u64> {
        let seq = self.next_seq;
        if stamp_ns < self.watermark_ns {
            return Err(BusError::StampBackwards {
                topic: self.topic().to_owned(),
                seq,
                stamp_ns,
                watermark_ns: self.watermark_ns,
            });
        }
        let reached = self.publisher.send_with(FrameHeader::data(seq, stamp_ns), len, fill)?;
        self.check_reached(seq, reached)?;
        self.next_seq += 1;
        self.sent += 1;
        self.watermark_ns = self.watermark_ns.max(stamp_ns);
        Ok(seq)
    }

    fn check_reached(&self, seq: u64, reached: usize) -> Result<()> {
        if reached < self.expected_subscribers {
            return Err(BusError::SubscriberLost {
                topic: self.topic().to_owned(),
                seq,
                reached,
                expected: self.expected_subscribers,
            });
        }
        Ok(())
    }

    /// Promises that nothing stamped before `stamp_ns` will follow. Sends a watermark frame
    /// only when it advances.
    ///
    /// # Errors
    /// Transport errors.
    pub fn advance_watermark(&mut self, stamp_ns: i64) -> Result<()> {
        if stamp_ns <= self.watermark_ns || self.ended {
            return Ok(());
        }
        self.watermark_ns = stamp_ns;
        let header = FrameHeader::control(FrameKind::Watermark, self.next_seq, stamp_ns);
        let reached = self.publisher.send_with(header, 0, &mut |out| out.finish())?;
        self.check_reached(self.next_seq, reached)
    }

    /// Waits until every subscriber has left the topic (or `timeout` passes, or `stop`
    /// turns true). A publisher must outlive the frames it sent: with iceoryx2 the payloads
    /// live in the publisher's shared memory, and a consumer that has not read them yet
    /// would lose them if the publisher exited first. Returns whether all left.
    pub fn linger(&self, timeout: Duration, stop: &dyn Fn() -> bool) -> bool {
        let start = std::time::Instant::now();
        while self.publisher.subscriber_count() > 0 {
            if stop() || start.elapsed() > timeout {
                return false;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        true
    }

    /// Sends end of stream (once).
    ///
    /// # Errors
    /// Transport errors.
    pub fn end(&mut self) -> Result<()> {
        if self.ended {
            return Ok(());
        }
        self.ended = true;
        let header = FrameHeader::control(FrameKind::EndOfStream, self.next_seq, i64::MAX);
        let reached = self.publisher.send_with(header, 0, &mut |out| out.finish())?;
        self.check_reached(self.next_seq, reached)
    }
}

/// What an [`Inbox`] hands out.
#[derive(Debug)]
pub enum Delivery {
    /// A data frame that passed the sequence check.
    Data(Frame),
    /// The publisher's watermark advanced to this stamp.
    Watermark(i64),
    /// The publisher ended the stream.
    EndOfStream,
}

/// Counters of one input.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct InboxStats {
    /// Data frames received.
    pub received: u64,
    /// Frames skipped on a latest-only topic (sequence gaps).
    pub dropped: u64,
}

/// A checked receiving end: verifies sequence numbers (gaps are an error on lossless topics
/// and counted drops on latest-only ones), decodes headers, and tracks end of stream.
pub struct Inbox {
    subscriber: Box<dyn Subscriber>,
    latest_only: bool,
    expected_seq: u64,
    /// The first frame sets the sequence (a subscriber that joined a running topic).
    joined_late: bool,
    ended: bool,
    stats: InboxStats,
}

impl std::fmt::Debug for Inbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Inbox")
            .field("topic", &self.subscriber.topic())
            .field("expected_seq", &self.expected_seq)
            .field("ended", &self.ended)
            .finish_non_exhaustive()
    }
}

impl Inbox {
    /// Wraps a subscriber.
    pub fn new(subscriber: Box<dyn Subscriber>, latest_only: bool) -> Self {
        Self {
            subscriber,
            latest_only,
            expected_seq: 0,
            joined_late: false,
            ended: false,
            stats: InboxStats::default(),
        }
    }

    /// Wraps a subscriber that joins a topic already running: its first frame, whatever its
    /// seq, starts the sequence check.
    pub fn joining(subscriber: Box<dyn Subscriber>, latest_only: bool) -> Self {
        Self {
            joined_late: true,
            ..Self::new(subscriber, latest_only)
        }
    }

    /// Topic name.
    pub fn topic(&self) -> &str {
        self.subscriber.topic()
    }

    /// True once end of stream was received.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Counters so far.
    pub fn stats(&self) -> InboxStats {
        self.stats
    }

    /// The next delivery, if one is queued.
    ///
    /// # Errors
    /// Transport errors, corrupt headers, sequence gaps on lossless topics.
    pub fn try_next(&mut self) -> Result<Option<Delivery>> {
        if self.ended {
            return Ok(None);
        }
        let Some(frame) = self.subscriber.try_receive()? else {
            return Ok(None);
        };
        let header = frame.header;
        let Some(kind) = header.kind() else {
            return Err(BusError::CorruptHeader {
                topic: self.topic().to_owned(),
                seq: header.seq,
                kind: header.kind,
            });
        };
        if std::mem::take(&mut self.joined_late) {
            self.expected_seq = header.seq;
        }
        // Control frames carry the next data seq: a gap before them is a loss too.
        if header.seq != self.expected_seq {
            if header.seq < self.expected_seq || !self.latest_only {
                return Err(BusError::SeqGap {
                    topic: self.topic().to_owned(),
                    first: self.expected_seq,
                    last: header.seq,
                });
            }
            self.stats.dropped += header.seq - self.expected_seq;
            self.expected_seq = header.seq;
        }
        Ok(Some(match kind {
            FrameKind::Data => {
                self.expected_seq += 1;
                self.stats.received += 1;
                Delivery::Data(frame)
            }
            FrameKind::Watermark => Delivery::Watermark(header.stamp_ns),
            FrameKind::EndOfStream => {
                self.ended = true;
                Delivery::EndOfStream
            }
        }))
    }

    /// Connects to the topic's publisher as an observer (see [`Subscriber::observe`]).
    ///
    /// # Errors
    /// As [`Subscriber::observe`].
    pub fn observe(&mut self) -> Result<bool> {
        self.subscriber.observe()
    }

    /// Attaches to the topic's publisher (see [`Subscriber::attach`]).
    ///
    /// # Errors
    /// As [`Subscriber::attach`].
    pub fn attach(&mut self, timeout: Duration, stop: &dyn Fn() -> bool) -> Result<()> {
        self.subscriber.attach(timeout, stop)
    }

    /// Blocks until a frame may be queued or `timeout` passes (does not consume).
    ///
    /// # Errors
    /// Transport errors.
    pub fn wait(&mut self, timeout: Duration) -> Result<()> {
        if self.ended {
            return Ok(());
        }
        self.subscriber.wait(timeout)
    }

    /// Waits for the next delivery, up to `timeout`.
    ///
    /// # Errors
    /// As [`Inbox::try_next`].
    pub fn next_timeout(&mut self, timeout: Duration) -> Result<Option<Delivery>> {
        if let Some(d) = self.try_next()? {
            return Ok(Some(d));
        }
        if self.ended {
            return Ok(None);
        }
        self.subscriber.wait(timeout)?;
        self.try_next()
    }
}

/// Decodes a data frame's payload as `M`, naming topic and seq on failure.
///
/// # Errors
/// [`BusError::Decode`].
pub fn decode_frame<'f, M: CdrDecode<'f> + Message>(topic: &str, frame: &'f Frame) -> Result<M> {
    msg::decode(frame.payload()).map_err(|source| BusError::Decode {
        topic: topic.to_owned(),
        seq: frame.header.seq,
        msg_type: M::TYPE_NAME,
        source,
    })
}
