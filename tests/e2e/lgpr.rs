//! LGPR prior-map localisation end to end (seed 001 §2.2): a simulated highway mapping pass
//! through graphs/lgpr-map.yaml into a map store, a faster tracking pass at a lateral offset
//! through graphs/lgpr-track.yaml against it, measured by `gprflow lgpr-eval` (eq. 11); and
//! unusable sweeps dropped, counted and named while tracking goes on.

use std::path::Path;

use crate::common::{gprflow, stderr};

fn path(p: &Path) -> &str {
    p.to_str().expect("utf8")
}

/// Simulates `run` of the highway for `seconds` into `dir/NAME.mcap`.
fn sim(dir: &Path, run: &str, seconds: &str) -> std::path::PathBuf {
    let out = dir.join(format!("{run}.mcap"));
    let o = gprflow(&[
        "sim",
        "tools/sim/scenarios/highway.yaml",
        "-o",
        path(&out),
        "--run",
        run,
        "--duration",
        seconds,
    ]);
    assert!(o.status.success(), "sim {run}: {}", stderr(&o));
    out
}

/// `gprflow lgpr-eval RUN --baseline MAP_RECORDING EXTRA... --format json`: the run's row.
fn eval_row(run: &Path, baseline: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["lgpr-eval", path(run), "--baseline", path(baseline), "--format", "json"];
    args.extend_from_slice(extra);
    let e = gprflow(&args);
    assert!(e.status.success(), "{}", stderr(&e));
    let rows: serde_json::Value = serde_json::from_slice(&e.stdout).expect("json");
    rows[0].clone()
}

/// Builds the map of the first 50 s of the mapping pass (about 200 m) into `dir/map`.
fn build_map(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let map_rec = sim(dir, "map", "50");
    let map = dir.join("map");
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-map.yaml",
        "--set",
        &format!("recording={}", path(&map_rec)),
        "--set",
        &format!("map={}", path(&map)),
    ]);
    let log = stderr(&o);
    assert!(o.status.success(), "{log}");
    assert!(log.contains("lgpr_map: map written"), "{log}");
    // the store reads back, with a whole number of tiles
    let inspect = gprflow(&["inspect", path(&map)]);
    let text = String::from_utf8_lossy(&inspect.stdout).into_owned();
    assert!(inspect.status.success(), "{}", stderr(&inspect));
    assert!(
        text.contains("gprflow-lgpr-map version 1") && text.contains("MB/km"),
        "{text}"
    );
    (map_rec, map)
}

#[test]
fn a_tracking_pass_localises_against_the_mapping_pass_within_the_papers_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (map_rec, map) = build_map(dir.path());
    // up to 48 km/h, 0.3 m to the left of the mapping line, for 20 s from standstill: about
    // 180 m, inside the map
    let track_rec = sim(dir.path(), "track_48", "20");
    let fixes = dir.path().join("fixes.mcap");
    // the fusion graph: the tracker's map fixes and the estimator fusing them in one run
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-fuse.yaml",
        "--set",
        &format!("recording={}", path(&track_rec)),
        "--set",
        &format!("map={}", path(&map)),
        "--record",
        path(&fixes),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // `gprflow lgpr-eval` of the run against the mapping pass: its one row
    let eval = |extra: &[&str]| eval_row(&fixes, &map_rec, extra);
    let r = &eval(&[]);
    let cm = |v: &serde_json::Value| v.as_f64().expect("number") * 100.0;
    let (cross, along) = (cm(&r["lgpr"]["cross_m"]), cm(&r["lgpr"]["along_m"]));
    let (gps_cross, lock) = (cm(&r["gps"]["cross_m"]), r["locked_pct"].as_f64().expect("number"));
    // seed 001's targets: <= 4 cm cross-track, <= 6 cm along-track RMS, lock nearly always
    assert!(
        cross <= 4.0 && along <= 6.0,
        "LGPR RMS cross {cross:.1} cm, along {along:.1} cm: {r}"
    );
    assert!(lock >= 99.0, "locked {lock:.2} % of the distance: {r}");
    assert!(r["distance_m"].as_f64().expect("number") > 100.0, "{r}");
    // the GPS/INS alone is an order of magnitude worse
    assert!(gps_cross > 3.0 * cross, "GPS/INS cross {gps_cross:.1} cm: {r}");
    // the estimator's fusion of the locked fixes with the IMU, the wheel and the GPS/INS,
    // over the same span (from the first lock): better than the fixes alone
    let f = &eval(&["--topic", "/estimate/state"]);
    let (total, gps_total) = (cm(&f["lgpr"]["total_m"]), cm(&f["gps"]["total_m"]));
    let heuristic = cm(&r["lgpr"]["total_m"]);
    // every pose of an estimate counts as a fix: no lock share is made up for it
    assert!(f["locked_pct"].is_null(), "{f}");
    assert!(
        total < heuristic && gps_total > 5.0 * total,
        "fused RMS {total:.1} cm, the fixes alone {heuristic:.1} cm, GPS/INS {gps_total:.1} cm: {f}"
    );
}

