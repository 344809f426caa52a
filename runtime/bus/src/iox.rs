//! iceoryx2 transport: shared memory between processes on one machine.
//!
//! Each topic is an iceoryx2 publish-subscribe service of byte slices with a
//! [`FrameHeader`] user header, plus an event service that wakes subscribers after each
//! send (no polling). A publisher loans a slice of shared memory and the message is encoded
//! straight into it; a subscriber reads the payload in place.
//!
//! All processes of one run share a resource prefix (`Bus::prefix`), so that concurrent runs
//! never see each other's services and everything a run leaves behind can be found and
//! removed by the launcher.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher as IoxPublisher;
use iceoryx2::port::subscriber::Subscriber as IoxSubscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::service::attribute::{AttributeKey, AttributeSpecifier, AttributeValue, AttributeVerifier};
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as StaticPattern;

use gprflow_msg as msg;

use super::{BusError, FillFn, Frame, FrameData, FrameHeader, Publisher, Result, Subscriber, TopicConfig, Transport};

/// Alignment of every payload: CDR aligns primitives to at most 8 bytes relative to the
/// payload start, so 8-byte aligned payloads make every array viewable in place.
const PAYLOAD_ALIGNMENT: usize = 8;
const MAX_PUBLISHERS: usize = 2;
const MAX_SUBSCRIBERS: usize = 16;
const MAX_BORROWED: usize = 4;

/// A received iceoryx2 sample, kept alive while its [`Frame`] lives.
pub(crate) struct IoxSample(Sample<ipc::Service, [u8], FrameHeader>);

impl IoxSample {
    pub(crate) fn payload(&self) -> &[u8] {
        self.0.payload()
    }
}

fn err(topic: &str, what: impl std::fmt::Display) -> BusError {
    BusError::Transport {
        topic: topic.to_owned(),
        what: what.to_string(),
    }
}

/// Every topic's service is named `gprflow/{topic}`.
const SERVICE_ROOT: &str = "gprflow/";
/// Service attribute: the topic's message type.
const TYPE_KEY: &str = "gprflow.type";
/// Service attribute: how many subscribers of the run that declared the topic read it.
const READERS_KEY: &str = "gprflow.readers";

fn attribute_key(key: &str) -> Result<AttributeKey> {
    AttributeKey::new(key.as_bytes()).map_err(|e| err(key, format!("attribute key: {e:?}")))
}

fn attribute_value(topic: &str, value: &str) -> Result<AttributeValue> {
    AttributeValue::new(value.as_bytes()).map_err(|e| err(topic, format!("attribute `{value}`: {e:?}")))
}

/// A topic found on the bus ([`IoxTransport::topics`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BusTopic {
    /// Topic name, `node/output`.
    pub name: String,
    /// Message type the topic keeps (none when opened without one).
    pub msg_type: Option<String>,
    /// The topic overwrites instead of waiting.
    pub latest_only: bool,
    /// Frames a subscriber may queue.
    pub buffer: usize,
}

impl BusTopic {
    /// Settings to open this topic with, identical to its own.
    pub fn topic_config(&self) -> TopicConfig {
        let config = TopicConfig::new(&self.name)
            .buffer(self.buffer)
            .latest_only(self.latest_only);
        match &self.msg_type {
            Some(t) => config.msg_type(t),
            None => config,
        }
    }
}

/// A topic declared by [`IoxTransport::declare`]; it stays while this lives.
pub struct DeclaredTopic {
    _factory: PubSubFactory<ipc::Service, [u8], FrameHeader>,
}

impl std::fmt::Debug for DeclaredTopic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DeclaredTopic").finish_non_exhaustive()
    }
}

/// The iceoryx2 resource prefix of the named bus `name` (`launch --bus`, `gprflow replay`,
/// `gprflow record`): processes on the same named bus see each other's topics.
///
/// # Errors
/// A name that is empty, longer than 32 characters, or has characters other than ASCII
/// letters, digits, `-` and `_`.
pub fn bus_prefix(name: &str) -> std::result::Result<String, String> {
    let ok = !name.is_empty()
        && name.len() <= 32
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok {
        Ok(format!("gfbus_{name}_"))
    } else {
        Err(format!(
            "bus name `{name}`: use 1 to 32 ASCII letters, digits, `-` or `_`"
        ))
    }
}

/// How long a process waits for a service or node resource another process is creating or
/// cleaning up ([`run_config`]).
pub const CREATION_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);

