//! The simulator: its recordings, which `gprflow inspect` and the Python reader agree on, and
//! the simulated samples other tests read, made on demand.

use std::path::{Path, PathBuf};

use crate::common::{gprflow, stderr};
use crate::peer_check;

/// The pipe-field sample that `graphs/slam.yaml` reads (`recording`), made on demand as
/// `tools/sim/make-samples.sh` makes it (the simulator is deterministic; too big to commit).
pub(crate) fn pipe_sample() -> PathBuf {
    sim_input("pipes_one_line.yaml", "lawnmower", "150")
}

/// The simulator's run `run` of `tools/sim/scenarios/SCENARIO`, `seconds` long, made once.
pub(crate) fn sim_input(scenario: &str, run: &str, seconds: &str) -> PathBuf {
    let stem = scenario.trim_end_matches(".yaml");
    let path = format!("tools/sim/scenarios/{scenario}");
    simulated(
        &format!("{stem}-{run}-{seconds}s.mcap"),
        &[&path, "--run", run, "--duration", seconds],
    )
}

/// `gprflow sim ARGS` into target/tmp/samples/NAME, once: tests running at once each write
/// their own copy and move it into place.
pub(crate) fn simulated(name: &str, args: &[&str]) -> PathBuf {
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
