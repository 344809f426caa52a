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

/// The pipe-field sample that `graphs/slam.yaml` reads (`recording`), made on demand as
/// `tools/sim/make-samples.sh` makes it (the simulator is deterministic; too big to commit).
fn pipe_sample() -> PathBuf {
    simulated(
        "pipes-lawnmower-150s.mcap",
        &[
            "tools/sim/scenarios/pipes_one_line.yaml",
            "--run",
            "lawnmower",
            "--duration",
            "150",
        ],
    )
}

/// `gprflow sim ARGS` into target/tmp/samples/NAME, once: tests running at once each write
/// their own copy and move it into place.
fn simulated(name: &str, args: &[&str]) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("samples");
    let path = dir.join(name);
    if !path.exists() {
        std::fs::create_dir_all(&dir).expect("samples dir");
        let partial = dir.join(format!("{name}.{}", std::process::id()));
        let mut all = vec!["sim"];
        all.extend(args);
        all.extend(["-o", partial.to_str().expect("utf8")]);
        let o = gprflow(&all);
        assert!(o.status.success(), "{}", stderr(&o));
        std::fs::rename(&partial, &path).expect("sample in place");
    }
    path
}

/// Payloads per topic, in file order.
fn payloads(path: &Path) -> BTreeMap<String, Vec<Vec<u8>>> {
    let rec = Recording::open(path).expect("recording opens");
    let mut out: BTreeMap<String, Vec<Vec<u8>>> = BTreeMap::new();
    let (_, stopped) = rec.scan(|m| out.entry(m.topic.to_owned()).or_default().push(m.data.to_vec()));
    assert_eq!(stopped, None, "{} is complete", path.display());
    out
}

/// Runs graphs/toy.yaml with `count` traces, recorded to `record`, and checks it succeeded.
fn record_toy(count: u32, record: &Path) {
    let o = gprflow(&[
        "launch",
        "graphs/toy.yaml",
        "--set",
        &format!("count={count}"),
        "--record",
        record.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "launch failed: {}", stderr(&o));
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
    assert!(pids_with(&format!("gprflow-{id}/")).is_empty(), "orphans after SIGINT");
    assert!(gprflow::launch::leftover_resources(&format!("gf{id}_")).is_empty());
    let recorded = payloads(&rec);
    assert!(
        recorded.get("/gen/trace").is_some_and(|v| !v.is_empty()),
        "the recording is complete and holds data"
    );
}

/// Runs the Python peer check on `rec`, asserting it decodes `expected` messages alike.
fn peer_check(rec: &Path, expected: &str) {
    let python = repo().join(".venv-peers/bin/python");
    assert!(
        python.exists(),
        "the peer venv is missing: run tools/peer/setup-venv.sh (the README's test command does)"
    );
    let dump = gprflow(&["inspect", rec.to_str().expect("utf8"), "--dump-json"]);
    assert!(dump.status.success(), "{}", stderr(&dump));
    let dump_file = rec.with_extension("jsonl");
    std::fs::write(&dump_file, &dump.stdout).expect("write dump");
    let check = Command::new(&python)
        .arg(repo().join("tools/peer/check_mcap.py"))
        .arg(rec)
        .arg(&dump_file)
        .output()
        .expect("python runs");
    let out = String::from_utf8_lossy(&check.stdout);
    assert!(check.status.success(), "peer disagrees:\n{out}{}", stderr(&check));
    assert!(out.contains(expected), "{out}");
}

#[test]
fn python_mcap_reader_decodes_every_message_type() {
    use gprflow::msg::*;
    use std::borrow::Cow;
    let h = |ns: i64| Header::new(ns, "base_link");
    let pose = Pose {
        position: Point {
            x: 1.5,
            y: -2.25,
            z: 0.125,
        },
        orientation: Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.38268343236,
            w: 0.92387953251,
        },
    };
    let mut cov = Covariance6::default();
    for (i, c) in cov.0.iter_mut().enumerate() {
        *c = i as f64 * 0.01;
    }
    let mut msgs: Vec<(&str, &str, Vec<u8>)> = vec![
        (
            "/t/trace",
            Trace::TYPE_NAME,
            encode(&Trace {
                header: h(1),
                samples_i16: Cow::Owned(vec![-3, 7, i16::MIN]),
                sample_interval_ns: 0.2,
                ..Trace::default()
            }),
        ),
        (
            "/t/trace32",
            Trace::TYPE_NAME,
            encode(&Trace {
                header: h(2),
                samples_i32: Cow::Owned(vec![i32::MAX, -1]),
                ..Trace::default()
            }),
        ),
        (
            "/t/sweep",
            Sweep::TYPE_NAME,
            encode(&Sweep {
                header: h(3),
                channel_count: 1,
                bin_count: 2,
                values: Cow::Owned(vec![0.5, -0.5, 1.0, 2.0]),
                calibration: Cow::Owned(vec![1.0, 0.0, 1.0, 0.0]),
                start_frequency_hz: 1e8,
                frequency_step_hz: 6e6,
                ..Sweep::default()
            }),
        ),
        (
            "/t/wheel",
            WheelOdometry::TYPE_NAME,
            encode(&WheelOdometry {
                header: h(4),
                distance_m: 12.5,
                ticks: -4096,
                speed_mps: 0.75,
            }),
        ),
        (
            "/t/submap",
            Submap::TYPE_NAME,
            encode(&Submap {
                header: h(5),
                id: 9,
                rows: 2,
                cols: 3,
                pixels: Cow::Owned(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]),
                start_pose: pose,
                end_pose: pose,
                saliency: 0.25,
                valid: true,
                start_stamp: Time::from_ns(-1_500_000_000),
                ..Submap::default()
            }),
        ),
        (
            "/t/registration",
            Registration::TYPE_NAME,
            encode(&Registration {
                header: h(6),
                reference_submap: 1,
                query_submap: 2,
                reference_from_query: pose,
                covariance: cov,
                along_track_m: 0.4,
                along_track_variance_m2: 0.01,
                score: 0.9,
                method: "learned".to_owned(),
                ..Registration::default()
            }),
        ),
        (
            "/t/line",
            LineObservation::TYPE_NAME,
            encode(&LineObservation {
                header: h(7),
                line_id: u32::MAX,
                forward_distance_m: 0.3,
                sigma_m: 0.05,
                apex_time_ns: 12.0,
                depth_m: 0.6,
                score: 0.5,
                submap_id: 4,
                along_distance_m: 12.5,
                apex_stamp: Time::from_ns(6),
                velocity_m_per_ns: 0.12,
            }),
        ),
        (
            "/t/linemap",
            LineMap::TYPE_NAME,
            encode(&LineMap {
                header: h(8),
                lines: vec![
                    HoughLine {
                        id: 1,
                        rho_m: 2.0,
                        theta_rad: 0.5,
                        covariance: [1.0, 0.1, 0.1, 2.0],
                    },
                    HoughLine::default(),
                ],
            }),
        ),
        (
            "/t/state",
            StateEstimate::TYPE_NAME,
            encode(&StateEstimate {
                header: h(9),
                state_index: u64::MAX,
                world_from_body: PoseWithCovariance { pose, covariance: cov },
                velocity_in_world_mps: Vector3 { x: 1.0, y: 2.0, z: 3.0 },
                ..StateEstimate::default()
            }),
        ),
        (
            "/t/trajectory",
            Trajectory::TYPE_NAME,
            encode(&Trajectory {
                header: h(10),
                state_indices: vec![0, 1],
                poses: vec![PoseStamped { header: h(1), pose }, PoseStamped { header: h(2), pose }],
            }),
        ),
        (
            "/t/mapfix",
            MapFix::TYPE_NAME,
            encode(&MapFix {
                header: h(11),
                world_from_body: pose,
                covariance: cov,
                correlation: 0.93,
                overlapping_channels: 5,
                locked: true,
            }),
        ),
        (
            "/t/imu",
            Imu::TYPE_NAME,
            encode(&Imu {
                header: h(12),
                orientation: pose.orientation,
                orientation_covariance: [0.5; 9],
                angular_velocity: Vector3 {
                    x: 0.1,
                    y: -0.2,
                    z: 0.3,
                },
                linear_acceleration: Vector3 {
                    x: 0.0,
                    y: 0.0,
                    z: 9.81,
                },
                ..Imu::default()
            }),
        ),
        (
            "/t/pose",
            PoseStamped::TYPE_NAME,
            encode(&PoseStamped { header: h(13), pose }),
        ),
        (
            "/t/odom",
            Odometry::TYPE_NAME,
            encode(&Odometry {
                header: h(14),
                child_frame_id: "gpr".to_owned(),
                pose: PoseWithCovariance { pose, covariance: cov },
                ..Odometry::default()
            }),
        ),
        (
            "/t/image",
            Image::TYPE_NAME,
            encode(&Image {
                header: h(15),
                height: 2,
                width: 2,
                encoding: "mono8".to_owned(),
                step: 2,
                data: Cow::Owned(vec![0, 127, 128, 255]),
                ..Image::default()
            }),
        ),
    ];
    assert_eq!(
        msgs.len(),
        gprflow::msg::message_types().len() + 1,
        "one message of every type (Trace twice)"
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("all-types.mcap");
    {
        let mut w =
            gprflow::record::Recorder::create(&rec, &gprflow::record::RunMetadata::this_build()).expect("create");
        for (i, (topic, ty, bytes)) in msgs.drain(..).enumerate() {
            let ch = w.add_topic(topic, ty).expect("topic");
            w.write(ch, 0, i as i64 + 1, &bytes).expect("write");
        }
        w.finish().expect("finish");
    }
    peer_check(&rec, "15 messages on 15 topics");
}

