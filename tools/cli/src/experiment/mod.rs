//! `gprflow experiment FILE`: the runs an experiment file declares (worlds simulated, each
//! sequence through each model's graph, evaluated against its truth), then its tables, on
//! stdout and between markers in a markdown file.
//!
//! The simulations, graph runs and evaluations are this binary's own `sim`, `launch` and
//! `eval` subcommands, run as child processes: each graph run is a real launch with its own
//! log. Paths in the file are relative to the current directory (the repository's root).

pub mod file;
pub mod plan;
pub mod tables;

use std::collections::{BTreeMap, BTreeSet};
use std::ffi::OsString;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::Instant;

use anyhow::{Context, Result, bail};

use file::ExperimentFile;
use plan::{Choices, Plan, RunPlan, SequencePlan};
use tables::{EvalResult, SequenceSet, WorldResults};

/// Arguments of `gprflow experiment`.
#[derive(Debug, Clone)]
pub struct ExperimentArgs {
    /// The experiment file.
    pub file: PathBuf,
    /// What the command line changes.
    pub choices: Choices,
    /// Keep the runs whose eval result is already there.
    pub reuse: bool,
    /// Write the tables into the file's markdown file (when it names one and no `--set` is
    /// given).
    pub write: bool,
    /// Print the runs and do nothing.
    pub dry_run: bool,
}

