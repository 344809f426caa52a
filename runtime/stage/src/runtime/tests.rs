//! The stamp-ordered merge, driven through the in-process transport by source threads
//! whose timing is jittered: the delivery order must not depend on it.

// Tests spawn short-lived helper threads; names would add nothing.
#![allow(clippy::disallowed_methods)]

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use super::*;
use crate::{InputPorts, PortSpec};
use gprflow_bus::inproc::InProcess;
use gprflow_msg::{Header, WheelOdometry};

thread_local! {
    static SEEN: RefCell<Vec<(String, i64)>> = const { RefCell::new(Vec::new()) };
}

#[derive(Debug)]
struct Collect;

impl Stage for Collect {
    type Params = serde_json::Value;
    const NAME: &'static str = "collect";
    const ABOUT: &'static str = "test sink";
    fn inputs() -> InputPorts {
        InputPorts::Any
    }
    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(Vec::new())
    }
    fn create(_: Self::Params, _: &Ports) -> Result<Self, StageError> {
        Ok(Self)
    }
    fn on_message(&mut self, input: Input<'_>, _: &mut Outputs) -> Result<(), StageError> {
        let odo: WheelOdometry = input.decode()?;
        assert_eq!(odo.header.stamp.to_ns(), input.stamp_ns());
        SEEN.with(|s| s.borrow_mut().push((input.name().to_owned(), input.stamp_ns())));
        Ok(())
    }
}

fn binding(name: &str, delay: Option<i64>) -> InputBinding {
    InputBinding {
        name: name.to_owned(),
        topic: format!("src/{name}"),
        msg_type: WheelOdometry::TYPE_NAME.to_owned(),
        feedback_delay_ns: delay,
        buffer: 4,
        latest_only: false,
    }
}

/// Publishes `stamps` on `src/NAME`, sleeping a jittered while between messages.
/// `required` is 0 for a feedback consumer, which may finish before the stream ends.
fn source(
    bus: InProcess,
    name: &'static str,
    stamps: Vec<i64>,
    jitter_seed: u64,
    required: usize,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let topic = binding(name, None).topic_config();
        let publisher = bus.publisher(&topic).expect("publisher");
        let mut out = Outbox::new(publisher, WheelOdometry::TYPE_NAME, required);
        let never = || false;
        bus::wait_for_subscribers(out.publisher(), 1, Duration::from_secs(5), &never).expect("handshake");
        let mut x = jitter_seed;
        for s in stamps {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            std::thread::sleep(Duration::from_micros((x >> 54) * 20));
            let msg = WheelOdometry {
                header: Header::new(s, "wheel"),
                distance_m: s as f64,
                ..WheelOdometry::default()
            };
            out.send(&msg).expect("send");
        }
        out.end().expect("end");
    })
}

/// The spec of the test sink reading `inputs`.
fn collect_spec(inputs: Vec<InputBinding>) -> NodeSpec {
    NodeSpec {
        run_id: "t".to_owned(),
        prefix: "t".to_owned(),
        node: "collect".to_owned(),
        stage: "collect".to_owned(),
        params: serde_json::Value::Null,
        inputs,
        outputs: Vec::new(),
        handshake_timeout_ms: 5000,
    }
}

fn run_merge(jitter: u64, delay_b: Option<i64>) -> Vec<(String, i64)> {
    let stop = Arc::new(AtomicBool::new(false));
    let bus = InProcess::new(stop.clone());
    let spec = collect_spec(vec![binding("a", None), binding("b", delay_b)]);
    // a: every 10 ns; b: every 15 ns, with shared stamps (ties) at multiples of 30
    let a = source(bus.clone(), "a", (0..40).map(|i| i * 10).collect(), jitter, 1);
    let b_required = usize::from(delay_b.is_none());
    let b = source(
        bus.clone(),
        "b",
        (0..30).map(|i| i * 15).collect(),
        jitter ^ 0xdead_beef,
        b_required,
    );
    SEEN.with(|s| s.borrow_mut().clear());
    let report = run_node::<Collect>(&spec, &bus, &stop).expect("runs");
    a.join().expect("a");
    b.join().expect("b");
    assert_eq!(report.received[0], ("src/a".to_owned(), 40));
    if delay_b.is_none() {
        assert_eq!(report.received[1], ("src/b".to_owned(), 30));
    }
    SEEN.with(|s| s.borrow().clone())
}

#[test]
fn inputs_are_delivered_in_stamp_order_whatever_the_timing() {
    let first = run_merge(1, None);
    assert_eq!(first.len(), 70);
    // sorted by stamp, ties broken by input declaration order (a before b)
    let mut sorted = first.clone();
    sorted.sort_by(|x, y| (x.1, &x.0).cmp(&(y.1, &y.0)));
    assert_eq!(first, sorted);
    for jitter in [2, 3, 4] {
        assert_eq!(
            run_merge(jitter, None),
            first,
            "order changed with timing (jitter {jitter})"
        );
    }
}

#[test]
fn feedback_input_is_seen_delayed_and_ties_go_to_feedback() {
    // b as feedback with delay 5: a message stamped s counts as s + 5
    let seen = run_merge(7, Some(5));
    let effective: Vec<(i64, u8)> = seen
        .iter()
        .map(|(name, s)| if name == "b" { (s + 5, 0) } else { (*s, 1) })
        .collect();
    let mut sorted = effective.clone();
    sorted.sort();
    assert_eq!(effective, sorted);
    // every feedback message stamped at or before the last primary stamp minus the delay
    // was seen before the stage finished
    let fed: Vec<i64> = seen.iter().filter(|(n, _)| n == "b").map(|(_, s)| *s).collect();
    // (a ends at 390: b up to 385, i.e. 375, counts; b at 390 counts as 395 and is not needed)
    assert_eq!(fed, (0..=25).map(|i| i * 15).collect::<Vec<i64>>());
    assert_eq!(run_merge(8, Some(5)), seen);
}

