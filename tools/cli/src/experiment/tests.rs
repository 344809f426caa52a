use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::file::{ExperimentFile, Sequences, Table};
use super::plan::{Choices, plan, sets_folder};
use super::tables::{EvalResult, RegistrationResult, Rmse, SequenceSet, WorldResults, render, replace_between_markers};

/// Differences allowed between a value computed here and the same by hand.
const TOLERANCE: f64 = 1e-12;

fn shipped(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tools/experiments")
        .join(name)
}

#[test]
fn shipped_files_parse() {
    let tables = ExperimentFile::load(&shipped("tables.yaml")).expect("tables.yaml");
    let names: Vec<&str> = tables.worlds.iter().map(|w| w.name.as_str()).collect();
    assert_eq!(names, ["basement", "factory_floor", "parking_garage"]);
    assert_eq!(tables.repeats, 8);
    assert_eq!(tables.sequences, Sequences::RunAndRepeats);
    assert_eq!(tables.variants["by_hand"].run, "by_hand");
    assert_eq!(
        tables.variants["by_hand"].write.as_ref().map(|w| w.marker.as_str()),
        Some("tables-by-hand")
    );
    let nonlinear = tables.model("nonlinear").expect("nonlinear model");
    assert_eq!(nonlinear.set["method"], "learned");
    assert!(nonlinear.set["head"].ends_with("nonlinear.json"));
    assert_eq!(tables.write.as_ref().map(|w| w.marker.as_str()), Some("tables"));
    assert!(matches!(&tables.tables[0], Table::Registration { models, .. } if models.len() == 5));

    let repeats = ExperimentFile::load(&shipped("repeats.yaml")).expect("repeats.yaml");
    assert_eq!(repeats.repeats, 4);
    assert_eq!(repeats.sequences, Sequences::Repeats);
    assert!(repeats.write.is_none());
}

const SMALL: &str = "\
out: out/x
repeats: 1
worlds:
  - { name: w, scenario: s.yaml, run: r }
models:
  - { name: odometry, graph: odometry.yaml }
  - { name: learned, graph: localize.yaml, set: { method: learned } }
  - { name: zeroth, graph: localize.yaml, set: { method: zeroth } }
tables:
  - { kind: registration, models: [learned, zeroth] }
  - { kind: ate, models: [odometry, learned] }
";

fn parse(text: &str) -> Result<ExperimentFile, super::file::FileError> {
    ExperimentFile::parse(text, Path::new("exp.yaml"))
}

#[test]
fn an_unknown_world_field_names_file_line_and_key() {
    let text = SMALL.replace("run: r }", "run: r, colour: red }");
    let e = parse(&text).expect_err("unknown field");
    assert_eq!(e.at.file, Path::new("exp.yaml"));
    assert_eq!(e.at.position.map(|p| p.line), Some(4));
    assert!(e.at.key_path.starts_with("worlds.0"), "{e}");
    assert!(e.message.contains("colour"), "{e}");
    assert!(e.to_string().starts_with("exp.yaml:4:"), "{e}");
}

#[test]
fn a_table_naming_an_unknown_model_names_the_key() {
    let e = parse(&SMALL.replace("[odometry, learned]", "[odometry, leanred]")).expect_err("unknown model");
    assert_eq!(e.at.key_path, "tables.1.models.1");
    assert_eq!(e.at.position.map(|p| p.line), Some(11));
    assert!(e.message.contains("no model `leanred`"), "{e}");
    let e = parse(&SMALL.replace("repeats: 1", "repeats: 1\nsequences: repeats")).expect_err("registration");
    assert_eq!(e.at.key_path, "tables.0.kind");
    let e = parse(&SMALL.replace("{ method: zeroth }", "{ method: zeroth, recording: a.mcap }")).expect_err("rec");
    assert_eq!(e.at.key_path, "models.2.set.recording");
    let e = parse(&SMALL.replace("kind: ate", "kind: ates")).expect_err("unknown kind");
    assert!(e.at.key_path.starts_with("tables.1"), "{e}");
}

fn declared() -> BTreeMap<PathBuf, BTreeSet<String>> {
    let vars = |v: &[&str]| v.iter().map(|s| (*s).to_owned()).collect();
    BTreeMap::from([
        (PathBuf::from("odometry.yaml"), vars(&["recording", "wheel_scale"])),
        (
            PathBuf::from("localize.yaml"),
            vars(&["recording", "method", "wheel_scale", "stamps"]),
        ),
    ])
}

