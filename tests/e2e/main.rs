//! End-to-end tests: real graphs launched as real processes over iceoryx2, recorded to MCAP,
//! replayed, killed mid-run, and read back by a peer MCAP reader. One test binary, one module
//! per concern; the helpers several modules use are here, those shared with
//! `tests/distributed.rs` in `tests/common`.

// Tests spawn short-lived helper threads; names would add nothing.
#![allow(clippy::disallowed_methods)]

#[path = "../common/mod.rs"]
mod common;

mod bus;
mod eval;
mod foxglove;
mod golden;
mod habits;
mod ingest;
mod launch;
mod lgpr;
mod lines;
mod localisation;
mod peer;
mod processing;
mod shutdown;
mod sim;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use gprflow::record::Recording;

use common::{gprflow, peer_venv, repo, stderr};

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

/// Runs the Python peer check on `rec`, asserting it decodes `expected` messages alike.
fn peer_check(rec: &Path, expected: &str) {
    let python = peer_venv("python");
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

fn decode_all<'a, M: gprflow::msg::CdrDecode<'a>>(msgs: &'a [Vec<u8>]) -> Vec<M> {
    msgs.iter()
        .map(|p| gprflow::msg::decode::<M>(p).expect("decodes"))
        .collect()
}
