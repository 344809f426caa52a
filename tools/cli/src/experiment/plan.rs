//! What an experiment runs, where its files go: pure, from the file and the command line.

use std::collections::{BTreeMap, BTreeSet};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

use super::file::{ExperimentFile, RECORDING_VAR, Sequences, World, WriteTo};

/// The command line's choices over the file's.
#[derive(Debug, Clone, Default)]
pub struct Choices {
    /// A variant of the file's `variants`.
    pub variant: Option<String>,
    /// Repeats instead of the file's.
    pub repeats: Option<u32>,
    /// Graph variables for every model whose graph declares them.
    pub sets: Vec<(String, String)>,
    /// Folder instead of the file's (or the variant's).
    pub out: Option<PathBuf>,
}

/// The runs of an experiment, in order, and where everything goes.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Where the recordings go (shared by every `--set` folder).
    pub recordings: PathBuf,
    /// Where the runs' logs, recordings and eval results go: the recordings' folder, with
    /// the command line's `--set`s appended to its name.
    pub runs: PathBuf,
    /// Repeats per world.
    pub repeats: u32,
    /// Which sequences.
    pub sequences: Sequences,
    /// The worlds, in column order, each with its sequences.
    pub worlds: Vec<WorldPlan>,
    /// Where the tables go; `None` with `--set`s (their runs are not the documented ones).
    pub write: Option<WriteTo>,
}

/// One world's sequences.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldPlan {
    /// Its name.
    pub name: String,
    /// Its sequences, in order.
    pub sequences: Vec<SequencePlan>,
}

/// One sequence: a simulated recording and the runs on it.
#[derive(Debug, Clone, PartialEq)]
pub struct SequencePlan {
    /// 0: the world's run; k: its repeat k.
    pub repeat: u32,
    /// `basement` or `basement repeat 3`.
    pub label: String,
    /// Scenario file.
    pub scenario: PathBuf,
    /// Scenario run.
    pub run: String,
    /// The recording (simulated when it is not there).
    pub recording: PathBuf,
    /// The runs on it, in model order.
    pub runs: Vec<RunPlan>,
}

/// One model on one sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct RunPlan {
    /// The model's name.
    pub model: String,
    /// Its graph file.
    pub graph: PathBuf,
    /// Every graph variable but the recording: the model's, then the command line's.
    pub sets: Vec<(String, String)>,
    /// `BASE.mcap`, `BASE.log`, `BASE.json`.
    pub base: PathBuf,
    /// Whether the run's recording stays (the world's run's do; the repeats' are deleted
    /// once evaluated).
    pub keep_recording: bool,
}

impl RunPlan {
    /// The eval result.
    pub fn json(&self) -> PathBuf {
        with_suffix(&self.base, ".json")
    }

    /// The launch's output.
    pub fn log(&self) -> PathBuf {
        with_suffix(&self.base, ".log")
    }

    /// The run's recording.
    pub fn mcap(&self) -> PathBuf {
        with_suffix(&self.base, ".mcap")
    }

    /// `gprflow launch`'s arguments for this run on `recording`.
    pub fn launch_args(&self, recording: &Path) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec!["launch".into(), self.graph.clone().into()];
        let mut recording_set = OsString::from(format!("{RECORDING_VAR}="));
        recording_set.push(recording);
        args.extend(["--set".into(), recording_set]);
        for (key, value) in &self.sets {
            args.extend(["--set".into(), format!("{key}={value}").into()]);
        }
        args.extend(["--record".into(), self.mcap().into()]);
        args
    }

    /// `gprflow eval`'s arguments for this run against `recording`'s truth.
    pub fn eval_args(&self, recording: &Path) -> Vec<OsString> {
        vec![
            "eval".into(),
            self.mcap().into(),
            "--truth".into(),
            recording.into(),
            "--format".into(),
            "json".into(),
        ]
    }
}

impl SequencePlan {
    /// `gprflow sim`'s arguments that simulate this sequence into `output`.
    pub fn sim_args(&self, output: &Path) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec![
            "sim".into(),
            self.scenario.clone().into(),
            "-o".into(),
            output.into(),
            "--run".into(),
            self.run.clone().into(),
        ];
        if self.repeat > 0 {
            args.extend(["--repeat".into(), self.repeat.to_string().into()]);
        }
        args
    }
}

impl Plan {
    /// Every run, in order, with its sequence.
    pub fn runs(&self) -> impl Iterator<Item = (&SequencePlan, &RunPlan)> {
        self.worlds
            .iter()
            .flat_map(|w| w.sequences.iter())
            .flat_map(|s| s.runs.iter().map(move |r| (s, r)))
    }
}

