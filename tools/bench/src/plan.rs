//! What the two processes agree on: the phases of a run, the control messages between the
//! driver and its partner, the topic settings, and how long to wait for the other side.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::bail;
use gprflow::bus::TopicConfig;
use gprflow::graph::ZenohDecl;
use serde::{Deserialize, Serialize};

use crate::IpcArgs;

/// Message sizes measured, in bytes.
pub const SIZES: [usize; 2] = [4 * 1024, 1024 * 1024];

/// Frames a subscriber queues before the publisher waits: the gprflow default topic depth.
pub const TOPIC_BUFFER: usize = 16;

/// Payload size of the end-of-stream acknowledgement.
pub const ACK_BYTES: usize = 8;

/// How a receiver waits for the next message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WaitMode {
    /// Sleeps until woken: the iceoryx2 event (`Subscriber::wait`), a blocking socket read.
    Event,
    /// Busy-polls: `Subscriber::try_receive` / non-blocking socket reads in a loop.
    Spin,
}

impl WaitMode {
    /// Short name for tables.
    pub fn label(self) -> &'static str {
        match self {
            Self::Event => "event",
            Self::Spin => "spin",
        }
    }
}

/// What a phase measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Test {
    /// Request of `size` bytes, reply of `size` bytes, one at a time.
    PingPong,
    /// `warmup` then `count` messages one way as fast as back-pressure allows; the receiver
    /// acknowledges after the warm-up and after the last message.
    Stream,
}

/// The path a phase goes over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Link {
    /// `gprflow::bus::iox::IoxTransport`.
    Iceoryx2,
    /// The Unix stream socket between the two processes.
    UnixSocket,
    /// `gprflow::bus::zenoh::ZenohTransport`: a zenoh session of the driver that listens and
    /// one of a second partner process that connects (see [`ZenohSetup`]).
    Zenoh,
}

/// Key prefix of the benchmark's zenoh topics, the same in both processes.
pub const ZENOH_KEY_PREFIX: &str = "gprflow/bench";

/// The zenoh link of a run (`--zenoh-listen`): where the driver listens, where its zenoh
/// partner connects, and the network namespace that partner runs in.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ZenohSetup {
    /// The driver's listening endpoint (`tcp/10.77.50.1:7447`).
    pub listen: String,
    /// The endpoint the partner connects to.
    pub connect: String,
    /// The network namespace the partner is started in (`ip netns exec`); `None`: the
    /// driver's own.
    pub partner_netns: Option<String>,
}

impl ZenohSetup {
    /// The zenoh link asked for by `args`, if any.
    pub fn from_args(args: &IpcArgs) -> Option<Self> {
        let listen = args.zenoh_listen.clone()?;
        Some(Self {
            connect: args.zenoh_connect.clone().unwrap_or_else(|| listen.clone()),
            listen,
            partner_netns: args.zenoh_partner_netns.clone(),
        })
    }

    /// Row label: the endpoint's protocol and where the partner runs
    /// (`zenoh tcp, 2 netns`).
    pub fn label(&self) -> String {
        let protocol = self.listen.split_once('/').map_or("?", |(protocol, _)| protocol);
        let namespaces = if self.partner_netns.is_some() { 2 } else { 1 };
        format!("zenoh {protocol}, {namespaces} netns")
    }

    /// The driver's session: listens, connects nowhere.
    pub fn driver_decl(&self) -> ZenohDecl {
        ZenohDecl {
            listen: vec![self.listen.clone()],
            ..ZenohDecl::default()
        }
    }
}

/// The partner's session: connects to `endpoint`, listens nowhere.
pub fn zenoh_partner_decl(endpoint: &str) -> ZenohDecl {
    ZenohDecl {
        connect: vec![endpoint.to_owned()],
        ..ZenohDecl::default()
    }
}

/// One phase, sent by the driver to its partner as a JSON line on the partner's stdin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Phase {
    /// Unique within the run: names the phase's topics.
    pub id: u32,
    /// Transport.
    pub link: Link,
    /// Ping-pong or stream.
    pub test: Test,
    /// How receivers wait (both sides).
    pub mode: WaitMode,
    /// Payload bytes per message.
    pub size: usize,
    /// Unrecorded messages (round trips) first.
    pub warmup: usize,
    /// Recorded messages (round trips).
    pub count: usize,
    /// Receivers check one payload byte in this many.
    pub touch_stride: usize,
}

impl Phase {
    /// Topic from the driver to the partner (pings, stream data).
    pub fn forward_topic(&self) -> TopicConfig {
        let what = match self.test {
            Test::PingPong => "ping",
            Test::Stream => "data",
        };
        topic(self.id, what, self.size)
    }

    /// Topic from the partner back to the driver (pongs, acknowledgements).
    pub fn backward_topic(&self) -> TopicConfig {
        match self.test {
            Test::PingPong => topic(self.id, "pong", self.size),
            Test::Stream => topic(self.id, "ack", ACK_BYTES),
        }
    }
}

