//! `gprflow eval`: its trajectory statistics agree with evo's on the same TUM files, and it
//! draws plots and radargrams.

use std::path::Path;
use std::process::Command;

use crate::common::{gprflow, peer_venv, repo, stderr};

/// Largest difference accepted between our statistics and evo's on the same TUM files.
const EVO_TOLERANCE_M: f64 = 1e-6;

fn evo_stats(tool: &str, args: &[&str], dir: &Path) -> serde_json::Value {
    let zip = dir.join(format!("{tool}-{}.zip", args.len()));
    let _ = std::fs::remove_file(&zip);
    let o = Command::new(peer_venv(tool))
        .current_dir(dir)
        .args(args)
        .arg("--save_results")
        .arg(&zip)
        .env("MPLBACKEND", "Agg")
        .output()
        .expect("evo runs (tools/peer/setup-venv.sh installs it)");
    assert!(o.status.success(), "{tool} failed: {}", stderr(&o));
    let unzip = Command::new(peer_venv("python"))
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
    // the radargram: every trace a column, drawn at the picture's fixed size
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
    assert_eq!((width, height), (1400, 820), "the same size whatever the trace count");
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(said.starts_with("501 columns of"), "50 traces/s for 10 s: {said}");
    // truth from a recording that has none: a clear error, exit 2
    let o = gprflow(&["eval", rec.to_str().expect("utf8"), "--truth", "recordings/toy.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("no ground truth on /truth/pose"), "{}", stderr(&o));
    // no estimate in the recording: a clear error, exit 2
    let o = gprflow(&["eval", "recordings/toy.mcap"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("recordings/toy.mcap"), "{}", stderr(&o));
}
