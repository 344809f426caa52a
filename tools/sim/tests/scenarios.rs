//! The shipped scenarios, the scenario file format and its errors, the CMU-GPR layout.

use std::path::{Path, PathBuf};

use gprflow_sim::motion::Motion;
use gprflow_sim::rng::Rng;
use gprflow_sim::{Scenario, SimError, SimOptions, simulate};

fn scenarios_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios")
}

fn shipped() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(scenarios_dir())
        .expect("scenarios dir")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .collect();
    files.sort();
    files
}

#[test]
fn every_shipped_scenario_loads_and_every_run_starts() {
    let dir = tempfile::tempdir().expect("tempdir");
    let files = shipped();
    assert!(files.len() >= 9, "scenarios: {files:?}");
    for file in files {
        let scenario = Scenario::load(&file).unwrap_or_else(|e| panic!("{e}"));
        for run in &scenario.runs {
            let opts = SimOptions {
                run: Some(run.name.clone()),
                output: dir.path().join("out.mcap"),
                max_duration_s: Some(2.5),
                ..SimOptions::default()
            };
            let summary = simulate(&scenario, &opts, &mut |_| {}).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
            assert!(
                summary.messages.values().sum::<u64>() > 100,
                "{}: {summary:?}",
                file.display()
            );
        }
    }
}

/// Ground footprint (min x, min y, max x, max y) of every run of a scenario.
fn footprint(scenario: &Scenario) -> [f64; 4] {
    let mut b = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    for run in &scenario.runs {
        let m = Motion::new(run, &scenario.vibration, &mut Rng::new(0));
        let n = 2000;
        for i in 0..=n {
            let p = m.at(m.duration_s() * f64::from(i) / f64::from(n)).position_m;
            b = [b[0].min(p.x), b[1].min(p.y), b[2].max(p.x), b[3].max(p.y)];
        }
    }
    b
}

#[test]
fn training_areas_never_overlap_the_evaluation_worlds() {
    let load = |name: &str| Scenario::load(&scenarios_dir().join(name)).expect("scenario");
    let margin = 50.0;
    let training: Vec<PathBuf> = shipped()
        .into_iter()
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("training_"))
        })
        .collect();
    assert!(training.len() >= 3, "training scenarios: {training:?}");
    for file in &training {
        let t = footprint(&Scenario::load(file).expect("scenario"));
        for eval in ["basement.yaml", "factory_floor.yaml", "parking_garage.yaml"] {
            let e = footprint(&load(eval));
            let apart = t[0] > e[2] + margin || e[0] > t[2] + margin || t[1] > e[3] + margin || e[1] > t[3] + margin;
            assert!(apart, "{} {t:?} overlaps {eval} {e:?}", file.display());
        }
    }
}

fn parse_err(text: &str) -> String {
    match Scenario::parse(text, Path::new("bad.yaml")) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

const GOOD: &str = "name: t
seed: 1
world:
  layers:
    - { top_depth_m: 0.0, eps_r: 6.0, attenuation_db_per_m: 3.0 }
radar: { kind: impulse }
runs:
  - name: a
    trajectory: { kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 3, speed_mps: 0.5 }
";

#[test]
fn scenario_errors_name_the_file_line_and_key() {
    assert!(Scenario::parse(GOOD, Path::new("good.yaml")).is_ok());
    let e = parse_err(&GOOD.replace("seed: 1", "seed: 1\nsead: 2"));
    assert!(e.starts_with("bad.yaml:3:"), "{e}");
    assert!(e.contains("sead"), "{e}");
    let e = parse_err(&GOOD.replace("eps_r: 6.0", "eps_r: wet"));
    assert!(e.starts_with("bad.yaml:5:"), "{e}");
    let e = parse_err(&GOOD.replace("eps_r: 6.0", "eps_r: 0.5"));
    assert!(
        e.starts_with("bad.yaml:5:") && e.contains("world.layers.0.eps_r: must be >= 1"),
        "{e}"
    );
    let e = parse_err(&GOOD.replace("speed_mps: 0.5", "speed_mps: -1"));
    assert!(
        e.starts_with("bad.yaml:9:") && e.contains("runs.0.trajectory.speed_mps"),
        "{e}"
    );
    let e = parse_err(&GOOD.replace("speed_mps: 0.5", "speed_mps: .nan"));
    assert!(e.contains("runs.0.trajectory.speed_mps"), "{e}");
    let contact = |c: &str| GOOD.replace("  - name: a\n", &format!("  - name: a\n    ground_contact: {c}\n"));
    assert!(
        Scenario::parse(
            &contact("{ ringing_sigma: 0.5, correlation_s: 1.0 }"),
            Path::new("good.yaml")
        )
        .is_ok()
    );
    let e = parse_err(&contact("{ ringing_sigma: -0.5, correlation_s: 1.0 }"));
    assert!(
        e.starts_with("bad.yaml:9:") && e.contains("runs.0.ground_contact.ringing_sigma"),
        "{e}"
    );
    let e = parse_err(&contact("{ ringing_sigma: 0.5, correlation_s: 0 }"));
    assert!(e.contains("runs.0.ground_contact.correlation_s"), "{e}");
    let e = parse_err(&contact("{ ringing_sigma: 0.5 }"));
    assert!(e.starts_with("bad.yaml:9:") && e.contains("correlation_s"), "{e}");
    let e = parse_err(&GOOD.replace("kind: long_drive", "kind: teleport"));
    assert!(e.starts_with("bad.yaml:9:") && e.contains("teleport"), "{e}");
    let e = parse_err("name: [unclosed");
    assert!(e.starts_with("bad.yaml:"), "{e}");
    let missing = Scenario::load(Path::new("/nonexistent/scenario.yaml")).expect_err("no file");
    assert!(matches!(missing, SimError::Read { .. }) && missing.to_string().contains("/nonexistent/scenario.yaml"));
    let s = Scenario::parse(GOOD, Path::new("good.yaml")).expect("good");
    let e = s.run(Some("b")).expect_err("no run b").to_string();
    assert!(e.contains("`b`") && e.contains("a"), "{e}");
}

#[test]
fn checked_in_schema_matches_the_code() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenario.schema.json");
    let fresh = serde_json::to_string_pretty(&Scenario::json_schema()).expect("schema") + "\n";
    if std::env::var_os("GPRFLOW_UPDATE_SCHEMA").is_some() {
        std::fs::write(&path, &fresh).expect("write schema");
    }
    let checked_in = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        checked_in == fresh,
        "tools/sim/scenario.schema.json is stale: GPRFLOW_UPDATE_SCHEMA=1 cargo test -p gprflow-sim --test scenarios"
    );
}

