//! One conformance suite, run against every [`Transport`]: iceoryx2 shared memory, zenoh
//! (two sessions over TCP on the loopback interface) and the in-process transport. Each case runs a publisher and a subscriber on two threads, each
//! with its own transport handle, as two processes would.

// Tests spawn short-lived helper threads; names would add nothing.
#![allow(clippy::disallowed_methods)]

use std::borrow::Cow;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use gprflow_bus::inproc::InProcess;
use gprflow_bus::iox::IoxTransport;
use gprflow_bus::zenoh::ZenohTransport;
use gprflow_bus::{self as bus, BusError, Delivery, FrameHeader, Inbox, Outbox, TopicConfig, Transport, ZenohDecl};

use gprflow_msg::{self as msg, Header, Message, Trace};

const TIMEOUT: Duration = Duration::from_secs(10);

/// Makes transport handles that see the same topics.
trait Sut: Send + Sync + Clone + 'static {
    fn transport(&self, node: &str) -> Box<dyn Transport>;
    /// Waits until frames the publisher handed over have reached the subscriber's queue:
    /// at once on one machine; over a network, sends return while frames are in flight.
    fn settle(&self) {}
}

#[derive(Clone)]
struct Iox {
    prefix: String,
    stop: Arc<AtomicBool>,
}

impl Sut for Iox {
    fn transport(&self, node: &str) -> Box<dyn Transport> {
        Box::new(IoxTransport::new(node, &self.prefix, self.stop.clone()).expect("iceoryx2 node"))
    }
}

/// Two zenoh sessions: the subscriber's listens on a free loopback port, the publisher's
/// connects to it.
#[derive(Clone)]
struct Zenoh {
    port: u16,
    prefix: String,
    stop: Arc<AtomicBool>,
}

impl Zenoh {
    fn new() -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        Self {
            port,
            prefix: format!("gprflow/conformance/{}", unique_prefix().trim_end_matches('_')),
            stop: Arc::new(AtomicBool::new(false)),
        }
    }
}

impl Sut for Zenoh {
    fn transport(&self, node: &str) -> Box<dyn Transport> {
        let endpoint = vec![format!("tcp/127.0.0.1:{}", self.port)];
        let decl = if node == "sub" {
            ZenohDecl {
                listen: endpoint,
                ..ZenohDecl::default()
            }
        } else {
            ZenohDecl {
                connect: endpoint,
                ..ZenohDecl::default()
            }
        };
        Box::new(ZenohTransport::open(&decl, &self.prefix, self.stop.clone()).expect("zenoh session"))
    }

    fn settle(&self) {
        std::thread::sleep(Duration::from_millis(500));
    }
}

#[derive(Clone)]
struct InProc(InProcess);

impl Sut for InProc {
    fn transport(&self, _: &str) -> Box<dyn Transport> {
        Box::new(self.0.clone())
    }
}

fn trace(i: u64, samples: usize) -> Trace<'static> {
    Trace {
        header: Header::new(1_000 + i as i64, "gpr"),
        samples_f32: Cow::Owned((0..samples).map(|k| (k as u64 + i) as f32).collect()),
        ..Trace::default()
    }
}

fn never() -> bool {
    false
}

/// Runs `publish` on a thread with a handshaken [`Outbox`] and returns a subscribed [`Inbox`].
fn pair<S: Sut>(
    sut: &S,
    topic: &TopicConfig,
    required: usize,
    publish: impl FnOnce(&mut Outbox) -> Result<(), BusError> + Send + 'static,
) -> (Inbox, Box<dyn Transport>, std::thread::JoinHandle<Result<(), BusError>>) {
    let sub_transport = sut.transport("sub");
    let mut inbox = Inbox::new(sub_transport.subscriber(topic).expect("subscriber"), topic.latest_only);
    let (s, t) = (sut.clone(), topic.clone());
    let handle = std::thread::spawn(move || {
        let transport = s.transport("pub");
        let mut out = Outbox::new(transport.publisher(&t)?, Trace::TYPE_NAME, required);
        bus::wait_for_subscribers(out.publisher(), 1, TIMEOUT, &never)?;
        let result = publish(&mut out);
        // keep the published frames alive until the subscriber has gone
        out.linger(TIMEOUT, &never);
        result
    });
    inbox.attach(TIMEOUT, &never).expect("attach");
    (inbox, sub_transport, handle)
}