/// The plan of `file` under `choices`; `declared` holds each model graph's variables.
///
/// # Errors
/// An unknown variant, a `--set` no model's graph declares, no sequences.
pub fn plan(file: &ExperimentFile, choices: &Choices, declared: &BTreeMap<PathBuf, BTreeSet<String>>) -> Result<Plan> {
    let (run_name, base, write) = match &choices.variant {
        None => (None, &file.out, file.write.clone()),
        Some(name) => match file.variants.get(name) {
            Some(v) => (Some(v.run.as_str()), &v.out, v.write.clone()),
            None => {
                let known: Vec<&str> = file.variants.keys().map(String::as_str).collect();
                bail!("no variant `{name}` (variants: {})", none_if_empty(&known));
            }
        },
    };
    let recordings = choices.out.clone().unwrap_or_else(|| base.clone());
    let runs_folder = sets_folder(&recordings, &choices.sets);
    for (key, _) in &choices.sets {
        if !file.models.iter().any(|m| declares(declared, &m.graph, key)) {
            bail!("--set {key}: no model's graph declares `{key}`");
        }
    }
    let repeats = choices.repeats.unwrap_or(file.repeats);
    if file.sequences == Sequences::Repeats && repeats == 0 {
        bail!("`sequences: repeats` needs at least one repeat");
    }
    let first = match file.sequences {
        Sequences::RunAndRepeats => 0,
        Sequences::Repeats => 1,
    };
    let on_run = file.needed_models(true);
    let on_repeat = file.needed_models(false);
    let layout = Layout {
        file,
        declared,
        sets: &choices.sets,
        recordings: &recordings,
        runs: &runs_folder,
    };
    let worlds = file
        .worlds
        .iter()
        .map(|world| {
            let run = run_name.unwrap_or(&world.run);
            let sequences = (first..=repeats)
                .map(|k| {
                    let needed = if k == 0 { &on_run } else { &on_repeat };
                    layout.sequence(world, run, k, needed)
                })
                .collect();
            WorldPlan {
                name: world.name.clone(),
                sequences,
            }
        })
        .collect();
    Ok(Plan {
        recordings,
        runs: runs_folder,
        repeats,
        sequences: file.sequences,
        worlds,
        write: if choices.sets.is_empty() { write } else { None },
    })
}

/// What every sequence's plan is made from.
struct Layout<'a> {
    file: &'a ExperimentFile,
    declared: &'a BTreeMap<PathBuf, BTreeSet<String>>,
    sets: &'a [(String, String)],
    recordings: &'a Path,
    runs: &'a Path,
}

impl Layout<'_> {
    /// Sequence `k` of `world` (its scenario run `run`), with the models in `needed`.
    fn sequence(&self, world: &World, run: &str, k: u32, needed: &BTreeSet<&str>) -> SequencePlan {
        let Self {
            file,
            declared,
            sets,
            recordings,
            runs: folder,
        } = *self;
        let name = &world.name;
        let (label, recording, stem) = if k == 0 {
            (
                name.clone(),
                recordings.join(format!("{name}-{run}.mcap")),
                name.clone(),
            )
        } else {
            (
                format!("{name} repeat {k}"),
                recordings.join(format!("{name}-{run}-{k}.mcap")),
                format!("{name}-{k}"),
            )
        };
        let runs = file
            .models
            .iter()
            .filter(|m| needed.contains(m.name.as_str()))
            .map(|m| RunPlan {
                model: m.name.clone(),
                graph: m.graph.clone(),
                sets: m
                    .set
                    .iter()
                    .map(|(k, v)| (k.clone(), v.clone()))
                    .chain(
                        sets.iter()
                            .filter(|(key, _)| declares(declared, &m.graph, key))
                            .cloned(),
                    )
                    .collect(),
                base: folder.join(format!("{stem}-{}", m.name)),
                keep_recording: k == 0,
            })
            .collect();
        SequencePlan {
            repeat: k,
            label,
            scenario: world.scenario.clone(),
            run: run.to_owned(),
            recording,
            runs,
        }
    }
}

fn declares(declared: &BTreeMap<PathBuf, BTreeSet<String>>, graph: &Path, key: &str) -> bool {
    declared.get(graph).is_some_and(|vars| vars.contains(key))
}

fn none_if_empty(names: &[&str]) -> String {
    if names.is_empty() {
        "none".into()
    } else {
        names.join(", ")
    }
}

/// The runs' folder for `--set`s: the folder itself, or `folder-key=value...` with every
/// character but `A-Za-z0-9_.=` of each `key=value` made `_`.
pub fn sets_folder(folder: &Path, sets: &[(String, String)]) -> PathBuf {
    let mut name = folder.as_os_str().to_owned();
    for (key, value) in sets {
        let clean: String = format!("{key}={value}")
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || "_.=".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        name.push(format!("-{clean}"));
    }
    PathBuf::from(name)
}

fn with_suffix(base: &Path, suffix: &str) -> PathBuf {
    let mut name = base.as_os_str().to_owned();
    name.push(suffix);
    PathBuf::from(name)
}