#[test]
fn the_plan_runs_what_the_tables_need_and_sets_go_where_declared() {
    let file = parse(SMALL).expect("small");
    let sets = vec![
        ("stamps".to_owned(), "overlap".to_owned()),
        ("wheel_scale".to_owned(), "1".to_owned()),
    ];
    let choices = Choices {
        sets: sets.clone(),
        ..Choices::default()
    };
    let p = plan(&file, &choices, &declared()).expect("plan");
    assert_eq!(p.recordings, Path::new("out/x"));
    assert_eq!(p.runs, Path::new("out/x-stamps=overlap-wheel_scale=1"));
    assert!(p.write.is_none());
    let runs: Vec<(String, String)> = p
        .runs()
        .map(|(s, r)| (s.label.clone(), r.base.display().to_string()))
        .collect();
    let folder = "out/x-stamps=overlap-wheel_scale=1";
    let want = [
        ("w", format!("{folder}/w-odometry")),
        ("w", format!("{folder}/w-learned")),
        ("w", format!("{folder}/w-zeroth")),
        ("w repeat 1", format!("{folder}/w-1-odometry")),
        ("w repeat 1", format!("{folder}/w-1-learned")),
    ];
    assert_eq!(runs, want.map(|(l, b)| (l.to_owned(), b)));
    let w = &p.worlds[0];
    assert_eq!(w.sequences[0].recording, Path::new("out/x/w-r.mcap"));
    assert_eq!(w.sequences[1].recording, Path::new("out/x/w-r-1.mcap"));
    assert!(w.sequences[0].runs[1].keep_recording && !w.sequences[1].runs[1].keep_recording);
    // odometry gets only the variable its graph declares; learned its own, then both
    assert_eq!(w.sequences[0].runs[0].sets, [sets[1].clone()]);
    let learned = &w.sequences[0].runs[1];
    assert_eq!(learned.sets[0], ("method".to_owned(), "learned".to_owned()));
    assert_eq!(learned.sets[1..], sets[..]);
    let args: Vec<String> = learned
        .launch_args(Path::new("out/x/w-r.mcap"))
        .iter()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        args.join(" "),
        format!(
            "launch localize.yaml --set recording=out/x/w-r.mcap --set method=learned --set stamps=overlap --set wheel_scale=1 --record {folder}/w-learned.mcap"
        )
    );

    let undeclared = Choices {
        sets: vec![("nope".to_owned(), "1".to_owned())],
        ..Choices::default()
    };
    let e = plan(&file, &undeclared, &declared()).expect_err("undeclared");
    assert!(e.to_string().contains("no model's graph declares `nope`"), "{e}");
    let e = plan(
        &file,
        &Choices {
            variant: Some("by_hand".into()),
            ..Choices::default()
        },
        &declared(),
    )
    .expect_err("no variants");
    assert!(e.to_string().contains("no variant `by_hand`"), "{e}");
}

#[test]
fn sets_folder_keeps_only_plain_characters() {
    let sets = [("head".to_owned(), "a/b c.json".to_owned())];
    assert_eq!(
        sets_folder(Path::new("out/t"), &sets),
        Path::new("out/t-head=a_b_c.json")
    );
    assert_eq!(sets_folder(Path::new("out/t"), &[]), Path::new("out/t"));
}

fn result(ate: f64, registration: Option<(f64, usize)>) -> EvalResult {
    EvalResult {
        ate: Some(Rmse { rmse: ate, count: 100 }),
        registration: registration.map(|(rmse, count)| RegistrationResult {
            along_track: Rmse { rmse, count },
        }),
    }
}