fn next(inbox: &mut Inbox) -> Delivery {
    let start = Instant::now();
    loop {
        if let Some(d) = inbox.next_timeout(Duration::from_millis(50)).expect("receive") {
            return d;
        }
        assert!(start.elapsed() < TIMEOUT, "nothing arrived on {}", inbox.topic());
    }
}

fn lossless_in_order_under_backpressure<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/lossless").buffer(4);
    let (mut inbox, _t, h) = pair(&sut, &topic, 1, |out| {
        for i in 0..300 {
            out.send(&trace(i, 16))?;
        }
        out.end()
    });
    for i in 0..300u64 {
        if i < 20 {
            std::thread::sleep(Duration::from_millis(1)); // a slow consumer: the publisher waits
        }
        match next(&mut inbox) {
            Delivery::Data(f) => {
                assert_eq!(f.header.seq, i);
                let t: Trace<'_> = msg::decode(f.payload()).expect("decodes");
                assert_eq!(t, trace(i, 16));
            }
            other => panic!("expected data {i}, got {other:?}"),
        }
    }
    assert!(matches!(next(&mut inbox), Delivery::EndOfStream));
    assert_eq!(inbox.stats().dropped, 0);
    drop(inbox);
    h.join().expect("publisher thread").expect("publisher");
}

fn watermarks_and_end_of_stream_arrive_in_order<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/control");
    let (mut inbox, _t, h) = pair(&sut, &topic, 1, |out| {
        out.send(&trace(0, 4))?;
        out.advance_watermark(5_000)?;
        out.advance_watermark(4_000)?; // not an advance: nothing sent
        out.end()
    });
    assert!(matches!(next(&mut inbox), Delivery::Data(_)));
    assert!(matches!(next(&mut inbox), Delivery::Watermark(5_000)));
    assert!(matches!(next(&mut inbox), Delivery::EndOfStream));
    assert!(inbox.ended());
    drop(inbox);
    h.join().expect("thread").expect("publisher");
}

fn one_mebibyte_is_read_in_place<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/large").initial_payload_bytes(1 << 20);
    let n = (1 << 20) / 4;
    let (mut inbox, _t, h) = pair(&sut, &topic, 1, move |out| {
        out.send(&trace(7, n))?;
        out.end()
    });
    let Delivery::Data(f) = next(&mut inbox) else {
        panic!("expected data")
    };
    let t: Trace<'_> = msg::decode(f.payload()).expect("decodes");
    assert!(
        matches!(t.samples_f32, Cow::Borrowed(_)),
        "large arrays must be views into the frame"
    );
    assert_eq!(t.samples_f32.len(), n);
    assert_eq!(t.samples_f32[n - 1], (n as u64 - 1 + 7) as f32);
    drop(t);
    drop(f);
    assert!(matches!(next(&mut inbox), Delivery::EndOfStream));
    drop(inbox);
    h.join().expect("thread").expect("publisher");
}

fn latest_only_overwrites_and_counts_drops<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/latest").buffer(2).latest_only(true);
    let (done_tx, done_rx) = std::sync::mpsc::sync_channel(1);
    let (mut inbox, _t, h) = pair(&sut, &topic, 1, move |out| {
        for i in 0..100 {
            out.send(&trace(i, 4))?; // nobody reads yet: must not block
        }
        out.end()?;
        let _ = done_tx.send(());
        Ok(())
    });
    done_rx
        .recv_timeout(TIMEOUT)
        .expect("the publisher finished without a reader");
    sut.settle();
    let mut got = Vec::new();
    loop {
        match next(&mut inbox) {
            Delivery::Data(f) => got.push(f.header.seq),
            Delivery::EndOfStream => break,
            Delivery::Watermark(_) => {}
        }
    }
    assert!(got.len() <= 2, "kept {got:?}");
    assert_eq!(inbox.stats().dropped + got.len() as u64, 100);
    drop(inbox);
    h.join().expect("thread").expect("publisher never blocked");
}