#[test]
fn a_payload_that_does_not_decode_is_counted_and_skipped() {
    let stop = Arc::new(AtomicBool::new(false));
    let bus = InProcess::new(stop.clone());
    let spec = collect_spec(vec![binding("a", None)]);
    let b = bus.clone();
    let source = std::thread::spawn(move || {
        let mut out = Outbox::new(
            b.publisher(&binding("a", None).topic_config()).expect("publisher"),
            WheelOdometry::TYPE_NAME,
            1,
        );
        let never = || false;
        bus::wait_for_subscribers(out.publisher(), 1, Duration::from_secs(5), &never).expect("handshake");
        let good = |s: i64| WheelOdometry {
            header: Header::new(s, "wheel"),
            ..WheelOdometry::default()
        };
        out.send(&good(1)).expect("send");
        out.send_bytes(2, &[0, 1, 0, 0, 0xff]).expect("send junk");
        out.send(&good(3)).expect("send");
        out.end().expect("end");
    });
    SEEN.with(|s| s.borrow_mut().clear());
    let report = run_node::<Collect>(&spec, &bus, &stop).expect("a bad payload does not stop the stage");
    source.join().expect("source");
    assert_eq!(report.decode_errors, 1);
    assert_eq!(
        SEEN.with(|s| s.borrow().iter().map(|(_, t)| *t).collect::<Vec<_>>()),
        vec![1, 3]
    );
}

/// Relays every input to `busy`, and every 20th to `rare` too, taking a while over each so
/// that its input never runs dry (it never waits, so never promises anything when idle).
#[derive(Debug)]
struct Relay {
    busy: Output<WheelOdometry>,
    rare: Output<WheelOdometry>,
    seen: u64,
}

impl Stage for Relay {
    type Params = serde_json::Value;
    const NAME: &'static str = "relay";
    const ABOUT: &'static str = "test relay";
    fn inputs() -> InputPorts {
        InputPorts::Any
    }
    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![
            PortSpec::new("busy", WheelOdometry::TYPE_NAME),
            PortSpec::new("rare", WheelOdometry::TYPE_NAME),
        ])
    }
    fn create(_: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        Ok(Self {
            busy: ports.output("busy")?,
            rare: ports.output("rare")?,
            seen: 0,
        })
    }
    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        std::thread::sleep(Duration::from_micros(200));
        let odo: WheelOdometry = input.decode()?;
        out.send(self.busy, &odo)?;
        self.seen += 1;
        if self.seen.is_multiple_of(20) {
            out.send(self.rare, &odo)?;
        }
        Ok(())
    }
}

#[test]
fn a_consumer_of_a_busy_and_a_rare_output_of_a_stage_that_never_waits_does_not_stall() {
    let stop = Arc::new(AtomicBool::new(false));
    let bus = InProcess::new(stop.clone());
    let output = |name: &str| OutputBinding {
        name: name.to_owned(),
        topic: format!("relay/{name}"),
        msg_type: WheelOdometry::TYPE_NAME.to_owned(),
        subscribers: 1,
        required_subscribers: 1,
        buffer: 4,
        latest_only: false,
    };
    let relay = NodeSpec {
        node: "relay".to_owned(),
        stage: "relay".to_owned(),
        outputs: vec![output("busy"), output("rare")],
        // a deep input queue, filled at once by the source: the relay never runs dry
        inputs: vec![InputBinding {
            buffer: 256,
            ..binding("in", None)
        }],
        ..collect_spec(Vec::new())
    };
    let sink = collect_spec(
        ["busy", "rare"]
            .iter()
            .map(|name| InputBinding {
                topic: format!("relay/{name}"),
                ..binding(name, None)
            })
            .collect(),
    );
    let source_bus = bus.clone();
    let source = std::thread::spawn(move || {
        let topic = InputBinding {
            buffer: 256,
            ..binding("in", None)
        }
        .topic_config();
        let mut out = Outbox::new(
            source_bus.publisher(&topic).expect("publisher"),
            WheelOdometry::TYPE_NAME,
            1,
        );
        let never = || false;
        bus::wait_for_subscribers(out.publisher(), 1, Duration::from_secs(5), &never).expect("handshake");
        for s in 0..200 {
            let msg = WheelOdometry {
                header: Header::new(s * 10, "wheel"),
                ..WheelOdometry::default()
            };
            out.send(&msg).expect("send");
        }
        out.end().expect("end");
    });
    let (relay_bus, relay_stop) = (bus.clone(), stop.clone());
    let relay = std::thread::spawn(move || run_node::<Relay>(&relay, &relay_bus, &relay_stop).map(|r| r.sent));
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    let (sink_bus, sink_stop) = (bus.clone(), stop.clone());
    let sink = std::thread::spawn(move || {
        SEEN.with(|s| s.borrow_mut().clear());
        let report = run_node::<Collect>(&sink, &sink_bus, &sink_stop);
        let _ = done_tx.send(());
        report.map(|r| (r.received, SEEN.with(|s| s.borrow().len())))
    });
    let finished = done_rx.recv_timeout(Duration::from_secs(20)).is_ok();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    source.join().expect("source");
    let _ = relay.join().expect("relay");
    let sunk = sink.join().expect("sink");
    assert!(finished, "the sink stalled waiting on the rare output");
    let (received, seen) = sunk.expect("sink runs");
    assert_eq!(
        received,
        vec![("relay/busy".to_owned(), 200), ("relay/rare".to_owned(), 10)]
    );
    assert_eq!(seen, 210);
}