/// Two worlds, three sequences each; results made by hand.
fn worlds() -> Vec<WorldResults> {
    let sequence = |label: &str, entries: &[(&str, EvalResult)]| {
        (
            label.to_owned(),
            entries.iter().map(|(m, r)| ((*m).to_owned(), r.clone())).collect(),
        )
    };
    vec![
        WorldResults {
            name: "a".into(),
            sequences: vec![
                sequence(
                    "a",
                    &[("learned", result(0.1, Some((0.01, 4)))), ("oracle", result(0.1, None))],
                ),
                sequence(
                    "a repeat 1",
                    &[("learned", result(0.2, None)), ("oracle", result(0.1, None))],
                ),
                sequence(
                    "a repeat 2",
                    &[("learned", result(0.3, None)), ("oracle", result(0.5, None))],
                ),
            ],
        },
        WorldResults {
            name: "b".into(),
            sequences: vec![
                sequence(
                    "b",
                    &[
                        ("learned", result(0.5, Some((0.02, 1)))),
                        ("oracle", result(0.25, None)),
                    ],
                ),
                sequence(
                    "b repeat 1",
                    &[("learned", result(0.5, None)), ("oracle", result(0.5, None))],
                ),
                sequence(
                    "b repeat 2",
                    &[("learned", result(0.5, None)), ("oracle", result(0.5, None))],
                ),
            ],
        },
    ]
}

fn lines(text: &str) -> Vec<&str> {
    text.lines().collect()
}

#[test]
fn the_registration_table_combines_worlds_by_their_counts() {
    let table = Table::Registration {
        models: vec!["learned".into(), "oracle".into()],
        labels: BTreeMap::from([("learned".to_owned(), "learned linear".to_owned())]),
    };
    let set = SequenceSet {
        sequences: Sequences::RunAndRepeats,
        repeats: 2,
    };
    let text = render(&[table], set, &worlds()).expect("render");
    // combined: sqrt((0.01^2 * 4 + 0.02^2 * 1) / 5) = sqrt(0.00016) = 0.012649 m
    let combined_cm = 100.0 * (0.000_16_f64).sqrt();
    assert!((combined_cm - 1.264_911).abs() < 1e-6);
    assert_eq!(
        lines(&text)[2..],
        [
            "| model | a | b | combined |",
            "|---|---|---|---|",
            "| learned linear | 1.00 (n=4) | 2.00 (n=1) | 1.26 |",
            "| oracle | - | - | - |",
        ]
    );
}

#[test]
fn the_ate_table_gives_mean_min_max_and_the_ratio_of_means() {
    let table = |form| Table::Ate {
        models: vec!["learned".into(), "oracle".into()],
        ratio: Some(super::file::Ratio {
            model: "learned".into(),
            reference: "oracle".into(),
            within_percent: 15,
            form,
        }),
    };
    let set = SequenceSet {
        sequences: Sequences::RunAndRepeats,
        repeats: 2,
    };
    let text = render(&[table(super::file::RatioForm::OfMeans)], set, &worlds()).expect("render");
    // a: learned 0.1, 0.2, 0.3 (mean 0.2), oracle 0.1, 0.1, 0.5 (mean 0.2333): ratio 0.857;
    // within 15 %: 0.1 <= 0.115, 0.2 > 0.115, 0.3 <= 0.575: 2 of 3.
    // b: learned 0.5 x3 (mean 0.5), oracle 0.25, 0.5, 0.5 (mean 0.41667): ratio 1.20; within:
    // 0.5 > 0.2875, then 0.5 <= 0.575 twice: 2 of 3.
    assert!((0.5_f64 / ((0.25 + 0.5 + 0.5) / 3.0) - 1.2).abs() < TOLERANCE);
    assert_eq!(
        lines(&text),
        [
            "ATE (RMSE of the final trajectory against the truth, m, no alignment) over 3 sequences per world, the world's run and its repeats 1-2 with fresh sensor noise: mean [min, max]:",
            "",
            "| run | a | b |",
            "|---|---|---|",
            "| learned | 0.200 [0.100, 0.300] | 0.500 [0.500, 0.500] |",
            "| oracle | 0.233 [0.100, 0.500] | 0.417 [0.250, 0.500] |",
            "| learned / oracle (of the means; per sequence) | 0.86; within 15 % in 2 of 3 | 1.20; within 15 % in 2 of 3 |",
        ]
    );

    // The repeats alone: a's per-sequence ratios 2.0, 0.6 (mean 1.3), b's 1, 1.
    let repeats_only: Vec<WorldResults> = worlds()
        .into_iter()
        .map(|mut w| {
            w.sequences.remove(0);
            w
        })
        .collect();
    let set = SequenceSet {
        sequences: Sequences::Repeats,
        repeats: 2,
    };
    let text = render(&[table(super::file::RatioForm::OfRatios)], set, &repeats_only).expect("render");
    assert_eq!(
        lines(&text),
        [
            "ATE over 2 repeats (fresh sensor noise, same world and path; m, no alignment): mean [min, max]",
            "",
            "| run | a | b |",
            "|---|---|---|",
            "| learned | 0.250 [0.200, 0.300] | 0.500 [0.500, 0.500] |",
            "| oracle | 0.300 [0.100, 0.500] | 0.500 [0.500, 0.500] |",
            "| learned / oracle | 1.30 [0.60, 2.00], within 15 %: 1 of 2 | 1.00 [1.00, 1.00], within 15 %: 2 of 2 |",
        ]
    );

    // No repeats: each world's run alone, one value per cell.
    let runs_only: Vec<WorldResults> = worlds()
        .into_iter()
        .map(|mut w| {
            w.sequences.truncate(1);
            w
        })
        .collect();
    let set = SequenceSet {
        sequences: Sequences::RunAndRepeats,
        repeats: 0,
    };
    let text = render(&[table(super::file::RatioForm::OfMeans)], set, &runs_only).expect("render");
    assert_eq!(
        lines(&text)[0],
        "ATE (RMSE of the final trajectory against the truth, m, no alignment) each world's run:"
    );
    assert_eq!(lines(&text)[4], "| learned | 0.100 | 0.500 |");
    assert_eq!(
        lines(&text)[6],
        "| learned / oracle (of the means; per sequence) | 1.00; within 15 % in 1 of 1 | 2.00; within 15 % in 0 of 1 |"
    );
}

