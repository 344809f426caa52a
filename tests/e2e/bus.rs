//! `gprflow replay`, `gprflow record` and `launch --bus --external`: a recording fed into a
//! separately launched graph, and a bus recorded by a process of its own.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::{gprflow, payloads, repo, stderr};
use crate::common::GPRFLOW;

/// A `gprflow` process whose stderr lines are collected while it runs.
struct Running {
    child: Child,
    lines: Arc<Mutex<Vec<String>>>,
    reader: std::thread::JoinHandle<()>,
}

impl Running {
    fn start(args: &[&str]) -> Self {
        let mut child = Command::new(GPRFLOW)
            .current_dir(repo())
            .args(args)
            .stderr(Stdio::piped())
            .spawn()
            .expect("gprflow starts");
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = lines.clone();
        let stderr = child.stderr.take().expect("stderr");
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                sink.lock().expect("lines").push(line);
            }
        });
        Self { child, lines, reader }
    }

    /// Waits until a stderr line contains `needle`.
    fn wait_for_line(&self, needle: &str) {
        let start = Instant::now();
        while !self.lines.lock().expect("lines").iter().any(|l| l.contains(needle)) {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "no line with `{needle}`; so far:\n{}",
                self.lines.lock().expect("lines").join("\n")
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn interrupt(&self) {
        let _ = Command::new("kill")
            .args(["-INT", &self.child.id().to_string()])
            .status();
    }

    /// Waits for the end; exit code and stderr.
    fn finish(mut self) -> (Option<i32>, String) {
        let start = Instant::now();
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                break status;
            }
            if start.elapsed() > Duration::from_secs(120) {
                let _ = self.child.kill();
                panic!(
                    "still running after 120 s:\n{}",
                    self.lines.lock().expect("lines").join("\n")
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        self.reader.join().expect("stderr reader");
        let text = self.lines.lock().expect("lines").join("\n");
        (status.code(), text)
    }
}

fn path(p: &Path) -> &str {
    p.to_str().expect("utf8")
}

/// A bus name of this test process's own, so that concurrent tests never share one.
fn bus_name(what: &str) -> String {
    format!("t{}{what}", std::process::id())
}

#[test]
fn a_replayed_ingest_feeds_an_external_node_to_the_same_estimate_and_record_joins_the_bus() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (a, b, c) = (
        dir.path().join("a.mcap"),
        dir.path().join("b.mcap"),
        dir.path().join("c.mcap"),
    );
    // run A: the whole graph, its ingest topics recorded too
    let o = gprflow(&[
        "launch",
        "graphs/odometry.yaml",
        "-o",
        path(&a),
        "--record-topics",
        "ingest/*",
        "estimate/*",
    ]);
    assert!(o.status.success(), "run A: {}", stderr(&o));

    // run B: the same graph without its ingest node, fed by replaying A's ingest topics
    let bus = bus_name("od");
    let graph = Running::start(&[
        "launch",
        "graphs/odometry.yaml",
        "--bus",
        &bus,
        "--external",
        "ingest",
        "-o",
        path(&b),
    ]);
    graph.wait_for_line("waiting up to");
    let recorder = Running::start(&["record", "estimate/*", "--bus", &bus, "-o", path(&c)]);
    recorder.wait_for_line("joined `estimate/trajectory`");
    // all of A's topics: those no reader on the bus declared (estimate/*) are left out
    let o = gprflow(&["replay", path(&a), "--bus", &bus, "--rate", "max"]);
    assert!(o.status.success(), "replay: {}", stderr(&o));
    assert!(
        stderr(&o).contains("not replayed (no reader on bus `") && stderr(&o).contains("estimate/state"),
        "{}",
        stderr(&o)
    );
    let (code, log) = graph.finish();
    assert_eq!(code, Some(0), "run B: {log}");
    let (code, log) = recorder.finish();
    assert_eq!(code, Some(0), "record: {log}");

    let (pa, pb, pc) = (payloads(&a), payloads(&b), payloads(&c));
    for topic in ["/estimate/state", "/estimate/trajectory", "/estimate/line_map"] {
        let from_a = pa.get(topic).unwrap_or_else(|| panic!("A has {topic}"));
        assert!(!from_a.is_empty(), "A has {topic} messages");
        assert!(pb.get(topic) == Some(from_a), "B's {topic} is A's, message for message");
        assert!(
            pc.get(topic) == Some(from_a),
            "record's {topic} is A's, message for message"
        );
    }
    assert!(
        pb.keys().all(|t| !t.starts_with("/ingest")),
        "B records what its graph's `record:` names: {:?}",
        pb.keys()
    );
}

#[test]
fn a_looped_replay_keeps_time_moving_and_ctrl_c_ends_it_cleanly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("looped.mcap");
    let bus = bus_name("loop");
    let recorder = Running::start(&["record", "--bus", &bus, "-o", path(&out)]);
    // one reader: the recorder, which joins as soon as the topic is there
    let replay = Running::start(&[
        "replay",
        "recordings/toy.mcap",
        "--bus",
        &bus,
        "--loop",
        "--readers",
        "0",
        "--rate",
        "20",
    ]);
    recorder.wait_for_line("joined `gen/trace`");
    // the toy recording spans 2 s: at 20x a pass takes 0.1 s
    std::thread::sleep(Duration::from_millis(1500));
    replay.interrupt();
    let (code, log) = replay.finish();
    assert_eq!(code, Some(130), "replay stopped by Ctrl-C: {log}");
    assert!(log.contains("stopped after"), "{log}");
    // the replay ended its topics, so the recorder ends by itself
    let (code, log) = recorder.finish();
    assert_eq!(code, Some(0), "record: {log}");

    let rec = gprflow::record::Recording::open(&out).expect("opens");
    let mut stamps = Vec::new();
    let (_, stopped) = rec.scan(|m| {
        if m.topic == "/gen/trace" {
            stamps.push(m.log_time);
        }
    });
    assert_eq!(stopped, None, "the recording is complete");
    let passes = stamps.len() as f64 / 200.0;
    assert!(passes > 2.0, "more than two passes recorded, {} messages", stamps.len());
    assert!(
        stamps.windows(2).all(|w| w[1] > w[0]),
        "stamps always move forward across passes"
    );
}