#[test]
fn unusable_sweeps_are_dropped_counted_and_named_while_tracking_goes_on() {
    use gprflow::msg::{Sweep, decode, encode};
    use gprflow::record::{Recorder, Recording, RunMetadata};
    let dir = tempfile::tempdir().expect("tempdir");
    let (_, map) = build_map(dir.path());
    // processed sweeps of a short tracking pass, with the GPS/INS
    let track_rec = sim(dir.path(), "track_48", "5");
    let processed = dir.path().join("processed.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-sweeps.yaml",
        "--set",
        &format!("recording={}", path(&track_rec)),
        "--record",
        path(&processed),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // a recording of those sweeps with two spoilt: one with ten channels, one with a NaN
    let bad = dir.path().join("bad.mcap");
    let (mut sweeps, mut spoilt) = (0u64, 0u64);
    {
        let mut w = Recorder::create(&bad, &RunMetadata::this_build()).expect("create");
        let sweep_ch = w.add_topic("/lgpr/sweep", Sweep::ROS_NAME).expect("topic");
        let src = Recording::open(&processed).expect("open");
        let (_, stopped) = src.scan(|m| {
            if m.topic != "/lgpr/sweep" {
                return;
            }
            let mut s: Sweep = decode(m.data).expect("decodes");
            sweeps += 1;
            if sweeps == 300 {
                s.channel_count = 10;
                s.values.to_mut().truncate(10 * 369);
                spoilt += 1;
            } else if sweeps == 400 {
                s.values.to_mut()[5 * 369 + 17] = f32::NAN;
                spoilt += 1;
            }
            w.write(sweep_ch, u64::from(m.sequence), m.log_time as i64, &encode(&s))
                .expect("write");
        });
        assert_eq!(stopped, None);
        let gps_ch = w
            .add_topic("/gps/odometry", gprflow::msg::Odometry::ROS_NAME)
            .expect("topic");
        let sim = Recording::open(&track_rec).expect("open");
        sim.scan(|m| {
            if m.topic == "/gps/odometry" {
                w.write(gps_ch, u64::from(m.sequence), m.log_time as i64, m.data)
                    .expect("write");
            }
        });
        w.finish().expect("finish");
    }
    let fixes = dir.path().join("fixes.mcap");
    let o = gprflow(&[
        "launch",
        "tests/e2e/graphs/lgpr-track-processed.yaml",
        "--set",
        &format!("recording={}", path(&bad)),
        "--set",
        &format!("map={}", path(&map)),
        "--record",
        path(&fixes),
    ]);
    let log = stderr(&o);
    assert!(o.status.success(), "{log}");
    assert!(
        log.contains("10 channels") && log.contains("the first sweep had 11 channels"),
        "{log}"
    );
    assert!(log.contains("channel 5 sample 17 is NaN"), "{log}");
    assert!(!log.contains("panicked"), "{log}");
    let out = crate::payloads(&fixes);
    assert_eq!(out["/track/map_fix"].len() as u64, sweeps - spoilt, "{log}");
}

/// Tracks `recording` against `map` (graphs/lgpr-track.yaml): the recorded run and the share
/// of its map fixes that are locked.
fn track(dir: &Path, recording: &Path, map: &Path, name: &str) -> (std::path::PathBuf, f64) {
    let fixes = dir.join(format!("{name}.mcap"));
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-track.yaml",
        "--set",
        &format!("recording={}", path(recording)),
        "--set",
        &format!("map={}", path(map)),
        "--record",
        path(&fixes),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let all = crate::payloads(&fixes).remove("/track/map_fix").unwrap_or_default();
    let locked = all
        .iter()
        .filter(|p| gprflow::msg::decode::<gprflow::msg::MapFix>(p).expect("decodes").locked)
        .count();
    assert!(all.len() > 500, "{name}: {} fixes", all.len());
    (fixes, locked as f64 / all.len() as f64)
}

#[test]
fn a_second_lane_aligned_to_the_map_lets_a_pass_beside_the_first_lane_lock() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (map_rec, map) = build_map(dir.path());
    // the second mapping pass, 0.7 m to the left, tracked against the map and written at its
    // locked fixes into a store of its own
    let lane2_rec = sim(dir.path(), "map_lane2", "50");
    let lane2 = dir.path().join("lane2");
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-map-align.yaml",
        "--set",
        &format!("recording={}", path(&lane2_rec)),
        "--set",
        &format!("map={}", path(&map)),
        "--set",
        &format!("aligned={}", path(&lane2)),
    ]);
    let log = stderr(&o);
    assert!(o.status.success(), "{log}");
    let placed = log
        .lines()
        .find(|l| l.contains("placed by their locked map fixes"))
        .unwrap_or_else(|| panic!("no placement line: {log}"));
    let count = |key: &str| -> u64 {
        let at = placed
            .find(&format!("{key}="))
            .unwrap_or_else(|| panic!("{key}: {placed}"));
        placed[at + key.len() + 1..]
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{key}: {placed}"))
    };
    let (written, unlocked) = (count("placed"), count("unlocked"));
    // 50 s of sweeps at 126 Hz, 5 of the 11 channels over the map: all but the first 2-3 s
    // (standing still before the first lock) and a few near misses (correlation 0.89) lock
    let sweeps = written + unlocked;
    assert!(sweeps > 6000 && written * 10 > 9 * sweeps, "{placed}");
    // joined to a copy of the map: two passes
    let both = dir.path().join("both");
    let o = gprflow(&["lgpr-merge", path(&map), "--into", path(&both)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = gprflow(&["lgpr-merge", path(&lane2), "--into", path(&both)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = gprflow(&["lgpr-merge", path(&both), "--into", path(&both)]);
    assert!(!o.status.success() && stderr(&o).contains("cannot add a map to itself"));
    let inspect = gprflow(&["inspect", path(&both), "--json"]);
    assert!(inspect.status.success(), "{}", stderr(&inspect));
    let info: serde_json::Value = serde_json::from_slice(&inspect.stdout).expect("json");
    assert_eq!(info["passes"], 2, "{info}");
    assert!(info["damaged"].as_array().is_some_and(Vec::is_empty), "{info}");
    // a pass 1.3 m to the left on wetter soil: one channel over the single lane, which is too
    // few to acquire a lock; over the two lanes it locks, in the first lane's frame (its first
    // lock comes after about 13 s, 90 m; the 19 s simulated here end near the map's end)
    let offset_rec = sim(dir.path(), "track_97_offset", "19");
    let (_, one) = track(dir.path(), &offset_rec, &map, "one-lane");
    let (fixes, two) = track(dir.path(), &offset_rec, &both, "two-lanes");
    assert!(one == 0.0 && two > 0.2, "locked: one lane {one:.3}, two lanes {two:.3}");
    let r = &eval_row(&fixes, &map_rec, &["--max-offset-m", "2"]);
    let cm = |v: &serde_json::Value| v.as_f64().expect("number") * 100.0;
    let (cross, along) = (cm(&r["lgpr"]["cross_m"]), cm(&r["lgpr"]["along_m"]));
    assert!(
        cross <= 4.0 && along <= 6.0,
        "two lanes: cross {cross:.1} cm, along {along:.1} cm: {r}"
    );
}

#[test]
fn a_map_store_of_another_version_is_refused_by_name() {
    let dir = tempfile::tempdir().expect("tempdir");
    let map = dir.path().join("map");
    std::fs::create_dir_all(map.join("tiles")).expect("mkdir");
    std::fs::write(
        map.join("manifest.json"),
        r#"{"format": "gprflow-lgpr-map", "version": 2, "tile_m": 50.0, "samples": 369, "sample_interval_ns": 0.16}"#,
    )
    .expect("write");
    let o = gprflow(&["inspect", path(&map)]);
    let log = stderr(&o);
    assert!(!o.status.success());
    assert!(log.contains("manifest.json") && log.contains("version 2"), "{log}");
    let o = gprflow(&[
        "launch",
        "graphs/lgpr-track.yaml",
        "--set",
        &format!("map={}", path(&map)),
    ]);
    let log = stderr(&o);
    assert!(!o.status.success());
    assert!(log.contains("manifest.json") && log.contains("version 2"), "{log}");
}