#[test]
fn a_missing_result_is_an_error_naming_the_run() {
    let mut w = worlds();
    w[1].sequences[2].1.remove("oracle");
    let table = Table::Ate {
        models: vec!["oracle".into()],
        ratio: None,
    };
    let set = SequenceSet {
        sequences: Sequences::RunAndRepeats,
        repeats: 2,
    };
    let e = render(&[table], set, &w).expect_err("missing");
    assert!(e.to_string().contains("b repeat 2 oracle"), "{e}");
}

#[test]
fn eval_json_reads_with_and_without_registrations() {
    let with: EvalResult = serde_json::from_str(
        r#"{"estimate": "x", "ate": {"rmse": 0.5, "mean": 0.4, "count": 7},
            "registration": {"topic": "/r", "along_track": {"rmse": 0.01, "count": 3}, "translation": {}}}"#,
    )
    .expect("with");
    assert_eq!(with, result_with_count(0.5, 7, Some((0.01, 3))));
    let without: EvalResult =
        serde_json::from_str(r#"{"ate": {"rmse": 0.5, "count": 7}, "registration": null}"#).expect("without");
    assert_eq!(without, result_with_count(0.5, 7, None));
}

fn result_with_count(ate: f64, count: usize, registration: Option<(f64, usize)>) -> EvalResult {
    EvalResult {
        ate: Some(Rmse { rmse: ate, count }),
        ..result(0.0, registration)
    }
}

#[test]
fn markers_are_replaced_and_a_missing_one_is_an_error() {
    let doc = "intro\n<!-- t:begin -->\nold\nlines\n<!-- t:end -->\nafter\n";
    assert_eq!(
        replace_between_markers(doc, "t", "new").expect("replace"),
        "intro\n<!-- t:begin -->\nnew\n<!-- t:end -->\nafter\n"
    );
    // another marker that starts with the same name is left alone
    let two = format!("{doc}<!-- t-x:begin -->\nkeep\n<!-- t-x:end -->\n");
    assert!(
        replace_between_markers(&two, "t", "new")
            .expect("replace")
            .ends_with("<!-- t-x:begin -->\nkeep\n<!-- t-x:end -->\n")
    );
    let e = replace_between_markers(doc, "u", "new").expect_err("no marker");
    assert!(e.to_string().contains("<!-- u:begin -->"), "{e}");
    let e = replace_between_markers("<!-- t:begin -->\nold\n", "t", "new").expect_err("no end");
    assert!(e.to_string().contains("<!-- t:end -->"), "{e}");
    let e = replace_between_markers("<!-- t:end -->\n<!-- t:begin -->\n", "t", "new").expect_err("end first");
    assert!(e.to_string().contains("<!-- t:end -->"), "{e}");
}