#[test]
fn scenario_reference_matches_the_code() {
    let path = scenarios_dir().join("README.md");
    let fresh = gprflow_sim::reference::reference_markdown();
    if std::env::var_os("GPRFLOW_UPDATE_SCHEMA").is_some() {
        std::fs::write(&path, &fresh).expect("write reference");
    }
    let checked_in = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        checked_in == fresh,
        "tools/sim/scenarios/README.md is stale: GPRFLOW_UPDATE_SCHEMA=1 cargo test -p gprflow-sim --test scenarios"
    );
}

#[test]
fn cmu_gpr_layout_has_the_dataset_columns_and_every_message() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = Scenario::parse(GOOD, Path::new("good.yaml")).expect("good");
    let folder = dir.path().join("seq");
    let opts = SimOptions {
        output: dir.path().join("seq.mcap"),
        cmu_gpr: Some(folder.clone()),
        ..SimOptions::default()
    };
    let summary = simulate(&scenario, &opts, &mut |_| {}).expect("simulate");
    for (file, columns, topic) in [
        ("gpr_meas.csv", 202, "gpr/trace"),
        ("imu_meas.csv", 11, "imu/data"),
        ("we_odom_meas.csv", 2, "wheel/odometry"),
        ("ts_meas.csv", 4, "truth/pose"),
    ] {
        let text = std::fs::read_to_string(folder.join(file)).expect(file);
        let mut lines = text.lines();
        let header = lines.next().expect("header row");
        assert_eq!(header.split(',').count(), columns, "{file} header: {header}");
        assert!(header.starts_with("t,"), "{file}");
        let rows: Vec<&str> = lines.collect();
        assert_eq!(rows.len() as u64, summary.messages[topic], "{file} rows");
        for row in &rows {
            assert_eq!(row.split(',').count(), columns, "{file}: {row}");
        }
        // stamps in seconds, increasing
        let t: Vec<f64> = rows
            .iter()
            .map(|r| r.split(',').next().and_then(|v| v.parse().ok()).expect("t"))
            .collect();
        assert!(t.windows(2).all(|w| w[1] > w[0]), "{file}: stamps must increase");
        assert!((t[0] - 1.6e9).abs() < 1.0, "{file}: first stamp {}", t[0]);
    }
}

#[test]
fn a_repeat_draws_other_sensor_noise_reproducibly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = Scenario::parse(GOOD, Path::new("good.yaml")).expect("good");
    let imu = |name: &str, repeat: u32| {
        let folder = dir.path().join(name);
        let opts = SimOptions {
            output: dir.path().join(format!("{name}.mcap")),
            cmu_gpr: Some(folder.clone()),
            repeat,
            ..SimOptions::default()
        };
        simulate(&scenario, &opts, &mut |_| {}).expect("simulate");
        std::fs::read_to_string(folder.join("imu_meas.csv")).expect("imu_meas.csv")
    };
    let (own, first, again) = (imu("own", 0), imu("first", 1), imu("again", 1));
    assert_eq!(first, again, "a repeat is reproducible");
    assert_ne!(own, first, "a repeat draws other noise");
    // the same samples at the same stamps
    let stamps = |text: &str| {
        text.lines()
            .map(|l| l.split(',').next().map(str::to_owned))
            .collect::<Vec<_>>()
    };
    assert_eq!(stamps(&own), stamps(&first));
}
