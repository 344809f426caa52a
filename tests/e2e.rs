//! End-to-end tests: real graphs launched as real processes over iceoryx2, recorded to MCAP,
//! replayed, killed mid-run, and read back by a peer MCAP reader.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use gprflow::record::Recording;

const GPRFLOW: &str = env!("CARGO_BIN_EXE_gprflow");

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn gprflow(args: &[&str]) -> Output {
    Command::new(GPRFLOW)
        .current_dir(repo())
        .args(args)
        .output()
        .expect("gprflow runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Payloads per topic, in file order.
fn payloads(path: &Path) -> BTreeMap<String, Vec<Vec<u8>>> {
    let rec = Recording::open(path).expect("recording opens");
    let mut out: BTreeMap<String, Vec<Vec<u8>>> = BTreeMap::new();
    let (_, stopped) = rec.scan(|m| out.entry(m.topic.to_owned()).or_default().push(m.data.to_vec()));
    assert_eq!(stopped, None, "{} is complete", path.display());
    out
}

fn run_id(stderr: &str) -> String {
    stderr
        .lines()
        .find_map(|l| l.split("run ").nth(1).and_then(|r| r.split_whitespace().next()))
        .expect("launcher names its run")
        .to_owned()
}

#[test]
fn toy_graph_is_deterministic_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let a = dir.path().join("a.mcap");
    let b = dir.path().join("b.mcap");
    for f in [&a, &b] {
        let o = gprflow(&[
            "launch",
            "graphs/toy.yaml",
            "--set",
            "count=500",
            "--record",
            f.to_str().expect("utf8"),
        ]);
        assert!(o.status.success(), "launch failed: {}", stderr(&o));
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
fn python_mcap_reader_decodes_every_field_alike() {
    let python = repo().join(".venv-peers/bin/python");
    assert!(
        python.exists(),
        "the peer venv is missing: run tools/peer/setup-venv.sh (the README's test command does)"
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("peer.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/toy.yaml",
        "--set",
        "count=300",
        "--record",
        rec.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let dump = gprflow(&["inspect", rec.to_str().expect("utf8"), "--dump-json"]);
    assert!(dump.status.success(), "{}", stderr(&dump));
    let dump_file = dir.path().join("peer.jsonl");
    std::fs::write(&dump_file, &dump.stdout).expect("write dump");
    let check = Command::new(&python)
        .arg(repo().join("tools/peer/check_mcap.py"))
        .arg(&rec)
        .arg(&dump_file)
        .output()
        .expect("python runs");
    assert!(
        check.status.success(),
        "peer disagrees:\n{}{}",
        String::from_utf8_lossy(&check.stdout),
        stderr(&check)
    );
    assert!(String::from_utf8_lossy(&check.stdout).contains("600 messages on 2 topics"));
}

/// Pids of processes whose command line mentions `needle`.
fn pids_with(needle: &str) -> Vec<u32> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        if let Ok(cmd) = std::fs::read(e.path().join("cmdline"))
            && String::from_utf8_lossy(&cmd).contains(needle)
        {
            out.push(pid);
        }
    }
    out
}

/// Starts a long toy run, SIGKILLs `victim` once it runs, and returns the launcher's output.
fn kill_mid_run(victim: &str, record: &Path, after: Duration) -> (Output, String) {
    let child = Command::new(GPRFLOW)
        .current_dir(repo())
        .args([
            "launch",
            "graphs/toy.yaml",
            "--set",
            "count=100000000",
            "--record",
            record.to_str().expect("utf8"),
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("launch starts");
    let needle = format!("{victim}.json");
    let start = Instant::now();
    let victim_pid = loop {
        let found: Vec<u32> = pids_with(&needle).into_iter().filter(|p| *p != child.id()).collect();
        if let Some(p) = found.first() {
            break *p;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "{victim} never started");
        std::thread::sleep(Duration::from_millis(20));
    };
    std::thread::sleep(after);
    let spec_dir = pids_with(&needle)
        .first()
        .and_then(|p| std::fs::read(format!("/proc/{p}/cmdline")).ok())
        .map(|c| String::from_utf8_lossy(&c).into_owned())
        .and_then(|c| {
            c.split('\0')
                .find(|a| a.ends_with(&needle))
                .map(|a| a.trim_end_matches(&needle).to_owned())
        })
        .expect("spec dir");
    let _ = Command::new("kill").args(["-9", &victim_pid.to_string()]).status();
    let out = child.wait_with_output().expect("launcher ends");
    (out, spec_dir)
}

#[test]
fn killed_stage_stops_the_run_and_leaves_nothing_behind() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("killed.mcap");
    let (out, spec_dir) = kill_mid_run("gain", &rec, Duration::from_millis(300));
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("node `gain` failed (killed by signal 9)"), "{err}");
    // no orphan processes of the run
    let start = Instant::now();
    while !pids_with(&spec_dir).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(5),
            "orphans: {:?}",
            pids_with(&spec_dir)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // no stale shared memory or iceoryx2 files of the run
    let id = run_id(&err);
    let left = gprflow::launch::leftover_resources(&format!("gf{id}_"));
    assert!(left.is_empty(), "stale resources: {left:?}");
    // the recorder was stopped cleanly: its file is complete and readable
    assert!(!payloads(&rec).is_empty());
}

#[test]
fn recording_cut_off_by_sigkill_gives_back_every_complete_chunk() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("cut.mcap");
    // the recorder closes a chunk at least every second: 2.5 s guarantees complete chunks
    let (out, _) = kill_mid_run("__record", &rec, Duration::from_millis(2500));
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    let inspect = gprflow(&["inspect", rec.to_str().expect("utf8"), "--json"]);
    assert_eq!(inspect.status.code(), Some(1), "a cut-off file is reported");
    let summary: serde_json::Value = serde_json::from_slice(&inspect.stdout).expect("json");
    assert!(summary["truncated"].is_string(), "{summary}");
    let read = summary["messages"].as_u64().expect("count");
    assert!(read > 0, "complete chunks must be readable: {summary}");

    let fixed = dir.path().join("fixed.mcap");
    let o = gprflow(&[
        "recover",
        rec.to_str().expect("utf8"),
        "-o",
        fixed.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let recovered: usize = payloads(&fixed).values().map(Vec::len).sum();
    assert_eq!(recovered as u64, read);
    let again = gprflow(&["inspect", fixed.to_str().expect("utf8")]);
    assert!(again.status.success(), "{}", stderr(&again));
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
    let dir = tempfile::tempdir().expect("tempdir");
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not an mcap file at all").expect("write");
    let o = gprflow(&["inspect", junk.to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("not a readable MCAP file"), "{}", stderr(&o));
}
