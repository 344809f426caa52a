//! Launching graphs: a run is deterministic and replays identically, a user's own
//! executable stands in for a built-in stage, graph files validate as declared, bad input
//! gets clear errors.

use std::path::Path;

use gprflow::record::Recording;

use crate::common::{GPRFLOW, gprflow, repo, stderr};
use crate::{payloads, record_toy};

#[test]
fn toy_graph_is_deterministic_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let a = dir.path().join("a.mcap");
    let b = dir.path().join("b.mcap");
    for f in [&a, &b] {
        record_toy(500, f);
    }
    let pa = payloads(&a);
    assert_eq!(pa.keys().collect::<Vec<_>>(), ["/gain/trace", "/gen/trace"]);
    assert_eq!(pa["/gen/trace"].len(), 500);
    assert_eq!(pa["/gain/trace"].len(), 500);
    assert_eq!(
        pa,
        payloads(&b),
        "two runs of one graph must record byte-identical payloads"
    );

    // replay A's source topic through the graph again: the gain output must be identical
    let c = dir.path().join("c.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/replay-toy.yaml",
        "--set",
        &format!("recording={}", a.display()),
        "--record",
        c.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "replay failed: {}", stderr(&o));
    let pc = payloads(&c);
    assert_eq!(pc["/replay/gen/trace"], pa["/gen/trace"]);
    assert_eq!(pc["/gain/trace"], pa["/gain/trace"]);
}

#[test]
fn a_replay_window_plays_exactly_its_span_and_every_process_reports_its_usage() {
    let dir = tempfile::tempdir().expect("tempdir");
    let source = dir.path().join("source.mcap");
    record_toy(500, &source);
    // what a window of 1.0 .. 2.5 s after the first message holds
    let rec = Recording::open(&source).expect("open");
    let mut stamps = Vec::new();
    let (_, stopped) = rec.scan(|m| {
        if m.topic == "/gen/trace" {
            stamps.push((m.log_time, m.data.to_vec()));
        }
    });
    assert_eq!(stopped, None);
    let first = stamps.iter().map(|s| s.0).min().expect("messages");
    let want: Vec<Vec<u8>> = stamps
        .iter()
        .filter(|(t, _)| *t >= first + 1_000_000_000 && *t < first + 2_500_000_000)
        .map(|(_, d)| d.clone())
        .collect();
    assert_eq!(want.len(), 150, "the toy source sends at 100 Hz");

    let graph = dir.path().join("window.yaml");
    std::fs::write(
        &graph,
        format!(
            "name: window\nnodes:\n  replay: {{ stage: replay, params: {{ path: {:?}, topics: [\"gen/*\"], start_s: 1.0, end_s: 2.5 }} }}\n  gain: {{ stage: toy_gain, inputs: {{ trace: replay/gen/trace }}, params: {{ gain: 0.5 }} }}\nrecord: {{ topics: [\"*\"] }}\n",
            source.display().to_string()
        ),
    )
    .expect("write graph");
    let out = dir.path().join("out.mcap");
    let report = dir.path().join("report.json");
    let o = gprflow(&[
        "launch",
        graph.to_str().expect("utf8"),
        "--record",
        out.to_str().expect("utf8"),
        "--report",
        report.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(payloads(&out)["/replay/gen/trace"], want);

    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).expect("report written")).expect("json");
    assert_eq!(report["succeeded"], true);
    assert!(report["wall_s"].as_f64().is_some_and(|w| w > 0.0));
    let nodes = report["nodes"].as_array().expect("nodes");
    assert_eq!(nodes.len(), 3, "replay, gain and the recorder: {report}");
    for n in nodes {
        let r = &n["report"];
        assert!(r["cpu_s"].as_f64().is_some_and(|c| c > 0.0), "{n}");
        assert!(r["peak_rss_bytes"].as_u64().is_some_and(|b| b > 1 << 20), "{n}");
    }
    let replay = nodes.iter().find(|n| n["node"] == "replay").expect("replay node");
    assert_eq!(replay["report"]["sent"][0][1], 150, "{replay}");
}

#[test]
fn a_users_own_executable_speaks_the_same_bus() {
    let exec = Path::new(GPRFLOW).with_file_name("toy_gain_exec");
    assert!(exec.exists(), "build the toy stage's binary first: {}", exec.display());
    let dir = tempfile::tempdir().expect("tempdir");
    let builtin = dir.path().join("builtin.mcap");
    let user = dir.path().join("user.mcap");
    record_toy(300, &builtin);
    let o = gprflow(&[
        "launch",
        "graphs/toy-exec.yaml",
        "--set",
        "count=300",
        "--set",
        &format!("exec={}", exec.display()),
        "--record",
        user.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        payloads(&user),
        payloads(&builtin),
        "the exec stage must behave as the built-in one"
    );
}

#[test]
fn graph_fixtures_validate_as_declared() {
    let catalog = gprflow_cli::catalog();
    let mut seen = 0;
    for e in std::fs::read_dir(repo().join("tests/graphs"))
        .expect("fixtures")
        .flatten()
    {
        let path = e.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
        let text = std::fs::read_to_string(&path).expect("readable");
        let result = gprflow::graph::load(&path, &[], &catalog);
        if name.starts_with("valid-") {
            assert!(
                result.is_ok(),
                "{name}: {}",
                result.err().map(|e| e.to_string()).unwrap_or_default()
            );
        } else if name.starts_with("invalid-") {
            let expected = text
                .lines()
                .next()
                .and_then(|l| l.strip_prefix("# expect: "))
                .unwrap_or_else(|| panic!("{name}: first line must be `# expect: Kind`"))
                .trim();
            let err = result
                .err()
                .unwrap_or_else(|| panic!("{name}: expected {expected}, got a valid graph"));
            assert_eq!(format!("{:?}", err.kind()), expected, "{name}: {err}");
            assert!(
                err.to_string().contains(&name),
                "{name}: error must name the file: {err}"
            );
        }
        seen += 1;
    }
    assert!(seen >= 10, "fixtures found: {seen}");
}

#[test]
fn bad_input_gets_clear_errors() {
    let o = gprflow(&["launch", "tests/graphs/invalid-unknown-stage.yaml"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("invalid-unknown-stage.yaml:"), "{}", stderr(&o));
    let o = gprflow(&["inspect", "does-not-exist.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("does-not-exist.mcap"), "{}", stderr(&o));
    // the OS's reason once, not again as the error's source
    assert_eq!(stderr(&o).matches("os error 2").count(), 1, "{}", stderr(&o));
    let dir = tempfile::tempdir().expect("tempdir");
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not an mcap file at all").expect("write");
    let o = gprflow(&["inspect", junk.to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("not a readable MCAP file"), "{}", stderr(&o));
}
