//! The command line's habits: every `--help` example runs as written, the output format
//! follows the file extension, shell completions.

use std::path::Path;
use std::process::Command;

use crate::common::{GPRFLOW, repo};
use crate::{gprflow, stderr};

/// Subcommands whose examples need what this test cannot give: `stage` runs one node of a
/// launcher's run (its spec file), `lgpr-eval` evaluates LGPR runs that take minutes to make.
const NOT_RUN: [&str; 2] = ["stage", "lgpr-eval"];

/// The subcommands `gprflow help` lists (and `bench`'s own).
fn subcommands() -> Vec<String> {
    let help = gprflow(&["help"]);
    let text = String::from_utf8_lossy(&help.stdout).into_owned();
    let mut names: Vec<String> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter(|l| l.starts_with("  ") && !l.starts_with("   "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_owned))
        .filter(|n| n != "help")
        .collect();
    if let Some(at) = names.iter().position(|n| n == "bench") {
        names[at] = "bench estimate".to_owned();
    }
    names
}

/// The example command lines of `gprflow help NAME`.
fn examples(name: &str) -> Vec<String> {
    let mut args = vec!["help"];
    args.extend(name.split(' '));
    let help = gprflow(&args);
    assert!(help.status.success(), "{}", stderr(&help));
    String::from_utf8_lossy(&help.stdout)
        .lines()
        .filter_map(|l| l.strip_prefix("  gprflow "))
        .map(|l| format!("gprflow {l}"))
        .collect()
}

/// A scratch copy of the repository's inputs (links), with an empty `out/`.
fn scratch(dir: &Path) {
    for entry in std::fs::read_dir(repo()).expect("repo") {
        let entry = entry.expect("entry");
        let name = entry.file_name();
        if name == "out" || name == "target" || name == ".git" {
            continue;
        }
        std::os::unix::fs::symlink(entry.path().canonicalize().expect("path"), dir.join(&name)).expect("link");
    }
    std::fs::create_dir(dir.join("out")).expect("out");
}

#[test]
fn every_help_example_runs_as_written() {
    let names = subcommands();
    assert!(names.len() > 15, "{names:?}");
    let dir = tempfile::tempdir().expect("tempdir");
    scratch(dir.path());
    let bin = Path::new(GPRFLOW)
        .parent()
        .expect("bin dir")
        .canonicalize()
        .expect("bin dir");
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap_or_default());
    let mut ran = 0;
    for name in &names {
        let lines = examples(name);
        assert!(!lines.is_empty(), "`gprflow help {name}` has no example");
        if NOT_RUN.contains(&name.as_str()) {
            continue;
        }
        for line in lines {
            let o = Command::new("bash")
                .args(["-c", &line])
                .current_dir(dir.path())
                .env("PATH", &path)
                .output()
                .expect("bash runs");
            assert!(
                o.status.success(),
                "`{line}` (from `gprflow help {name}`) failed: {}\n{}",
                o.status,
                stderr(&o)
            );
            ran += 1;
        }
    }
    assert!(ran > 25, "{ran} examples ran");
    // what some of them made
    for made in [
        "out/dzt.mcap",
        "out/truth.tum",
        "out/localize.png",
        "out/localize-registration.png",
    ] {
        assert!(dir.path().join(made).is_file(), "{made}");
    }
    let completions = std::fs::read_to_string(dir.path().join("out/gprflow.bash")).expect("completions");
    assert!(
        completions.contains("gprflow__subcmd__radargram") && completions.contains("--velocity"),
        "bash completions name the subcommands"
    );
}

#[test]
fn convert_takes_the_format_from_the_extension_or_says_what_it_needs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("line.dat");
    let o = gprflow(&[
        "convert",
        "recordings/real-gpr/GSSI_FILE____032.DZT",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let err = stderr(&o);
    assert!(
        err.contains("line.dat: cannot tell the output format") && err.contains("--to mcap"),
        "{err}"
    );
    let o = gprflow(&[
        "convert",
        "recordings/real-gpr/GSSI_FILE____032.DZT",
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let tum = dir.path().join("truth.txt");
    let o = gprflow(&[
        "convert",
        crate::common::BASEMENT,
        "--topic",
        "/truth/pose",
        "-o",
        tum.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let first = std::fs::read_to_string(&tum).expect("tum");
    assert_eq!(
        first.lines().next().map(|l| l.split_whitespace().count()),
        Some(8),
        "TUM: t x y z qx qy qz qw"
    );
}