#[test]
fn python_mcap_reader_decodes_every_field_alike() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("peer.mcap");
    record_toy(300, &rec);
    peer_check(&rec, "600 messages on 2 topics");
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

#[test]
fn sim_writes_recordings_that_inspect_and_the_python_reader_agree_on() {
    let dir = tempfile::tempdir().expect("tempdir");
    for (scenario, run, topics) in [
        ("tools/sim/scenarios/pipes_one_line.yaml", "lawnmower", 5),
        ("tools/sim/scenarios/highway.yaml", "track_97_offset", 7),
    ] {
        let rec = dir.path().join(format!("{run}.mcap"));
        let o = gprflow(&[
            "sim",
            scenario,
            "-o",
            rec.to_str().expect("utf8"),
            "--run",
            run,
            "--duration",
            "3",
            "--format",
            "cmu-gpr",
            "--json",
        ]);
        assert!(o.status.success(), "sim failed: {}", stderr(&o));
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).expect("summary json");
        let inspect = gprflow(&["inspect", rec.to_str().expect("utf8"), "--json"]);
        assert!(inspect.status.success(), "{}", stderr(&inspect));
        let report: serde_json::Value = serde_json::from_slice(&inspect.stdout).expect("inspect json");
        let text = report.to_string();
        for (topic, n) in summary["messages"].as_object().expect("counts") {
            assert!(text.contains(&format!("/{topic}")), "inspect lacks /{topic}: {text}");
            assert!(n.as_u64().expect("count") > 0);
        }
        assert!(text.contains("world.json") && text.contains("scenario.yaml"), "{text}");
        peer_check(&rec, &format!("on {topics} topics decoded identically"));
        // the impulse run also wrote the CMU-GPR folder beside the recording
        let folder = rec.with_extension("");
        assert_eq!(
            folder.join("gpr_meas.csv").exists(),
            run == "lawnmower",
            "{}",
            folder.display()
        );
    }
    // a broken scenario: exit 2, the file and line named
    let bad = dir.path().join("bad.yaml");
    std::fs::write(&bad, "name: x\nseed: 1\nwrold: {}\n").expect("write");
    let o = gprflow(&["sim", bad.to_str().expect("utf8"), "-o", "/dev/null"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("bad.yaml:3:"), "{}", stderr(&o));
}

/// Largest difference accepted between our statistics and evo's on the same TUM files.
const EVO_TOLERANCE_M: f64 = 1e-6;

fn evo_stats(tool: &str, args: &[&str], dir: &Path) -> serde_json::Value {
    let zip = dir.join(format!("{tool}-{}.zip", args.len()));
    let _ = std::fs::remove_file(&zip);
    let o = Command::new(repo().join(format!(".venv-peers/bin/{tool}")))
        .current_dir(dir)
        .args(args)
        .arg("--save_results")
        .arg(&zip)
        .env("MPLBACKEND", "Agg")
        .output()
        .expect("evo runs (tools/peer/setup-venv.sh installs it)");
    assert!(o.status.success(), "{tool} failed: {}", stderr(&o));
    let unzip = Command::new(repo().join(".venv-peers/bin/python"))
        .args([
            "-c",
            "import sys, zipfile; sys.stdout.write(zipfile.ZipFile(sys.argv[1]).read('stats.json').decode())",
        ])
        .arg(&zip)
        .output()
        .expect("python runs");
    serde_json::from_slice(&unzip.stdout).expect("evo stats.json")
}