/// The one place topic settings are made: both processes call it with the same arguments.
fn topic(phase: u32, what: &str, size: usize) -> TopicConfig {
    TopicConfig::new(&format!("bench/p{phase}/{what}"))
        .buffer(TOPIC_BUFFER)
        .initial_payload_bytes(size)
}

/// The partner's answers, one JSON line each on its stdout.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reply {
    /// Its ends of the phase are open (and its publishers see the driver's subscribers).
    Ready,
    /// The phase is over and its ends are closed.
    Done,
}

/// Message counts per size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Counts {
    /// Payload bytes.
    pub size: usize,
    /// Recorded ping-pong round trips.
    pub round_trips: usize,
    /// Unrecorded round trips before them.
    pub round_trip_warmup: usize,
    /// Recorded stream messages.
    pub stream_messages: usize,
    /// Unrecorded stream messages before them.
    pub stream_warmup: usize,
    /// Timed in-process copies.
    pub copies: usize,
}

impl Counts {
    /// Counts for `size` under `args`.
    pub fn for_size(size: usize, args: &IpcArgs) -> Self {
        let small = size <= 64 * 1024;
        let (default_trips, default_messages) = match (args.quick, small) {
            (true, true) => (100, 500),
            (true, false) => (20, 50),
            (false, true) => (2000, 20_000),
            (false, false) => (500, 2000),
        };
        let round_trips = args.iterations.unwrap_or(default_trips).max(1);
        let stream_messages = args.messages.unwrap_or(default_messages).max(1);
        Self {
            size,
            round_trips,
            round_trip_warmup: (round_trips / 10).clamp(5, 200),
            stream_messages,
            stream_warmup: (stream_messages / 10).clamp(5, 1000),
            copies: round_trips.saturating_mul(10),
        }
    }
}

/// How long a process waits for the other and when it gives up.
#[derive(Debug, Clone)]
pub struct Patience {
    stop: Arc<AtomicBool>,
    timeout: Option<Duration>,
}

impl Patience {
    /// Gives up when `stop` turns true or, with a `timeout`, when one wait lasts longer.
    pub fn new(stop: Arc<AtomicBool>, timeout: Option<Duration>) -> Self {
        Self { stop, timeout }
    }

    /// True once shutdown was requested.
    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Errors when the wait that began at `since` should end; `what` names what was awaited
    /// (called only then).
    ///
    /// # Errors
    /// Shutdown requested, or the timeout passed (the other process is gone or stuck).
    pub fn check(&self, since: Instant, what: impl FnOnce() -> String) -> anyhow::Result<()> {
        if self.stopped() {
            bail!("{}: stopped (interrupted, or the other process went away)", what());
        }
        if let Some(timeout) = self.timeout
            && since.elapsed() > timeout
        {
            bail!(
                "{}: nothing from the other process for {timeout:?} (it is gone or stuck)",
                what()
            );
        }
        Ok(())
    }
}

/// Busy-wait iterations between two [`Patience::check`]s.
pub const SPINS_PER_CHECK: u32 = 1024;

/// Sets `stop` on SIGINT and SIGTERM so that both processes close their iceoryx2 resources
/// before exiting; a second signal while `stop` is set terminates at once.
///
/// # Errors
/// When a handler cannot be installed.
pub fn watch_signals(stop: &Arc<AtomicBool>) -> anyhow::Result<()> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    for signal in [SIGINT, SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(stop))?;
        signal_hook::flag::register(signal, Arc::clone(stop))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_travel_as_json_lines() -> anyhow::Result<()> {
        let phase = Phase {
            id: 3,
            link: Link::Iceoryx2,
            test: Test::Stream,
            mode: WaitMode::Spin,
            size: 4096,
            warmup: 5,
            count: 10,
            touch_stride: 64,
        };
        let line = serde_json::to_string(&phase)?;
        assert!(!line.contains('\n'));
        assert_eq!(serde_json::from_str::<Phase>(&line)?, phase);
        Ok(())
    }

    #[test]
    fn both_sides_get_the_same_topics() {
        let phase = Phase {
            id: 1,
            link: Link::Iceoryx2,
            test: Test::PingPong,
            mode: WaitMode::Event,
            size: 1 << 20,
            warmup: 1,
            count: 1,
            touch_stride: 64,
        };
        assert_eq!(phase.forward_topic(), phase.forward_topic());
        assert_eq!(phase.forward_topic().initial_payload_bytes, 1 << 20);
        assert_eq!(phase.backward_topic().name, "bench/p1/pong");
    }

    #[test]
    fn zenoh_rows_say_where_the_partner_runs() {
        let mut setup = ZenohSetup {
            listen: "tcp/10.77.50.1:7447".to_owned(),
            connect: "tcp/10.77.50.1:7447".to_owned(),
            partner_netns: Some("ns2".to_owned()),
        };
        assert_eq!(setup.label(), "zenoh tcp, 2 netns");
        setup.partner_netns = None;
        assert_eq!(setup.label(), "zenoh tcp, 1 netns");
        assert_eq!(setup.driver_decl().listen, [setup.listen.clone()]);
        assert!(zenoh_partner_decl(&setup.connect).listen.is_empty());
    }
}