#[test]
fn bus_mistakes_are_named() {
    let cases: [(&[&str], &str); 5] = [
        (
            &[
                "launch",
                "graphs/toy.yaml",
                "--bus",
                "b",
                "--external",
                "nosuch",
                "--dry-run",
            ],
            "--external `nosuch`: no such node (nodes: gen, gain)",
        ),
        (
            &[
                "launch",
                "graphs/toy.yaml",
                "--bus",
                "b",
                "--external",
                "gain",
                "--dry-run",
            ],
            "only source nodes (no inputs) can come from outside the run; `gain` reads gen/trace",
        ),
        (
            &["launch", "graphs/toy.yaml", "--bus", "no spaces", "--dry-run"],
            "bus name `no spaces`: use 1 to 32 ASCII letters, digits, `-` or `_`",
        ),
        (
            &["replay", "recordings/toy.mcap", "--bus", "b", "--topics", "nosuch/*"],
            "recordings/toy.mcap: no topic matches --topics nosuch/* (its topics: gen/trace, gain/trace)",
        ),
        (
            &[
                "replay",
                "recordings/toy.mcap",
                "--bus",
                &bus_name("none"),
                "--topics",
                "gen/*",
                "--wait-s",
                "0.2",
            ],
            "reads `gen/trace` (waited 0 s): launch the graph with `--bus NAME --external NODE`",
        ),
    ];
    for (args, expected) in cases {
        let o = gprflow(args);
        assert!(!o.status.success(), "{args:?} fails");
        assert!(stderr(&o).contains(expected), "{args:?}: {}", stderr(&o));
    }
}
