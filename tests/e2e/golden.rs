//! `gprflow diff`, and the shipped graphs rerun against their golden recordings
//! (`recordings/golden`, remade by tools/scripts/update-goldens.sh).

use crate::common::{gprflow, repo, stderr};
use crate::sim::sim_input;

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

/// The `--set`s of `graph`'s golden run as `recordings/golden/inputs.txt` lists it
/// (`tools/scripts/update-goldens.sh` reads the same list), its simulator input made on demand.
fn golden_sets(graph: &str) -> Vec<String> {
    let list = repo().join("recordings/golden/inputs.txt");
    let text = std::fs::read_to_string(&list).expect("recordings/golden/inputs.txt");
    let row = text
        .lines()
        .map(|line| line.split_whitespace().collect::<Vec<_>>())
        .find(|fields| fields.first() == Some(&graph))
        .unwrap_or_else(|| panic!("{graph} is not listed in {}", list.display()));
    let mut sets = Vec::new();
    if row[1] != "-" {
        let [scenario, run, seconds] = row[1].split(':').collect::<Vec<_>>()[..] else {
            panic!("{graph}: input `{}` is not SCENARIO:RUN:SECONDS", row[1]);
        };
        sets.push(format!("recording={}", sim_input(scenario, run, seconds).display()));
    }
    sets.extend(row[2..].iter().map(|s| (*s).to_owned()));
    sets
}

/// The goldens each test reruns (all of recordings/golden/inputs.txt between them).
const OUTPUTS: [&str; 4] = ["toy", "replay-toy", "odometry", "slam"];
const LOCALISATION: &str = "localize";
const SUBMAPS_AND_SWEEPS: [&str; 2] = ["submaps", "lgpr-sweeps"];

#[test]
fn golden_outputs_still_match() {
    for graph in OUTPUTS {
        assert_reproduces_golden(graph, &golden_sets(graph));
    }
}

#[test]
fn golden_localisation_still_matches() {
    assert_reproduces_golden(LOCALISATION, &golden_sets(LOCALISATION));
}

#[test]
fn golden_submaps_and_sweeps_still_match() {
    // short inputs and sparse submaps keep these goldens small (floats compress poorly)
    for graph in SUBMAPS_AND_SWEEPS {
        assert_reproduces_golden(graph, &golden_sets(graph));
    }
}

#[test]
fn every_golden_is_listed_and_tested() {
    let text = std::fs::read_to_string(repo().join("recordings/golden/inputs.txt")).expect("list");
    let mut listed: Vec<String> = text
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .filter_map(|l| l.split_whitespace().next().map(str::to_owned))
        .collect();
    let mut goldens: Vec<String> = std::fs::read_dir(repo().join("recordings/golden"))
        .expect("goldens")
        .filter_map(|e| e.ok()?.file_name().to_str()?.strip_suffix(".mcap").map(str::to_owned))
        .collect();
    listed.sort();
    goldens.sort();
    assert_eq!(listed, goldens, "recordings/golden/*.mcap and inputs.txt disagree");
    let tested = [
        "toy",
        "replay-toy",
        "odometry",
        "slam",
        "localize",
        "submaps",
        "lgpr-sweeps",
    ];
    assert!(
        listed.iter().all(|g| tested.contains(&g.as_str())),
        "a listed golden no test reruns"
    );
}
