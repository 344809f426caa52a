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

mod config;
mod envelope;
mod publisher;
mod subscriber;
mod window;

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use ::zenoh::Wait;

pub use config::{check_settings, config, key_prefix};
pub use publisher::ZenohPublisher;
pub use subscriber::ZenohSubscriber;

use crate::{BusError, Publisher, Result, Subscriber, TopicConfig, Transport, ZenohDecl};

/// Default of [`ZenohDecl::link_timeout_s`].
pub const DEFAULT_LINK_TIMEOUT: Duration = Duration::from_secs(60);
/// Heartbeat period of both sides.
const HEARTBEAT: Duration = Duration::from_millis(100);
/// Resend what is unacknowledged when nothing advanced for this long.
const RESEND_AFTER: Duration = Duration::from_millis(300);
const POLL: Duration = Duration::from_millis(20);
/// Frames of a lossless topic a publisher sends ahead of the remote consumer at most, however
/// deep the topic's buffer: with more in flight, a link that stalls fills zenoh's transmission
/// queue, and zenoh then closes the session itself before the link timeout can report what
/// was not delivered.
const MAX_IN_FLIGHT: usize = 16;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

fn err(topic: &str, what: impl std::fmt::Display) -> BusError {
    BusError::Transport {
        topic: topic.to_owned(),
        what: what.to_string(),
    }
}

/// The zenoh transport of one process: one zenoh session; topic `node/output` travels on
/// the keys `PREFIX/node/output/d` (frames) and `PREFIX/node/output/a` (acknowledgements).
#[derive(Clone)]
pub struct ZenohTransport {
    pub(super) session: ::zenoh::Session,
    key_prefix: String,
    pub(super) link_timeout: Duration,
    pub(super) stop: Arc<AtomicBool>,
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

    pub(super) fn keys(
        &self,
        topic: &str,
    ) -> Result<(::zenoh::key_expr::KeyExpr<'static>, ::zenoh::key_expr::KeyExpr<'static>)> {
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
