//! End-to-end tests: real graphs launched as real processes over iceoryx2, recorded to MCAP,
//! replayed, killed mid-run, and read back by a peer MCAP reader.

// Tests spawn short-lived helper threads; names would add nothing.
#![allow(clippy::disallowed_methods)]

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
fn a_users_own_executable_speaks_the_same_bus() {
    let exec = Path::new(GPRFLOW).with_file_name("toy_gain_exec");
    assert!(exec.exists(), "build the toy stage's binary first: {}", exec.display());
    let dir = tempfile::tempdir().expect("tempdir");
    let builtin = dir.path().join("builtin.mcap");
    let user = dir.path().join("user.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/toy.yaml",
        "--set",
        "count=300",
        "--record",
        builtin.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
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
fn sigint_stops_every_stage_and_finalises_the_recording() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("interrupted.mcap");
    let run = LongRun::start(&rec);
    run.pid_of("gain");
    std::thread::sleep(Duration::from_millis(500));
    kill(run.child.id(), "-INT");
    let id = run.id.clone();
    let (code, err) = run.finish();
    assert_eq!(code, Some(130), "{err}");
    assert!(pids_with(&format!("gprflow-{id}/")).is_empty(), "orphans after SIGINT");
    assert!(gprflow::launch::leftover_resources(&format!("gf{id}_")).is_empty());
    let recorded = payloads(&rec);
    assert!(
        recorded.get("/gen/trace").is_some_and(|v| !v.is_empty()),
        "the recording is complete and holds data"
    );
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

/// A long toy run whose launcher's stderr is collected while it runs.
struct LongRun {
    child: std::process::Child,
    id: String,
    lines: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    reader: std::thread::JoinHandle<()>,
}

impl LongRun {
    fn start(record: &Path) -> Self {
        use std::io::BufRead;
        let mut child = Command::new(GPRFLOW)
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
        let lines = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let stderr = child.stderr.take().expect("stderr");
        let sink = lines.clone();
        let reader = std::thread::spawn(move || {
            for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
                sink.lock().expect("lines").push(line);
            }
        });
        let start = Instant::now();
        let id = loop {
            let found = lines
                .lock()
                .expect("lines")
                .iter()
                .find(|l| l.contains(" run "))
                .map(|l| run_id(l));
            if let Some(id) = found {
                break id;
            }
            assert!(
                start.elapsed() < Duration::from_secs(20),
                "the launcher never named its run"
            );
            std::thread::sleep(Duration::from_millis(10));
        };
        Self {
            child,
            id,
            lines,
            reader,
        }
    }

    /// Pid of this run's process for `node`, once it runs.
    fn pid_of(&self, node: &str) -> u32 {
        let needle = format!("gprflow-{}/{node}.json", self.id);
        let start = Instant::now();
        loop {
            if let Some(p) = pids_with(&needle).into_iter().find(|p| *p != self.child.id()) {
                return p;
            }
            assert!(start.elapsed() < Duration::from_secs(20), "{node} never started");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits for the launcher; returns its exit code and stderr.
    fn finish(self) -> (Option<i32>, String) {
        let status = self.child.wait_with_output().expect("launcher ends").status;
        self.reader.join().expect("stderr reader");
        let text = self.lines.lock().expect("lines").join("\n");
        (status.code(), text)
    }

    /// The run's processes still alive.
    fn survivors(&self) -> Vec<u32> {
        pids_with(&format!("gprflow-{}/", self.id))
    }
}

fn kill(pid: u32, signal: &str) {
    let _ = Command::new("kill").args([signal, &pid.to_string()]).status();
}

#[test]
fn killed_stage_stops_the_run_and_leaves_nothing_behind() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("killed.mcap");
    let run = LongRun::start(&rec);
    let gain = run.pid_of("gain");
    std::thread::sleep(Duration::from_millis(300));
    kill(gain, "-9");
    let id = run.id.clone();
    let start = Instant::now();
    let (code, err) = loop {
        // the launcher must end on its own, having stopped the others
        if run.survivors().is_empty() || start.elapsed() > Duration::from_secs(15) {
            break run.finish();
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("node `gain` failed (killed by signal 9)"), "{err}");
    assert!(
        pids_with(&format!("gprflow-{id}/")).is_empty(),
        "orphans: {:?}",
        pids_with(&format!("gprflow-{id}/"))
    );
    let left = gprflow::launch::leftover_resources(&format!("gf{id}_"));
    assert!(left.is_empty(), "stale resources: {left:?}");
    // the recorder was stopped cleanly: its file is complete and readable
    assert!(!payloads(&rec).is_empty());
}

#[test]
fn recording_cut_off_by_sigkill_gives_back_every_complete_chunk() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("cut.mcap");
    let run = LongRun::start(&rec);
    let recorder = run.pid_of("__record");
    // the recorder closes a chunk at least every second: 2.5 s guarantees complete chunks
    std::thread::sleep(Duration::from_millis(2500));
    kill(recorder, "-9");
    let (code, err) = run.finish();
    assert_eq!(code, Some(1), "{err}");
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
