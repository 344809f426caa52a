//! Ending a run early: SIGINT stops every stage and finalises the recording, a killed stage
//! stops the run and leaves no process or resource behind, a recording cut off by SIGKILL
//! gives back every complete chunk (`gprflow recover`).

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use crate::common::{GPRFLOW, gprflow, repo, stderr};
use crate::payloads;

fn run_id(stderr: &str) -> String {
    stderr
        .lines()
        .find_map(|l| l.split("run ").nth(1).and_then(|r| r.split_whitespace().next()))
        .expect("launcher names its run")
        .to_owned()
}

/// Waits until the recorder has its file open: signal a run only then (on a loaded machine
/// start-up can take longer than any fixed wait).
fn wait_for_recorder(rec: &Path) {
    let start = Instant::now();
    while !rec.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "the recorder never opened its file"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn sigint_stops_every_stage_and_finalises_the_recording() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("interrupted.mcap");
    let run = LongRun::start(&rec);
    run.pid_of("gain");
    wait_for_recorder(&rec);
    std::thread::sleep(Duration::from_millis(500));
    kill(run.child.id(), "-INT");
    let id = run.id.clone();
    let (code, err) = run.finish();
    assert_eq!(code, Some(130), "{err}");
    // a stage whose consumers went first is stopped, not failed
    assert!(!err.contains("error: node"), "{err}");
    assert!(pids_with(&format!("gprflow-{id}/")).is_empty(), "orphans after SIGINT");
    assert!(gprflow::launch::leftover_resources(&format!("gf{id}_")).is_empty());
    let recorded = payloads(&rec);
    assert!(
        recorded.get("/gen/trace").is_some_and(|v| !v.is_empty()),
        "the recording is complete and holds data"
    );
}

#[test]
fn sigint_stops_a_source_blocked_on_a_slow_consumer_without_an_error() {
    // the estimator is slower than ingest, so ingest waits in a send when the signal comes;
    // its consumer may be gone before the send returns
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("five-minutes.mcap");
    let sim = gprflow(&[
        "sim",
        "tools/sim/scenarios/basement.yaml",
        "--run",
        "long",
        "--duration",
        "300",
        "-o",
        rec.to_str().expect("utf8"),
    ]);
    assert!(sim.status.success(), "{}", stderr(&sim));
    let mut child = Command::new(GPRFLOW)
        .current_dir(repo())
        .args([
            "launch",
            "graphs/odometry.yaml",
            "--set",
            &format!("recording={}", rec.display()),
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("launch starts");
    std::thread::sleep(Duration::from_millis(1500));
    kill(child.id(), "-INT");
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().expect("stderr"), &mut err).expect("stderr reads");
    let code = child.wait().expect("launcher ends").code();
    assert_eq!(code, Some(130), "still running when interrupted: {err}");
    assert!(!err.contains("error: node"), "{err}");
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
    wait_for_recorder(&rec);
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