fn a_gap_on_a_lossless_topic_is_an_error<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/gap");
    let sub_transport = sut.transport("sub");
    let mut inbox = Inbox::new(sub_transport.subscriber(&topic).expect("subscriber"), false);
    let t = topic.clone();
    let s = sut.clone();
    let h = std::thread::spawn(move || {
        let transport = s.transport("pub");
        let mut p = transport.publisher(&t).expect("publisher");
        bus::wait_for_subscribers(p.as_ref(), 1, TIMEOUT, &never).expect("handshake");
        for seq in [0u64, 1, 5] {
            p.send_with(FrameHeader::data(seq, 10), 0, &mut |out| out.finish())
                .expect("send");
        }
        let start = Instant::now();
        while p.subscriber_count() > 0 && start.elapsed() < TIMEOUT {
            std::thread::sleep(Duration::from_millis(2));
        }
    });
    inbox.attach(TIMEOUT, &never).expect("attach");
    assert!(matches!(next(&mut inbox), Delivery::Data(_)));
    assert!(matches!(next(&mut inbox), Delivery::Data(_)));
    let err = loop {
        match inbox.try_next() {
            Err(e) => break e,
            Ok(_) => std::thread::sleep(Duration::from_millis(5)),
        }
    };
    assert!(matches!(err, BusError::SeqGap { first: 2, last: 5, .. }), "{err}");
    drop(inbox);
    h.join().expect("thread");
}

fn a_vanished_subscriber_is_reported<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/lost");
    let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel(1);
    let (inbox, transport, h) = pair(&sut, &topic, 1, move |out| {
        let _ = ready_tx.send(());
        std::thread::sleep(Duration::from_millis(200)); // the subscriber leaves meanwhile
        let mut last = Ok(());
        for i in 0..50 {
            last = out.send(&trace(i, 4)).map(|_| ());
            if last.is_err() {
                break;
            }
        }
        last
    });
    ready_rx.recv_timeout(TIMEOUT).expect("publisher handshake");
    drop(inbox);
    drop(transport);
    let err = h.join().expect("thread").expect_err("sending to nobody must fail");
    assert!(
        matches!(
            err,
            BusError::SubscriberLost {
                reached: 0,
                expected: 1,
                ..
            }
        ),
        "{err}"
    );
}

fn stamps_going_backwards_are_refused<S: Sut>(sut: S) {
    let topic = TopicConfig::new("conf/backwards");
    let (mut inbox, _t, h) = pair(&sut, &topic, 1, |out| {
        out.send(&trace(10, 4))?;
        out.send(&trace(3, 4)).map(|_| ())
    });
    assert!(matches!(next(&mut inbox), Delivery::Data(_)));
    drop(inbox);
    let err = h.join().expect("thread").expect_err("must refuse");
    assert!(matches!(err, BusError::StampBackwards { seq: 1, .. }), "{err}");
}

macro_rules! conformance {
    ($module:ident, $make:expr) => {
        mod $module {
            use super::*;
            #[test]
            fn lossless_in_order_under_backpressure() {
                super::lossless_in_order_under_backpressure($make);
            }
            #[test]
            fn watermarks_and_end_of_stream_arrive_in_order() {
                super::watermarks_and_end_of_stream_arrive_in_order($make);
            }
            #[test]
            fn one_mebibyte_is_read_in_place() {
                super::one_mebibyte_is_read_in_place($make);
            }
            #[test]
            fn latest_only_overwrites_and_counts_drops() {
                super::latest_only_overwrites_and_counts_drops($make);
            }
            #[test]
            fn a_gap_on_a_lossless_topic_is_an_error() {
                super::a_gap_on_a_lossless_topic_is_an_error($make);
            }
            #[test]
            fn a_vanished_subscriber_is_reported() {
                super::a_vanished_subscriber_is_reported($make);
            }
            #[test]
            fn stamps_going_backwards_are_refused() {
                super::stamps_going_backwards_are_refused($make);
            }
        }
    };
}

fn unique_prefix() -> String {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    format!("gft{}x{}_", std::process::id(), N.fetch_add(1, Ordering::Relaxed))
}

conformance!(
    iceoryx2,
    Iox {
        prefix: unique_prefix(),
        stop: Arc::new(AtomicBool::new(false))
    }
);
conformance!(zenoh, Zenoh::new());
conformance!(in_process, InProc(InProcess::new(Arc::new(AtomicBool::new(false)))));