/// iceoryx2 settings of a run: every process of the run uses the same prefix.
pub fn run_config(prefix: &str) -> std::result::Result<Config, String> {
    // defaults, not a config file: every process of a run must agree
    let mut config = Config::default();
    config.global.prefix =
        FileName::new(prefix.as_bytes()).map_err(|e| format!("iceoryx2 prefix `{prefix}`: {e:?}"))?;
    // how long opening a service another process is creating may take: iceoryx2's 1 s default
    // ran out once when a loaded machine started many runs at once (a stage failed with
    // `EventOpenError(DoesNotExist)` for a service its neighbour was still creating)
    config.global.creation_timeout = CREATION_TIMEOUT;
    Ok(config)
}

/// The iceoryx2 transport of one process.
pub struct IoxTransport {
    node: Node<ipc::Service>,
    stop: Arc<AtomicBool>,
}

impl std::fmt::Debug for IoxTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IoxTransport").field("node", &self.node.name()).finish()
    }
}

impl IoxTransport {
    /// Creates this process's iceoryx2 node named `node_name` under the run's `prefix`.
    /// Blocking sends give up when `stop` turns true.
    ///
    /// # Errors
    /// When the node cannot be created.
    pub fn new(node_name: &str, prefix: &str, stop: Arc<AtomicBool>) -> Result<Self> {
        let config = run_config(prefix).map_err(|e| err(node_name, e))?;
        let name = NodeName::new(node_name).map_err(|e| err(node_name, format!("node name: {e:?}")))?;
        let node = NodeBuilder::new()
            .name(&name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| err(node_name, format!("cannot create iceoryx2 node: {e:?}")))?;
        Ok(Self { node, stop })
    }

    /// Removes resources of dead processes of this run (call after a crash).
    pub fn cleanup_dead_nodes(&self) {
        let _ = self.node.try_cleanup_dead_nodes();
    }

    fn pubsub_builder(
        &self,
        topic: &str,
    ) -> Result<iceoryx2::service::builder::publish_subscribe::Builder<[u8], FrameHeader, ipc::Service>> {
        let name = ServiceName::new(&format!("{SERVICE_ROOT}{topic}"))
            .map_err(|e| err(topic, format!("service name: {e:?}")))?;
        let alignment =
            Alignment::new(PAYLOAD_ALIGNMENT).ok_or_else(|| err(topic, "payload alignment is not a power of two"))?;
        Ok(self
            .node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .user_header::<FrameHeader>()
            .payload_alignment(alignment))
    }

    /// The builder of `topic`'s service with the settings every side of it uses.
    fn pubsub_settings(
        &self,
        topic: &TopicConfig,
    ) -> Result<iceoryx2::service::builder::publish_subscribe::Builder<[u8], FrameHeader, ipc::Service>> {
        Ok(self
            .pubsub_builder(&topic.name)?
            .subscriber_max_buffer_size(topic.buffer)
            .subscriber_max_borrowed_samples(MAX_BORROWED)
            .history_size(0)
            .max_publishers(MAX_PUBLISHERS)
            .max_subscribers(MAX_SUBSCRIBERS)
            .enable_safe_overflow(topic.latest_only))
    }

    fn pubsub(&self, topic: &TopicConfig) -> Result<PubSubFactory<ipc::Service, [u8], FrameHeader>> {
        let mut verifier = AttributeVerifier::new();
        if let Some(t) = &topic.msg_type {
            verifier = verifier
                .require(&attribute_key(TYPE_KEY)?, &attribute_value(&topic.name, t)?)
                .map_err(|e| err(&topic.name, format!("{e:?}")))?;
        }
        self.pubsub_settings(topic)?
            .open_or_create_with_attributes(&verifier)
            .map_err(|e| err(&topic.name, format!("cannot open publish-subscribe service: {e:?}")))
    }

    /// Creates `topic` ahead of its publisher, saying that `readers` subscribers of this run
    /// read it: a publisher outside the run (`gprflow replay`) waits for that many before it
    /// sends (see [`IoxTransport::declared_readers`]). The topic stays declared while the
    /// returned handle lives.
    ///
    /// # Errors
    /// When the topic exists already or cannot be created.
    pub fn declare(&self, topic: &TopicConfig, readers: usize) -> Result<DeclaredTopic> {
        let mut attributes = AttributeSpecifier::new()
            .define(
                &attribute_key(READERS_KEY)?,
                &attribute_value(&topic.name, &readers.to_string())?,
            )
            .map_err(|e| err(&topic.name, format!("{e:?}")))?;
        if let Some(t) = &topic.msg_type {
            attributes = attributes
                .define(&attribute_key(TYPE_KEY)?, &attribute_value(&topic.name, t)?)
                .map_err(|e| err(&topic.name, format!("{e:?}")))?;
        }
        let factory = self
            .pubsub_settings(topic)?
            .create_with_attributes(&attributes)
            .map_err(|e| err(&topic.name, format!("cannot declare the topic: {e:?}")))?;
        Ok(DeclaredTopic { _factory: factory })
    }

