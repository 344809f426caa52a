//! SLAM with line features: the `lines` stage finds the buried pipe and its factors beat
//! odometry.

use crate::common::{gprflow, repo, stderr};
use crate::sim::pipe_sample;
use crate::{eval_json, launch_recorded};

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
        r#"record: { topics: ["estimate/*", "lines/*", "viz/*"] }"#,
        r#"record: { topics: ["estimate/*", "lines/*", "viz/*", "dsp/*", "filter/*"] }"#,
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
    let (with_lines, without) = (eval_json(&slam, sample), eval_json(&odom, sample));
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

/// A pipe crossed about a metre before a row's end: the drive turns before it has left the
/// apex behind, and the `lines` stage drops it instead of measuring it from the first submap
/// after the U-turn (about 6 m off along the new heading, and a line made from it turned the
/// whole map by more than a radian). On the unseen three-pipe field every observation sent
/// is of its true pipe, the lines come out within degrees and the trajectory within 0.5 m
/// (odometry alone 4.5 m).
#[test]
fn a_turn_cuts_the_apex_it_would_mismeasure() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = crate::sim::sim_input("unseen_pipes_parallel.yaml", "lawnmower", "300");
    let rec = rec.to_str().expect("utf8");
    let (_, o) = launch_recorded(dir.path(), "graphs/slam.yaml", &[format!("recording={rec}")]);
    assert!(stderr(&o).contains("cut_by_turns=1"), "{}", stderr(&o));
    let v = eval_json(&dir.path().join("run.mcap"), rec);
    let obs = &v["line_observations"];
    assert_eq!(obs["observations"], obs["matched"], "{obs}");
    let lines = &v["lines"];
    assert_eq!(lines["matched"], 3, "{lines}");
    assert!(lines["theta_rmse_rad"].as_f64().expect("theta") < 0.05, "{lines}");
    let ate = v["ate"]["rmse"].as_f64().expect("ate");
    assert!(ate < 0.5, "ATE {ate} m");
}