#[test]
fn eval_agrees_with_evo_on_ate_and_rpe() {
    let dir = tempfile::tempdir().expect("tempdir");
    // a lawnmower with GPS: turns make the SE(3) alignment well posed
    let scenario = dir.path().join("gps.yaml");
    let text = std::fs::read_to_string(repo().join("tools/sim/scenarios/pipes_one_line.yaml")).expect("scenario");
    std::fs::write(&scenario, format!("{text}\ngps: {{ rate_hz: 10 }}\n")).expect("write");
    let rec = dir.path().join("gps.mcap");
    let o = gprflow(&[
        "sim",
        scenario.to_str().expect("utf8"),
        "-o",
        rec.to_str().expect("utf8"),
        "--duration",
        "45",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let prefix = dir.path().join("pair");
    let o = gprflow(&[
        "eval",
        rec.to_str().expect("utf8"),
        "--format",
        "json",
        "--delta",
        "2",
        "--write-tum",
        prefix.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let ours: serde_json::Value = serde_json::from_slice(&o.stdout).expect("eval json");
    assert!(
        ours["estimate"].as_str().expect("estimate").ends_with("/gps/odometry"),
        "{ours}"
    );
    let (gt, est) = ("pair_gt.txt", "pair_est.txt");
    let cases = [
        (
            "ate",
            evo_stats("evo_ape", &["tum", gt, est, "-r", "trans_part"], dir.path()),
        ),
        (
            "ate_aligned",
            evo_stats("evo_ape", &["tum", gt, est, "-r", "trans_part", "--align"], dir.path()),
        ),
        (
            "rpe",
            evo_stats(
                "evo_rpe",
                &["tum", gt, est, "-r", "trans_part", "--delta", "2", "--delta_unit", "f"],
                dir.path(),
            ),
        ),
    ];
    for (name, theirs) in cases {
        for stat in ["rmse", "mean", "median", "std", "min", "max"] {
            let (a, b) = (
                ours[name][stat].as_f64().expect("ours"),
                theirs[stat].as_f64().expect("evo"),
            );
            assert!((a - b).abs() < EVO_TOLERANCE_M, "{name} {stat}: ours {a}, evo {b}");
        }
    }
    // the TUM converter writes what evo reads
    let tum = dir.path().join("truth.txt");
    let o = gprflow(&[
        "convert",
        rec.to_str().expect("utf8"),
        "--to",
        "tum",
        "--topic",
        "truth/pose",
        "-o",
        tum.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let self_ape = evo_stats("evo_ape", &["tum", "truth.txt", "truth.txt"], dir.path());
    assert!(self_ape["max"].as_f64().expect("max") < 1e-12);
}

#[test]
fn diff_passes_identical_runs_and_names_the_first_divergence() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sim = |name: &str, scenario: &str| {
        let path = dir.path().join(name);
        let o = gprflow(&["sim", scenario, "-o", path.to_str().expect("utf8"), "--duration", "4"]);
        assert!(o.status.success(), "{}", stderr(&o));
        path
    };
    let scenario = dir.path().join("s.yaml");
    let text = std::fs::read_to_string(repo().join("tools/sim/scenarios/pipes_one_line.yaml")).expect("scenario");
    std::fs::write(&scenario, &text).expect("write");
    let a = sim("a.mcap", scenario.to_str().expect("utf8"));
    let b = sim("b.mcap", scenario.to_str().expect("utf8"));
    let same = gprflow(&["diff", a.to_str().expect("utf8"), b.to_str().expect("utf8")]);
    assert_eq!(same.status.code(), Some(0), "{}", String::from_utf8_lossy(&same.stdout));
    // a different seed: the same topics and counts, other values
    std::fs::write(&scenario, text.replace("seed: 4004", "seed: 4005")).expect("write");
    let c = sim("c.mcap", scenario.to_str().expect("utf8"));
    let o = gprflow(&["diff", a.to_str().expect("utf8"), c.to_str().expect("utf8"), "--json"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).expect("diff json");
    let first = &report["report"]["first_divergence"];
    assert!(first["topic"].is_string() && first["path"].is_string(), "{first}");
    let trace = report["report"]["topics"]
        .as_array()
        .expect("topics")
        .iter()
        .find(|t| t["topic"] == "/gpr/trace")
        .expect("trace topic");
    assert_eq!(trace["count_a"], trace["count_b"]);
    assert!(
        trace["fields"]["samples_i16[]"]["max_abs"].as_f64().expect("max_abs") > 0.0,
        "{trace}"
    );
    // huge tolerances accept the value differences
    let o = gprflow(&[
        "diff",
        a.to_str().expect("utf8"),
        c.to_str().expect("utf8"),
        "--abs-tol",
        "1e9",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stdout));
    // a tolerance file: huge on the trace samples only, so the other topics still differ ...
    let tol = dir.path().join("tol.yaml");
    std::fs::write(
        &tol,
        "rules:\n  - { topic: \"/gpr/trace\", field: \"samples_i16[]\", abs: 1.0e9 }\n",
    )
    .expect("write");
    let o = gprflow(&[
        "diff",
        a.to_str().expect("utf8"),
        c.to_str().expect("utf8"),
        "--tolerances",
        tol.to_str().expect("utf8"),
        "--json",
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stdout));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).expect("diff json");
    assert_ne!(report["report"]["first_divergence"]["topic"], "/gpr/trace", "{report}");
    // ... and huge everywhere, as the flag
    std::fs::write(&tol, "default: { abs: 1.0e9 }\n").expect("write");
    let o = gprflow(&[
        "diff",
        a.to_str().expect("utf8"),
        c.to_str().expect("utf8"),
        "--tolerances",
        tol.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stdout));
    // a bad tolerance file: exit 2 naming it
    std::fs::write(&tol, "default: { abs: -1 }\n").expect("write");
    let o = gprflow(&[
        "diff",
        a.to_str().expect("utf8"),
        c.to_str().expect("utf8"),
        "--tolerances",
        tol.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("tol.yaml: default"), "{}", stderr(&o));
    // fewer messages: a regression even with tolerances
    let short = dir.path().join("short.mcap");
    let o = gprflow(&[
        "sim",
        scenario.to_str().expect("utf8"),
        "-o",
        short.to_str().expect("utf8"),
        "--duration",
        "3",
    ]);
    assert!(o.status.success());
    let o = gprflow(&[
        "diff",
        c.to_str().expect("utf8"),
        short.to_str().expect("utf8"),
        "--abs-tol",
        "1e9",
    ]);
    assert_eq!(o.status.code(), Some(1));
    // different topic sets: a regression, each topic counted on both sides
    let o = gprflow(&["diff", a.to_str().expect("utf8"), "recordings/toy.mcap", "--json"]);
    assert_eq!(o.status.code(), Some(1));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).expect("diff json");
    let topics = report["report"]["topics"].as_array().expect("topics");
    assert!(
        topics.iter().any(|t| t["topic"] == "/gen/trace" && t["count_a"] == 0),
        "{report}"
    );
    assert!(
        topics.iter().any(|t| t["topic"] == "/gpr/trace" && t["count_b"] == 0),
        "{report}"
    );
    // not a recording: exit 2 naming the file
    let o = gprflow(&["diff", a.to_str().expect("utf8"), scenario.to_str().expect("utf8")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("s.yaml"), "{}", stderr(&o));
}

/// Reruns `graph` (with `sets`) and diffs its recording against
/// `recordings/golden/{graph}.mcap`.
fn assert_reproduces_golden(graph: &str, sets: &[String]) {
    let dir = tempfile::tempdir().expect("tempdir");
    let golden = repo().join(format!("recordings/golden/{graph}.mcap"));
    assert!(
        golden.exists(),
        "{} missing: tools/scripts/update-goldens.sh",
        golden.display()
    );
    let out = dir.path().join(format!("{graph}.mcap"));
    let graph_file = format!("graphs/{graph}.yaml");
    let mut args = vec!["launch", &graph_file, "--record", out.to_str().expect("utf8")];
    for set in sets {
        args.extend(["--set", set]);
    }
    let o = gprflow(&args);
    assert!(o.status.success(), "{graph}: {}", stderr(&o));
    let d = gprflow(&["diff", golden.to_str().expect("utf8"), out.to_str().expect("utf8")]);
    assert_eq!(
        d.status.code(),
        Some(0),
        "{graph} no longer reproduces its golden (if intended: tools/scripts/update-goldens.sh):\n{}",
        String::from_utf8_lossy(&d.stdout)
    );
}

#[test]
fn golden_outputs_still_match() {
    let pipes = format!("recording={}", pipe_sample().display());
    for graph in ["toy", "replay-toy", "odometry"] {
        assert_reproduces_golden(graph, &[]);
    }
    assert_reproduces_golden("slam", &[pipes]);
}

#[test]
fn golden_localisation_still_matches() {
    assert_reproduces_golden("localize", &[]);
}

#[test]
fn golden_submaps_and_sweeps_still_match() {
    // short inputs and sparse submaps keep these goldens small (floats compress poorly);
    // made as tools/scripts/update-goldens.sh makes them (keep the two alike)
    let garage = simulated(
        "garage-loops-20s.mcap",
        &[
            "tools/sim/scenarios/parking_garage.yaml",
            "--run",
            "loops",
            "--duration",
            "20",
        ],
    );
    assert_reproduces_golden(
        "submaps",
        &[format!("recording={}", garage.display()), "spacing_m=1.0".into()],
    );
    let highway = simulated(
        "highway-map-1s.mcap",
        &["tools/sim/scenarios/highway.yaml", "--run", "map", "--duration", "1"],
    );
    assert_reproduces_golden("lgpr-sweeps", &[format!("recording={}", highway.display())]);
}

#[test]
fn eval_draws_a_plot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = dir.path().join("gps.yaml");
    let text = std::fs::read_to_string(repo().join("tools/sim/scenarios/pipes_one_line.yaml")).expect("scenario");
    std::fs::write(&scenario, format!("{text}\ngps: {{ rate_hz: 10 }}\n")).expect("write");
    let rec = dir.path().join("gps.mcap");
    let o = gprflow(&[
        "sim",
        scenario.to_str().expect("utf8"),
        "-o",
        rec.to_str().expect("utf8"),
        "--duration",
        "20",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let png = dir.path().join("eval.png");
    let o = gprflow(&[
        "eval",
        rec.to_str().expect("utf8"),
        "--plot",
        png.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&png).expect("png written");
    assert!(
        bytes.starts_with(b"\x89PNG\r\n\x1a\n") && bytes.len() > 20_000,
        "{} bytes",
        bytes.len()
    );
    // the radargram: one column per trace
    let rg = dir.path().join("rg.png");
    let o = gprflow(&[
        "radargram",
        rec.to_str().expect("utf8"),
        "--to",
        "10",
        "-o",
        rg.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&rg).expect("png written");
    let width = u32::from_be_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
    let height = u32::from_be_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]);
    assert_eq!((width, height), (501, 201), "50 traces/s for 10 s, 201 samples");
    // truth from a recording that has none: a clear error, exit 2
    let o = gprflow(&["eval", rec.to_str().expect("utf8"), "--truth", "recordings/toy.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("no ground truth on /truth/pose"), "{}", stderr(&o));
    // no estimate in the recording: a clear error, exit 2
    let o = gprflow(&["eval", "recordings/toy.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("recordings/toy.mcap"), "{}", stderr(&o));
}

#[test]
fn estimate_tracks_a_simulated_garage_loop_from_imu_and_wheel() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("odom.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/odometry.yaml",
        "--record",
        rec.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = gprflow(&[
        "eval",
        rec.to_str().expect("utf8"),
        "--truth",
        "recordings/sim/garage-loops-60s.mcap",
        "--format",
        "json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let e: serde_json::Value = serde_json::from_slice(&o.stdout).expect("eval json");
    // 60 s at 10 states per second, all of them in the final trajectory and paired with truth
    assert!(
        e["estimate"]
            .as_str()
            .expect("estimate")
            .ends_with("/estimate/trajectory"),
        "{e}"
    );
    assert!(e["associated"].as_u64().expect("associated") >= 595, "{e}");
    // A 27 m loop with three 90-degree corners: within 0.4 m of the truth in the world frame
    // (anchored by the first truth pose) and 0.15 m after alignment; measured 0.20 and 0.065 m.
    let ate = e["ate"]["rmse"].as_f64().expect("ate");
    let aligned = e["ate_aligned"]["rmse"].as_f64().expect("aligned");
    assert!(ate < 0.4 && aligned < 0.15, "ATE {ate} m, aligned {aligned} m");
}

/// Launches `graph` with `--set` assignments, recorded to `dir/run.mcap`; checks that it
/// succeeded and returns the recorded payloads per topic and the launcher's output.
fn launch_recorded(dir: &Path, graph: &str, sets: &[String]) -> (BTreeMap<String, Vec<Vec<u8>>>, Output) {
    let rec = dir.join("run.mcap");
    let mut args = vec!["launch".to_owned(), graph.to_owned()];
    for s in sets {
        args.extend(["--set".to_owned(), s.clone()]);
    }
    args.extend(["--record".to_owned(), rec.to_str().expect("utf8").to_owned()]);
    let o = gprflow(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{graph}: {}", stderr(&o));
    (payloads(&rec), o)
}

fn decode_all<'a, M: gprflow::msg::CdrDecode<'a>>(msgs: &'a [Vec<u8>]) -> Vec<M> {
    msgs.iter()
        .map(|p| gprflow::msg::decode::<M>(p).expect("decodes"))
        .collect()
}

#[test]
fn submap_pipeline_resamples_a_simulated_run_by_wheel_distance() {
    use gprflow::msg::Submap;
    let dir = tempfile::tempdir().expect("tempdir");
    // a submap every 0.1 m, not 0.02 m: a fifth of the data to write and read
    let (p, _) = launch_recorded(dir.path(), "graphs/submaps.yaml", &["spacing_m=0.1".into()]);
    let raw: Vec<Submap> = decode_all(&p["/submap/submap"]);
    let filtered: Vec<Submap> = decode_all(&p["/filter/submap"]);
    // 60 s, 27 m with three corners: submaps every 0.1 m once 3 m are covered, none across
    // a corner (the gyro rule)
    assert!(raw.len() > 80, "{} submaps", raw.len());
    assert_eq!(raw.len(), filtered.len());
    for (r, f) in raw.iter().zip(&filtered) {
        assert!(r.valid && f.valid);
        assert_eq!((r.rows, r.cols, r.id), (f.rows, f.cols, f.id));
        assert_eq!((r.rows, r.cols), (201, 200));
        assert!((r.resolution_m - 0.015).abs() < 1e-12);
        assert!(
            (r.end_distance_m - r.start_distance_m - 199.0 * 0.015).abs() < 1e-6,
            "{}",
            r.id
        );
        assert!(r.header.stamp.to_ns() > r.start_stamp.to_ns());
        assert!(f.pixels.iter().all(|v| v.is_finite()));
        assert!(f.saliency.is_finite() && f.saliency > 0.0);
    }
    // consecutive valid submaps: 0.1 m apart (to a column)
    let steps: Vec<f64> = raw
        .windows(2)
        .filter(|w| w[1].id == w[0].id + 1)
        .map(|w| w[1].start_distance_m - w[0].start_distance_m)
        .collect();
    assert!(steps.len() > 60);
    assert!(steps.iter().all(|s| (s - 0.1).abs() <= 0.015 + 1e-9), "{steps:?}");
    // the filtered submaps differ from the raw ones (background, wavelet, gaussian ran)
    assert!(raw[0].pixels != filtered[0].pixels);
    // prior-mean background: the first submap's own mean trace is removed
    let f0 = &filtered[0];
    let cols = f0.cols as usize;
    let mean_abs_row_mean = (0..f0.rows as usize)
        .map(|r| (f0.pixels[r * cols..(r + 1) * cols].iter().sum::<f32>() / cols as f32).abs())
        .sum::<f32>()
        / f0.rows as f32;
    let mean_abs = f0.pixels.iter().map(|v| v.abs()).sum::<f32>() / f0.pixels.len() as f32;
    assert!(mean_abs_row_mean < 0.2 * mean_abs, "{mean_abs_row_mean} vs {mean_abs}");
}

#[test]
fn a_cmu_gpr_folder_ingests_as_the_recording_it_was_written_with() {
    use gprflow::msg::{Imu, Trace, WheelOdometry};
    let dir = tempfile::tempdir().expect("tempdir");
    let sim = dir.path().join("basement.mcap");
    let o = gprflow(&[
        "sim",
        "tools/sim/scenarios/basement.yaml",
        "-o",
        sim.to_str().expect("utf8"),
        "--format",
        "cmu-gpr",
        "--duration",
        "4",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let folder = dir.path().join("basement");
    let conv = dir.path().join("converted.mcap");
    let o = gprflow(&[
        "convert",
        folder.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        conv.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, b) = (payloads(&sim), payloads(&conv));
    let (ta, tb): (Vec<Trace>, Vec<Trace>) = (decode_all(&a["/gpr/trace"]), decode_all(&b["/gpr/trace"]));
    assert_eq!(ta.len(), tb.len());
    assert!(ta.len() > 150);
    for (x, y) in ta.iter().zip(&tb) {
        assert_eq!(x.header.stamp, y.header.stamp);
        assert_eq!(x.samples_i16, y.samples_i16);
        assert_eq!(x.sample_interval_ns, y.sample_interval_ns);
    }
    let (wa, wb): (Vec<WheelOdometry>, Vec<WheelOdometry>) =
        (decode_all(&a["/wheel/odometry"]), decode_all(&b["/wheel/odometry"]));
    assert_eq!(wa.len(), wb.len());
    for (x, y) in wa.iter().zip(&wb) {
        assert_eq!(x.header.stamp, y.header.stamp);
        // the CSV holds 6 decimals
        assert!((x.distance_m - y.distance_m).abs() <= 5e-7 + 1e-12);
    }
    let (ia, ib): (Vec<Imu>, Vec<Imu>) = (decode_all(&a["/imu/data"]), decode_all(&b["/imu/data"]));
    assert_eq!(ia.len(), ib.len());
    for (x, y) in ia.iter().zip(&ib) {
        assert_eq!(x.header.stamp, y.header.stamp);
        // 7 decimals
        let close = |p: f64, q: f64| (p - q).abs() <= 5e-8 + 1e-12;
        assert!(close(x.angular_velocity.z, y.angular_velocity.z));
        assert!(close(x.linear_acceleration.x, y.linear_acceleration.x));
        assert!(close(x.linear_acceleration.z, y.linear_acceleration.z));
    }
}

/// The real radar files committed in `recordings/real-gpr`.
fn real_gpr(file: &str) -> PathBuf {
    let dir = repo().join("recordings/real-gpr");
    assert!(
        dir.is_dir(),
        "{} is missing: the tests read the real radar files there",
        dir.display()
    );
    dir.join(file)
}

#[test]
fn real_radar_files_convert_and_the_python_reader_agrees() {
    use gprflow::msg::{Trace, WheelOdometry};
    let dir = tempfile::tempdir().expect("tempdir");
    // file, traces, samples, sample interval ns, metres between traces
    let cases = [
        ("GSSI_FILE____032.DZT", 1040, 512, 48.0 / 512.0, 1.0 / 50.0),
        ("SnS_ComOffs_XLINE00.DT1", 531, 1500, 0.8, f64::NAN),
        ("SnS_WARR_XLINE00.DT1", 164, 1900, 0.4, f64::NAN),
    ];
    for (file, traces, samples, dt, spacing) in cases {
        let out = dir.path().join(format!("{file}.mcap"));
        let o = gprflow(&[
            "convert",
            real_gpr(file).to_str().expect("utf8"),
            "--to",
            "mcap",
            "-o",
            out.to_str().expect("utf8"),
        ]);
        assert!(o.status.success(), "{file}: {}", stderr(&o));
        let p = payloads(&out);
        let t: Vec<Trace> = decode_all(&p["/gpr/trace"]);
        assert_eq!(t.len(), traces, "{file}");
        assert!(t.iter().all(|t| t.len() == samples), "{file}");
        assert!(
            (t[0].sample_interval_ns - dt).abs() < 1e-9,
            "{file}: {}",
            t[0].sample_interval_ns
        );
        let w: Vec<WheelOdometry> = decode_all(&p["/wheel/odometry"]);
        assert_eq!(w.len(), traces, "{file}: a distance per trace");
        if spacing.is_finite() {
            let step = w[1].distance_m - w[0].distance_m;
            assert!((step - spacing).abs() < 1e-6, "{file}: {step}");
        }
        peer_check(&out, &format!("{} messages", 2 * traces));
    }
}

#[test]
fn bad_radar_files_get_clear_errors_and_lose_no_complete_trace() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bytes = std::fs::read(real_gpr("GSSI_FILE____032.DZT")).expect("dzt");
    // cut inside the last trace: every complete trace is kept, the cut one reported
    let cut = dir.path().join("cut.DZT");
    std::fs::write(&cut, &bytes[..bytes.len() - 300]).expect("write");
    let out = dir.path().join("cut.mcap");
    let o = gprflow(&[
        "convert",
        cut.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("1039 messages"), "{text}");
    assert!(text.contains("cut.DZT: trace 1039: truncated"), "{text}");
    // a header that says 12-bit samples: refused, naming the file and field
    let mut bad = bytes.clone();
    bad[6] = 12;
    bad[7] = 0;
    let badf = dir.path().join("bits.DZT");
    std::fs::write(&badf, &bad).expect("write");
    let o = gprflow(&[
        "convert",
        badf.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("bits.DZT: header: rh_bits: 12"), "{}", stderr(&o));
    // a DT1 without its HD
    let dt1 = dir.path().join("line.DT1");
    std::fs::copy(real_gpr("SnS_WARR_XLINE00.DT1"), &dt1).expect("copy");
    let o = gprflow(&[
        "convert",
        dt1.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("line.HD: not found"), "{}", stderr(&o));
    // the same errors stop a launched ingest stage with the file named
    let o = gprflow(&[
        "launch",
        "graphs/submaps.yaml",
        "--set",
        &format!("recording={}", badf.display()),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("bits.DZT: header: rh_bits: 12"), "{}", stderr(&o));
    // a CMU-GPR row with NaN is dropped and reported with file and line
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).expect("mkdir");
    let row = |t: &str, v: &str| format!("{t},{}\n", [v; 4].join(","));
    let gpr = format!(
        "t,amp_1,amp_2,amp_3,amp_4\n{}{}{}",
        row("1.00", "5"),
        row("1.02", "nan"),
        row("1.04", "7")
    );
    std::fs::write(seq.join("gpr_meas.csv"), gpr).expect("write");
    std::fs::write(seq.join("we_odom_meas.csv"), "t,dist\n1.0,0.0\n1.1,0.05\n").expect("write");
    let o = gprflow(&[
        "convert",
        seq.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("/gpr/trace                   2 messages"), "{text}");
    assert!(text.contains("gpr_meas.csv:3"), "{text}");
}

#[test]
fn lgpr_sweep_chain_turns_simulated_sweeps_into_high_passed_range_profiles() {
    use gprflow::msg::Sweep;
    let dir = tempfile::tempdir().expect("tempdir");
    let (p, _) = launch_recorded(dir.path(), "graphs/lgpr-sweeps.yaml", &[]);
    let out: Vec<Sweep> = decode_all(&p["/lgpr/sweep"]);
    // every one of the 5 s x 126 Hz sweeps, none waiting on the factory calibration
    assert_eq!(out.len(), 631);
    let t0 = out[0].header.stamp.to_ns();
    let mut still = 0.0f32;
    let mut moving = 0.0f32;
    for s in &out {
        assert_eq!(s.domain, Sweep::DOMAIN_TIME);
        assert_eq!((s.channel_count, s.bin_count), (11, 369));
        assert_eq!(s.values.len(), 11 * 369);
        assert!(s.calibration.is_empty());
        assert!(s.values.iter().all(|v| v.is_finite()));
        let peak = s.values.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let t = (s.header.stamp.to_ns() - t0) as f64 * 1e-9;
        // the vehicle stands for the first 2.3 s, then accelerates
        if t < 2.0 {
            still = still.max(peak);
        } else if t > 3.0 {
            moving = moving.max(peak);
        }
    }
    // standing still, the distance IIR holds its mean (beta = 1): the static scene and the
    // ground bounce cancel and only noise is left; moving, the subsurface features pass
    assert!(moving > 20.0 * still, "moving peak {moving}, still peak {still}");
}

#[test]
fn a_real_dzt_line_runs_through_the_submap_pipeline() {
    use gprflow::msg::Submap;
    let dir = tempfile::tempdir().expect("tempdir");
    let dzt = real_gpr("GSSI_FILE____032.DZT");
    let sets = [
        format!("recording={}", dzt.display()),
        "spacing_m=0.5".into(),
        "hold_first_samples=2".into(),
    ];
    let (p, _) = launch_recorded(dir.path(), "graphs/submaps.yaml", &sets);
    let maps: Vec<Submap> = decode_all(&p["/filter/submap"]);
    // 1040 scans at 50 scans/m: 20.78 m of line, a submap every 0.5 m after the first 3 m
    // (traces 0.02 m apart fill every 0.015 m column but one in four: the rest interpolated)
    assert!((35..=37).contains(&maps.len()), "{} submaps", maps.len());
    assert!(maps.iter().all(|m| m.valid && m.rows == 512 && m.cols == 200));
    assert!(maps.iter().all(|m| m.pixels.iter().all(|v| v.is_finite())));
    let last = maps.last().expect("submaps");
    assert!((last.end_distance_m - 20.78).abs() < 0.5, "{}", last.end_distance_m);
    for w in maps.windows(2) {
        let step = w[1].end_distance_m - w[0].end_distance_m;
        assert!((step - 0.5).abs() < 0.02 + 1e-9, "{step}");
    }
}

#[test]
fn unusable_traces_are_dropped_counted_and_named_while_the_run_goes_on() {
    use gprflow::msg::{Header, Message, Submap, Trace, WheelOdometry, encode};
    use std::borrow::Cow;
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("bad-traces.mcap");
    {
        let mut w =
            gprflow::record::Recorder::create(&rec, &gprflow::record::RunMetadata::this_build()).expect("create");
        let tr = w.add_topic("/gpr/trace", Trace::TYPE_NAME).expect("topic");
        let wh = w.add_topic("/wheel/odometry", WheelOdometry::TYPE_NAME).expect("topic");
        // 4 m at 1 m/s, 100 traces/s, 201 samples; trace 50 holds a NaN, trace 60 is short
        for k in 0..400i64 {
            let stamp = 1_000_000_000 + k * 10_000_000;
            let mut samples: Vec<f32> = (0..201)
                .map(|i| ((i as f32) * 0.3 + (k as f32) * 0.05).sin() * 1000.0)
                .collect();
            if k == 50 {
                samples[5] = f32::NAN;
            }
            if k == 60 {
                samples.truncate(150);
            }
            let t = Trace {
                header: Header::new(stamp, "gpr"),
                sample_interval_ns: 0.2,
                center_frequency_hz: 5e8,
                distance_m: f64::NAN,
                samples_f32: Cow::Owned(samples),
                ..Trace::default()
            };
            w.write(tr, k as u64, stamp, &encode(&t)).expect("write");
            if k % 2 == 0 {
                let m = WheelOdometry {
                    header: Header::new(stamp, "odom"),
                    distance_m: k as f64 * 0.01,
                    ticks: 0,
                    speed_mps: 1.0,
                };
                w.write(wh, (k / 2) as u64, stamp, &encode(&m)).expect("write");
            }
        }
        w.finish().expect("finish");
    }
    let graph = dir.path().join("g.yaml");
    std::fs::write(
        &graph,
        "name: bad\nnodes:\n  ingest: { stage: ingest, params: { source: \"".to_owned()
            + rec.to_str().expect("utf8")
            + "\" } }\n  dsp: { stage: dsp, inputs: { trace: ingest/gpr } }\n  submap: { stage: submap, inputs: { trace: dsp/trace, wheel: ingest/wheel } }\nrecord: { topics: [\"dsp/*\", \"submap/*\"] }\n",
    )
    .expect("graph");
    let (p, o) = launch_recorded(dir.path(), graph.to_str().expect("utf8"), &[]);
    let err = stderr(&o);
    assert!(
        err.contains("topic=\"ingest/gpr\" seq=50") && err.contains("trace: value 5 is not finite"),
        "{err}"
    );
    assert!(
        err.contains("seq=60") && err.contains("expected 201 values, got 150"),
        "{err}"
    );
    assert!(err.contains("dsp: messages dropped as unusable messages=2"), "{err}");
    assert_eq!(p["/dsp/trace"].len(), 398);
    let maps: Vec<Submap> = decode_all(&p["/submap/submap"]);
    // 3.98 m of travel: submaps from 3 m on, every 0.02 m
    assert!((45..=52).contains(&maps.len()), "{}", maps.len());
}

#[test]
fn holding_the_dzt_counter_samples_lets_zero_time_find_the_first_negative_peak() {
    use gprflow::msg::Trace;
    let dir = tempfile::tempdir().expect("tempdir");
    let dzt = real_gpr("GSSI_FILE____032.DZT");
    let run = |hold: usize| -> Vec<Vec<f32>> {
        let graph = dir.path().join(format!("hold{hold}.yaml"));
        let run_dir = dir.path().join(format!("hold{hold}"));
        std::fs::create_dir(&run_dir).expect("mkdir");
        std::fs::write(
            &graph,
            format!(
                "name: hold\nnodes:\n  ingest: {{ stage: ingest, params: {{ source: \"{}\" }} }}\n  dsp: {{ stage: dsp, inputs: {{ trace: ingest/gpr }}, params: {{ hold_first_samples: {hold}, dewow: null, bandpass: null, sec_gain: null }} }}\nrecord: {{ topics: [\"dsp/*\", \"ingest/gpr\"] }}\n",
                dzt.display()
            ),
        )
        .expect("graph");
        let (p, _) = launch_recorded(&run_dir, graph.to_str().expect("utf8"), &[]);
        decode_all::<Trace>(&p["/dsp/trace"])
            .iter()
            .map(|t| t.samples_f32.to_vec())
            .collect()
    };
    let raw = run(0);
    let held = run(2);
    assert_eq!((raw.len(), held.len()), (1040, 1040));
    // sample 0 of a DZT trace is a scan counter (about -32768 after the unsigned offset): left
    // in, it is the "first negative peak" and nothing moves
    assert!(raw.iter().all(|t| t[0] < -30_000.0), "{}", raw[0][0]);
    // held, zero time finds the direct wave: the trace starts at a negative lobe that is the
    // minimum of its first run below half the peak, well above the counter's value
    for t in &held {
        assert!(t[0] < 0.0 && t[0] > -30_000.0, "{}", t[0]);
        assert!(t[1] >= t[0], "{} {}", t[0], t[1]);
    }
}

/// `gprflow eval RUN --truth TRUTH --format json`.
fn eval_json(run: &Path, truth: &str) -> serde_json::Value {
    let o = gprflow(&[
        "eval",
        run.to_str().expect("utf8"),
        "--truth",
        truth,
        "--format",
        "json",
    ]);
    assert!(o.status.success(), "eval: {}", stderr(&o));
    serde_json::from_slice(&o.stdout).expect("eval json")
}

const BASEMENT: &str = "recordings/sim/basement-forward_backward.mcap";

#[test]
fn calibrate_wheel_measures_the_rigs_scale_and_the_odometry_takes_it() {
    // the simulated wheel's radius is 1 % above nominal, less what it slips
    let o = gprflow(&["calibrate-wheel", BASEMENT, "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let c: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    let scale = c["wheel_scale"].as_f64().expect("wheel_scale");
    assert!((scale - 1.01).abs() < 0.003, "{c}");
    assert!(c["combined"]["wheel_m"].as_f64().expect("wheel_m") > 40.0, "{c}");
    // odometry on the recording's own distances, then calibrated
    let along = |wheel_scale: f64| {
        let dir = tempfile::tempdir().expect("tempdir");
        launch_recorded(
            dir.path(),
            "graphs/odometry.yaml",
            &[format!("recording={BASEMENT}"), format!("wheel_scale={wheel_scale}")],
        );
        let e = eval_json(&dir.path().join("run.mcap"), BASEMENT);
        let a = &e["along_track"];
        (a["mean"].as_f64().expect("mean"), a["rmse"].as_f64().expect("rmse"))
    };
    let (raw, calibrated) = (along(1.0), along(scale));
    assert!(
        calibrated.0.abs() < 0.3 * raw.0.abs() && calibrated.1 < raw.1,
        "along-track (mean, rmse): {raw:?} raw, {calibrated:?} calibrated"
    );
    // bad input: a recording without a wheel, a scale that is no scale
    let o = gprflow(&["calibrate-wheel", "recordings/toy.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("recordings/toy.mcap: no wheel topic"),
        "{}",
        stderr(&o)
    );
    let o = gprflow(&["launch", "graphs/odometry.yaml", "--set", "wheel_scale=0"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("wheel_scale: must be finite and > 0, got 0"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn localisation_with_engineered_registration_beats_odometry_on_the_basement_run() {
    use gprflow::msg::Registration;
    let dir = tempfile::tempdir().expect("tempdir");
    // the whole pipeline, with the default 16-frame buffers: the estimate -> register
    // feedback ran into a wait cycle at 45 s before feedback inputs drained their inboxes
    let (p, o) = launch_recorded(dir.path(), "graphs/localize.yaml", &[]);
    let regs: Vec<Registration> = decode_all(&p["/register/registration"]);
    assert!(regs.len() >= 20, "{} registrations: {}", regs.len(), stderr(&o));
    for r in &regs {
        assert_eq!(r.method, "engineered");
        // loop candidates, not sequential submaps: at least 15 s apart
        assert!((r.query_stamp.to_ns() - r.reference_stamp.to_ns()).abs() >= 15_000_000_000);
        assert!((r.along_track_variance_m2 - 0.05f64.powi(2)).abs() < 1e-12);
    }
    let run = eval_json(&dir.path().join("run.mcap"), BASEMENT);
    let reg_rmse = run["registration"]["along_track"]["rmse"]
        .as_f64()
        .expect("registration rmse");
    assert!(reg_rmse < 0.03, "registration along-track RMSE {reg_rmse} m");
    // the same recording without registration
    let odo_dir = tempfile::tempdir().expect("tempdir");
    launch_recorded(
        odo_dir.path(),
        "graphs/odometry.yaml",
        &[format!("recording={BASEMENT}")],
    );
    let odo = eval_json(&odo_dir.path().join("run.mcap"), BASEMENT);
    let (ate, ate_odo) = (
        run["ate"]["rmse"].as_f64().expect("ate"),
        odo["ate"]["rmse"].as_f64().expect("odometry ate"),
    );
    assert!(
        ate < 0.8 * ate_odo,
        "ATE {ate} m with registration, {ate_odo} m odometry only"
    );
}

#[test]
fn registrations_on_overlap_stamps_leave_the_wheel_scale_out() {
    use gprflow::msg::Registration;
    let dir = tempfile::tempdir().expect("tempdir");
    let (p, o) = launch_recorded(dir.path(), "graphs/localize.yaml", &["stamps=overlap".to_owned()]);
    let regs: Vec<Registration> = decode_all(&p["/register/registration"]);
    assert!(regs.len() >= 20, "{} registrations: {}", regs.len(), stderr(&o));
    for r in &regs {
        // the two passes' moments over the same ground: no offset left, passes seconds apart
        assert_eq!(r.along_track_m, 0.0);
        assert!((r.query_stamp.to_ns() - r.reference_stamp.to_ns()).abs() >= 5_000_000_000);
    }
    // against the truth between those moments; with the anchors' wheel-metre shifts the same
    // matches are 0.78 cm off on this recording (0.34 cm this way, 3 Dec 2026)
    let run = eval_json(&dir.path().join("run.mcap"), BASEMENT);
    let reg_rmse = run["registration"]["along_track"]["rmse"]
        .as_f64()
        .expect("registration rmse");
    assert!(reg_rmse < 0.005, "registration along-track RMSE {reg_rmse} m");
}

#[test]
fn localisation_with_the_learned_model_and_the_oracle() {
    use gprflow::msg::Registration;
    for method in ["learned", "oracle"] {
        let dir = tempfile::tempdir().expect("tempdir");
        let (p, o) = launch_recorded(dir.path(), "graphs/localize.yaml", &[format!("method={method}")]);
        let regs: Vec<Registration> = decode_all(&p["/register/registration"]);
        assert!(
            regs.len() >= 20,
            "{method}: {} registrations: {}",
            regs.len(),
            stderr(&o)
        );
        assert!(regs.iter().all(|r| r.method == method));
        let run = eval_json(&dir.path().join("run.mcap"), BASEMENT);
        let reg_rmse = run["registration"]["along_track"]["rmse"]
            .as_f64()
            .expect("registration rmse");
        // the oracle is the truth (to the interpolation); the model within a few cm
        let limit = if method == "oracle" { 1e-3 } else { 0.03 };
        assert!(reg_rmse < limit, "{method}: registration along-track RMSE {reg_rmse} m");
    }
}

/// The number after `key=` in a stage's log (its last mention), e.g. the register stage's
/// `stretched=` count.
fn logged_count(log: &str, key: &str) -> Option<u64> {
    let pattern = format!(" {key}=");
    let at = log.rfind(&pattern)? + pattern.len();
    let digits: String = log[at..].chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// The simulated basement's `by_hand` run (wander, drying soil, uneven ground contact), as
/// the shipped graph localises it: the learned model registers queries whose travel times it
/// stretched, the estimator gates a registration far from its estimate, and the run ends
/// closer to the truth than the same graph with the search and the gate off, and far closer
/// than odometry alone. The register stage encodes a submap once, only when it is a query
/// with loop candidates or a kept reference, and the search adds two stretched encodings per
/// query.
#[test]
fn the_stretch_search_and_the_gate_on_a_by_hand_run() {
    let rec = simulated(
        "basement-by_hand.mcap",
        &["tools/sim/scenarios/basement.yaml", "--run", "by_hand"],
    );
    let rec = rec.to_str().expect("utf8").to_owned();
    let localise = |graph: &str, sets: &[&str]| {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut all = vec![format!("recording={rec}")];
        all.extend(sets.iter().map(|s| (*s).to_owned()));
        let (p, o) = launch_recorded(dir.path(), graph, &all);
        let registrations = p.get("/register/registration").map_or(0, Vec::len);
        let ate = eval_json(&dir.path().join("run.mcap"), &rec)["ate"]["rmse"]
            .as_f64()
            .expect("ate");
        (registrations, stderr(&o), ate)
    };
    let (n, log, ate) = localise("graphs/localize.yaml", &["method=learned"]);
    let (n_off, log_off, ate_off) = localise(
        "graphs/localize.yaml",
        &["method=learned", "stretch_steps=0", "gate_m=0"],
    );
    let (_, _, ate_odo) = localise("graphs/odometry.yaml", &[]);
    let stretched = logged_count(&log, "stretched").expect("the register stage's counts");
    assert!(
        stretched > 0 && n > n_off,
        "{n} registrations ({stretched} stretched), {n_off} without the search"
    );
    assert_eq!(logged_count(&log_off, "stretched"), Some(0));
    // the estimate stage logs its count only when it dropped something
    let gated = logged_count(&log, "gated").unwrap_or(0);
    assert!(
        gated >= 1 && gated * 10 < n as u64,
        "{gated} of {n} registrations gated"
    );
    assert!(logged_count(&log_off, "gated").is_none(), "gate off, yet: {log_off}");
    for (log, stretched_per_query) in [(&log, 2), (&log_off, 0)] {
        let count = |key| logged_count(log, key).unwrap_or_else(|| panic!("no {key}= in {log}"));
        let (encoded, queries, references, submaps) =
            (count("encoded"), count("queries"), count("references"), count("valid"));
        // the submaps encoded unstretched: every query and every reference, a submap that is
        // both once, and none of the rest
        let once = encoded
            .checked_sub(stretched_per_query * queries)
            .unwrap_or_else(|| panic!("{encoded} encoder runs for {queries} queries"));
        assert!(
            queries.max(references) <= once && once <= queries + references && once < submaps,
            "{encoded} encoder runs for {queries} queries, {references} references, {submaps} submaps"
        );
    }
    assert!(
        ate < ate_off && ate < 0.25 * ate_odo,
        "ATE {ate} m, {ate_off} m without the search and the gate, {ate_odo} m odometry"
    );
}

#[test]
fn register_refuses_an_oracle_without_truth_and_a_missing_model() {
    let dir = tempfile::tempdir().expect("tempdir");
    let graph = dir.path().join("g.yaml");
    std::fs::write(
        &graph,
        "name: bad\nnodes:\n  ingest: { stage: ingest, params: { source: recordings/sim/basement-forward_backward.mcap } }\n  submap: { stage: submap, inputs: { trace: ingest/gpr, wheel: ingest/wheel } }\n  register: { stage: register, inputs: { submap: submap/submap }, params: { method: oracle, association: truth } }\n",
    )
    .expect("write");
    let o = gprflow(&["launch", graph.to_str().expect("utf8")]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("`truth` input"), "{}", stderr(&o));
    std::fs::write(
        &graph,
        "name: bad\nnodes:\n  ingest: { stage: ingest, params: { source: recordings/sim/basement-forward_backward.mcap } }\n  submap: { stage: submap, inputs: { trace: ingest/gpr, wheel: ingest/wheel } }\n  register: { stage: register, inputs: { submap: submap/submap, truth: ingest/truth }, params: { method: learned, association: truth, model: /nonexistent/enc.onnx } }\n",
    )
    .expect("write");
    let o = gprflow(&["launch", graph.to_str().expect("utf8")]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("/nonexistent/enc.onnx"), "{}", stderr(&o));
}

/// SLAM with line features on the pipe-field sample: every hyperbola the `lines` stage finds
/// is a crossing of the true pipe, one line comes out, and the line factors bring the
/// trajectory error well below the same estimator's without them; the detections are drawn
/// over the submaps and the traces.
#[test]
fn slam_detects_the_pipe_and_beats_odometry() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sample = pipe_sample();
    let sample = sample.to_str().expect("utf8");
    // the shipped graph, recording the traces and submaps too (for the pictures)
    let text = std::fs::read_to_string(repo().join("graphs/slam.yaml")).expect("graph");
    let text = text.replace(
        r#"record: { topics: ["estimate/*", "lines/*"] }"#,
        r#"record: { topics: ["estimate/*", "lines/*", "dsp/*", "filter/*"] }"#,
    );
    assert!(text.contains("dsp/*"), "graphs/slam.yaml's record line changed");
    let graph = dir.path().join("slam.yaml");
    std::fs::write(&graph, text).expect("write");
    let slam = dir.path().join("slam.mcap");
    let o = gprflow(&[
        "launch",
        graph.to_str().expect("utf8"),
        "--set",
        "spacing_m=0.25",
        "--set",
        &format!("recording={sample}"),
        "--record",
        slam.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let odom = dir.path().join("odom.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/odometry.yaml",
        "--set",
        &format!("recording={sample}"),
        "--record",
        odom.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let eval = |rec: &Path| -> serde_json::Value {
        let o = gprflow(&[
            "eval",
            rec.to_str().expect("utf8"),
            "--truth",
            sample,
            "--format",
            "json",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_slice(&o.stdout).expect("json")
    };
    let (with_lines, without) = (eval(&slam), eval(&odom));
    let obs = &with_lines["line_observations"];
    // the drive crosses the pipe four times in 150 s; nothing else is taken for a line
    assert_eq!(obs["observations"], 4, "{obs}");
    assert_eq!(obs["matched"], 4, "{obs}");
    assert!(obs["forward_distance"]["rmse"].as_f64().expect("rmse") < 0.1, "{obs}");
    let lines = &with_lines["lines"];
    assert_eq!(lines["matched"], 1, "{lines}");
    assert!(lines["rho_rmse_m"].as_f64().expect("rho") < 0.2, "{lines}");
    assert!(lines["theta_rmse_rad"].as_f64().expect("theta") < 0.1, "{lines}");
    let ate = |v: &serde_json::Value| v["ate"]["rmse"].as_f64().expect("ate");
    assert!(
        ate(&with_lines) < 0.6 * ate(&without),
        "ATE with lines {} m, without {} m",
        ate(&with_lines),
        ate(&without)
    );
    // the detections over a submap and over the traces
    for (topic, png) in [("/filter/submap", "submap.png"), ("/dsp/trace", "traces.png")] {
        let out = dir.path().join(png);
        let o = gprflow(&[
            "radargram",
            slam.to_str().expect("utf8"),
            "--topic",
            topic,
            "-o",
            out.to_str().expect("utf8"),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let said = String::from_utf8_lossy(&o.stdout);
        assert!(said.contains("line observations of /lines/observation"), "{said}");
        assert!(std::fs::metadata(&out).expect("png").len() > 1000);
    }
    // the most salient submap holds the pipe: its detection is drawn on it
    let out = dir.path().join("submap.png");
    let o = gprflow(&[
        "radargram",
        slam.to_str().expect("utf8"),
        "--topic",
        "/filter/submap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(!said.contains("with 0 line observations"), "{said}");
    // a topic that is not there is an error naming it
    let o = gprflow(&[
        "radargram",
        slam.to_str().expect("utf8"),
        "--features",
        "/nope",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("/nope"), "{}", stderr(&o));
}