    /// The subscribers a run declared for `topic` ([`IoxTransport::declare`]), if it did.
    pub fn declared_readers(&self, topic: &str) -> Option<usize> {
        let factory = self.pubsub_builder(topic).ok()?.open().ok()?;
        let key = attribute_key(READERS_KEY).ok()?;
        let value = factory.attributes().key_value(&key, 0)?;
        std::str::from_utf8(value.as_bytes()).ok()?.parse().ok()
    }

    /// The topics on this bus now (the prefix's publish-subscribe services), with the message
    /// type each keeps, sorted by name.
    ///
    /// # Errors
    /// When the services cannot be listed.
    pub fn topics(&self) -> Result<Vec<BusTopic>> {
        let config = self.node.config().clone();
        let type_key = attribute_key(TYPE_KEY)?;
        let mut found = Vec::new();
        ipc::Service::list(&config, |details| {
            let static_details = &details.static_details;
            if let StaticPattern::PublishSubscribe(pubsub) = static_details.messaging_pattern()
                && let Some(topic) = static_details.name().as_str().strip_prefix(SERVICE_ROOT)
            {
                let msg_type = static_details
                    .attributes()
                    .key_value(&type_key, 0)
                    .and_then(|v| std::str::from_utf8(v.as_bytes()).ok())
                    .map(str::to_owned);
                let latest_only = pubsub.has_safe_overflow();
                let buffer = pubsub.subscriber_max_buffer_size();
                found.push(BusTopic {
                    name: topic.to_owned(),
                    msg_type,
                    latest_only,
                    buffer,
                });
            }
            CallbackProgression::Continue
        })
        .map_err(|e| err("*", format!("cannot list the bus's topics: {e:?}")))?;
        found.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(found)
    }

    fn event(&self, topic: &TopicConfig, purpose: &str) -> Result<EventFactory> {
        let name = ServiceName::new(&format!("gprflow/{}/{purpose}", topic.name))
            .map_err(|e| err(&topic.name, format!("service name: {e:?}")))?;
        self.node
            .service_builder(&name)
            .event()
            .max_notifiers(MAX_SUBSCRIBERS)
            .max_listeners(MAX_SUBSCRIBERS)
            .open_or_create()
            .map_err(|e| err(&topic.name, format!("cannot open event service: {e:?}")))
    }
}

impl Transport for IoxTransport {
    fn publisher(&self, topic: &TopicConfig) -> Result<Box<dyn Publisher>> {
        let service = self.pubsub(topic)?;
        let stop = self.stop.clone();
        let latest_only = topic.latest_only;
        let strategy = if topic.latest_only {
            BackpressureStrategy::DiscardData
        } else {
            BackpressureStrategy::RetryUntilDelivered
        };
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(topic.initial_payload_bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(strategy)
            .set_backpressure_handler(move |info: &iceoryx2::port::BackpressureInfo| {
                if stop.load(Ordering::Relaxed) {
                    return iceoryx2::port::BackpressureAction::DiscardDataAndFail;
                }
                // Spin briefly, then sleep so that a full consumer on the other core gets
                // the CPU instead of a busy publisher.
                if info.retries > 64 {
                    let pause = if info.elapsed_time > Duration::from_millis(10) {
                        500
                    } else {
                        20
                    };
                    std::thread::sleep(Duration::from_micros(pause));
                }
                if latest_only {
                    iceoryx2::port::BackpressureAction::DiscardData
                } else {
                    iceoryx2::port::BackpressureAction::Retry
                }
            })
            .create()
            .map_err(|e| err(&topic.name, format!("cannot create publisher: {e:?}")))?;
        let notifier = self
            .event(topic, "wake")?
            .notifier_builder()
            .create()
            .map_err(|e| err(&topic.name, format!("cannot create notifier: {e:?}")))?;
        let ready = self.event(topic, "ready")?;
        Ok(Box::new(IoxPub {
            topic: topic.name.clone(),
            service,
            ready,
            publisher,
            notifier,
        }))
    }

    fn subscriber(&self, topic: &TopicConfig) -> Result<Box<dyn Subscriber>> {
        let service = self.pubsub(topic)?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(topic.buffer)
            .create()
            .map_err(|e| err(&topic.name, format!("cannot create subscriber: {e:?}")))?;
        let listener = self
            .event(topic, "wake")?
            .listener_builder()
            .create()
            .map_err(|e| err(&topic.name, format!("cannot create listener: {e:?}")))?;
        Ok(Box::new(IoxSub {
            topic: topic.name.clone(),
            service,
            ready: self.event(topic, "ready")?,
            ready_notifier: None,
            subscriber,
            listener,
        }))
    }
}

type EventFactory = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;

struct IoxPub {
    topic: String,
    service: PubSubFactory<ipc::Service, [u8], FrameHeader>,
    /// Subscribers announce here that they have attached (see [`IoxSub::attach`]).
    ready: EventFactory,
    publisher: IoxPublisher<ipc::Service, [u8], FrameHeader>,
    notifier: Notifier<ipc::Service>,
}

impl Publisher for IoxPub {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn send_with(&mut self, header: FrameHeader, len: usize, fill: &mut FillFn<'_>) -> Result<usize> {
        let mut sample = self
            .publisher
            .loan_slice_uninit(len)
            .map_err(|e| err(&self.topic, format!("cannot loan {len} bytes: {e:?}")))?;
        *sample.user_header_mut() = header;
        msg::fill_payload(sample.payload_mut(), fill).map_err(|source| BusError::Encode {
            topic: self.topic.clone(),
            source,
        })?;
        // SAFETY: `fill_payload` returned Ok: `fill` handed back the token of this very
        // buffer, which only a writer that wrote each of its bytes makes.
        let sample = unsafe { sample.assume_init() };
        let reached = sample
            .send()
            .map_err(|e| err(&self.topic, format!("send failed: {e:?}")))?;
        self.notifier
            .notify()
            .map_err(|e| err(&self.topic, format!("wake-up failed: {e:?}")))?;
        Ok(reached)
    }

