//! Launching graphs: a run is deterministic and replays identically, a user's own
//! executable stands in for a built-in stage, graph files validate as declared, bad input
//! gets clear errors.

use std::path::Path;

use crate::common::{GPRFLOW, gprflow, repo, stderr};
use crate::{payloads, record_toy};

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