/// Runs `gprflow experiment`.
///
/// # Errors
/// The file, a `--set`, a model's graph, a run, an eval result or the markdown file.
pub fn experiment_command(args: &ExperimentArgs) -> Result<ExitCode> {
    let experiment = ExperimentFile::load(&args.file)?;
    let declared = declared_variables(&experiment)?;
    let plan = plan::plan(&experiment, &args.choices, &declared).with_context(|| args.file.display().to_string())?;
    if args.dry_run {
        print_plan(&plan)?;
        return Ok(ExitCode::SUCCESS);
    }
    let gprflow = std::env::current_exe().context("the gprflow binary's path")?;
    for program in &experiment.prepare {
        prepare(program)?;
    }
    std::fs::create_dir_all(&plan.runs).with_context(|| format!("creating {}", plan.runs.display()))?;
    std::fs::create_dir_all(&plan.recordings).with_context(|| format!("creating {}", plan.recordings.display()))?;
    let total = plan.runs().count();
    let mut done = 0;
    for sequence in plan.worlds.iter().flat_map(|w| &w.sequences) {
        simulate(&gprflow, sequence)?;
        for run in &sequence.runs {
            done += 1;
            let reused = args.reuse && non_empty(&run.json());
            let started = Instant::now();
            if !reused {
                launch_and_eval(&gprflow, sequence, run)?;
            }
            let how = if reused {
                "reused".to_owned()
            } else {
                format!("done in {:.0} s", started.elapsed().as_secs_f64())
            };
            eprintln!("[{done}/{total}] {} {}: {how}", sequence.label, run.model);
        }
    }
    let results = read_results(&plan)?;
    let set = SequenceSet {
        sequences: plan.sequences,
        repeats: plan.repeats,
    };
    let text = tables::render(&experiment.tables, set, &results).with_context(|| plan.runs.display().to_string())?;
    writeln!(std::io::stdout().lock(), "{text}")?;
    if let (Some(to), true) = (&plan.write, args.write) {
        let doc = std::fs::read_to_string(&to.file).with_context(|| format!("reading {}", to.file.display()))?;
        let doc =
            tables::replace_between_markers(&doc, &to.marker, &text).with_context(|| to.file.display().to_string())?;
        std::fs::write(&to.file, doc).with_context(|| format!("writing {}", to.file.display()))?;
        eprintln!("{} updated", to.file.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// Each model graph's variables, as `gprflow check` reads the file.
fn declared_variables(experiment: &ExperimentFile) -> Result<BTreeMap<PathBuf, BTreeSet<String>>> {
    let catalog = crate::catalog();
    let mut declared = BTreeMap::new();
    for model in &experiment.models {
        if declared.contains_key(&model.graph) {
            continue;
        }
        let graph = gprflow::graph::load(&model.graph, &[], &catalog)
            .with_context(|| format!("model `{}`'s graph", model.name))?;
        declared.insert(model.graph.clone(), graph.vars.into_keys().collect());
    }
    Ok(declared)
}

fn print_plan(plan: &Plan) -> Result<()> {
    let mut out = std::io::stdout().lock();
    let show = |args: &[OsString]| {
        args.iter()
            .map(|a| a.to_string_lossy().into_owned())
            .collect::<Vec<_>>()
            .join(" ")
    };
    for sequence in plan.worlds.iter().flat_map(|w| &w.sequences) {
        writeln!(out, "gprflow {}", show(&sequence.sim_args(&sequence.recording)))?;
        for run in &sequence.runs {
            writeln!(
                out,
                "gprflow {} > {}",
                show(&run.launch_args(&sequence.recording)),
                run.log().display()
            )?;
            writeln!(
                out,
                "gprflow {} > {}",
                show(&run.eval_args(&sequence.recording)),
                run.json().display()
            )?;
        }
    }
    match &plan.write {
        Some(to) => writeln!(out, "tables -> {} (marker {})", to.file.display(), to.marker)?,
        None => writeln!(out, "tables -> stdout")?,
    }
    Ok(())
}

fn prepare(program: &Path) -> Result<()> {
    let status = Command::new(program)
        .stdout(Stdio::null())
        .status()
        .with_context(|| format!("running {}", program.display()))?;
    if !status.success() {
        bail!("{} failed ({status})", program.display());
    }
    Ok(())
}

/// Simulates the sequence's recording when it is not there (into a `.part` file first, so
/// that an interrupted simulation leaves no recording behind).
fn simulate(gprflow: &Path, sequence: &SequencePlan) -> Result<()> {
    if sequence.recording.is_file() {
        return Ok(());
    }
    let mut partial = sequence.recording.clone().into_os_string();
    partial.push(".part");
    let partial = PathBuf::from(partial);
    let started = Instant::now();
    let output = Command::new(gprflow)
        .args(sequence.sim_args(&partial))
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("running {}", gprflow.display()))?;
    if !output.status.success() {
        let _ = std::fs::remove_file(&partial);
        bail!(
            "{}: gprflow sim failed ({}): {}",
            sequence.label,
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    std::fs::rename(&partial, &sequence.recording)
        .with_context(|| format!("renaming {} to {}", partial.display(), sequence.recording.display()))?;
    eprintln!(
        "{}: simulated {} in {:.0} s",
        sequence.label,
        sequence.recording.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Runs the model's graph on the sequence (output in `BASE.log`) and evaluates it
/// (`BASE.json`); a repeat's run recording is deleted afterwards.
fn launch_and_eval(gprflow: &Path, sequence: &SequencePlan, run: &RunPlan) -> Result<()> {
    let what = format!("{} {}", sequence.label, run.model);
    let log = std::fs::File::create(run.log()).with_context(|| format!("creating {}", run.log().display()))?;
    let status = Command::new(gprflow)
        .args(run.launch_args(&sequence.recording))
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log)
        .status()
        .with_context(|| format!("running {}", gprflow.display()))?;
    if !status.success() {
        bail!(
            "{what}: gprflow launch failed ({status}); its output is in {}",
            run.log().display()
        );
    }
    let output = Command::new(gprflow)
        .args(run.eval_args(&sequence.recording))
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("running {}", gprflow.display()))?;
    if !output.status.success() {
        bail!(
            "{what}: gprflow eval failed ({}): {}",
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    std::fs::write(run.json(), &output.stdout).with_context(|| format!("writing {}", run.json().display()))?;
    if !run.keep_recording {
        std::fs::remove_file(run.mcap()).with_context(|| format!("removing {}", run.mcap().display()))?;
    }
    Ok(())
}

/// The command line's `--set KEY=VALUE`s as pairs.
///
/// # Errors
/// One has no `=`.
pub fn parse_sets(sets: &[String]) -> Result<Vec<(String, String)>> {
    sets.iter()
        .map(|kv| {
            kv.split_once('=')
                .map(|(k, v)| (k.trim().to_owned(), v.to_owned()))
                .with_context(|| format!("--set `{kv}`: expected KEY=VALUE"))
        })
        .collect()
}

fn non_empty(path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| m.len() > 0)
}

/// Every run's eval result, by world, sequence and model.
fn read_results(plan: &Plan) -> Result<Vec<WorldResults>> {
    plan.worlds
        .iter()
        .map(|world| {
            let sequences = world
                .sequences
                .iter()
                .map(|sequence| {
                    let results = sequence
                        .runs
                        .iter()
                        .map(|run| Ok((run.model.clone(), read_result(&run.json())?)))
                        .collect::<Result<BTreeMap<_, _>>>()?;
                    Ok((sequence.label.clone(), results))
                })
                .collect::<Result<_>>()?;
            Ok(WorldResults {
                name: world.name.clone(),
                sequences,
            })
        })
        .collect()
}

fn read_result(path: &Path) -> Result<EvalResult> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not an eval result", path.display()))
}

#[cfg(test)]
mod tests;