    fn subscriber_count(&self) -> usize {
        // Only subscribers that attached to our connection count: frames sent to one that
        // has registered but not attached are lost once its buffer is full.
        let n = self
            .service
            .dynamic_config()
            .number_of_subscribers()
            .min(self.ready.dynamic_config().number_of_notifiers());
        if n > 0 {
            let _ = self.publisher.update_connections();
        }
        n
    }
}

struct IoxSub {
    topic: String,
    service: PubSubFactory<ipc::Service, [u8], FrameHeader>,
    ready: EventFactory,
    ready_notifier: Option<Notifier<ipc::Service>>,
    subscriber: IoxSubscriber<ipc::Service, [u8], FrameHeader>,
    listener: Listener<ipc::Service>,
}

impl Subscriber for IoxSub {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn try_receive(&mut self) -> Result<Option<Frame>> {
        let sample = self
            .subscriber
            .receive()
            .map_err(|e| err(&self.topic, format!("receive failed: {e:?}")))?;
        Ok(sample.map(|s| Frame {
            header: *s.user_header(),
            data: FrameData::Iox(IoxSample(s)),
        }))
    }

    fn wait(&mut self, timeout: Duration) -> Result<()> {
        if self
            .subscriber
            .has_samples()
            .map_err(|e| err(&self.topic, format!("{e:?}")))?
        {
            return Ok(());
        }
        match self.listener.timed_wait(|_| {}, timeout) {
            // a signal woke us: the caller checks its stop flag
            Ok(_) | Err(iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => Ok(()),
            Err(e) => Err(err(&self.topic, format!("wait failed: {e:?}"))),
        }
    }

    fn attach(&mut self, timeout: Duration, stop: &dyn Fn() -> bool) -> Result<()> {
        let start = std::time::Instant::now();
        while self.service.dynamic_config().number_of_publishers() == 0 {
            if stop() {
                return Err(BusError::Shutdown);
            }
            if start.elapsed() > timeout {
                return Err(BusError::HandshakeTimeout {
                    topic: self.topic.clone(),
                    connected: 0,
                    expected: 1,
                    waited: start.elapsed(),
                });
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        self.subscriber
            .update_connections()
            .map_err(|e| err(&self.topic, format!("cannot attach to the publisher: {e:?}")))?;
        if self.ready_notifier.is_none() {
            // a reader the publisher waits for: it counts notifiers of `ready`
            self.ready_notifier = Some(
                self.ready
                    .notifier_builder()
                    .create()
                    .map_err(|e| err(&self.topic, format!("cannot announce readiness: {e:?}")))?,
            );
        }
        Ok(())
    }

    fn observe(&mut self) -> Result<bool> {
        if self.service.dynamic_config().number_of_publishers() == 0 {
            return Ok(false);
        }
        self.subscriber
            .update_connections()
            .map_err(|e| err(&self.topic, format!("cannot connect to the publisher: {e:?}")))?;
        Ok(true)
    }
}
