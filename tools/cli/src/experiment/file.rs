//! The experiment file (YAML): the worlds, the models that run on them, how many repeats,
//! the tables to make of their results and where to write them. Read once, with every
//! unknown key refused; errors name the file, the line and the key.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::path::{Path, PathBuf};

use gprflow::graph::Location;
use serde::Deserialize;

/// An experiment: what `gprflow experiment FILE` runs and tabulates.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExperimentFile {
    /// Folder of the recordings, the runs' logs and their eval results (`-o` overrides it).
    pub out: PathBuf,
    /// Repeats per world: `gprflow sim --repeat 1..=repeats` (`--repeats` overrides it).
    #[serde(default)]
    pub repeats: u32,
    /// The sequences of each world the tables are over.
    #[serde(default)]
    pub sequences: Sequences,
    /// Programs run once, without arguments, before anything else (e.g.
    /// `tools/scripts/ensure-onnxruntime.sh`, which the learned model needs).
    #[serde(default)]
    pub prepare: Vec<PathBuf>,
    /// The worlds, in table column order.
    pub worlds: Vec<World>,
    /// Named variants (`--variant NAME`): another run of every world, another folder, another
    /// place to write.
    #[serde(default)]
    pub variants: BTreeMap<String, Variant>,
    /// The models, in run order.
    pub models: Vec<Model>,
    /// The tables, in print order.
    pub tables: Vec<Table>,
    /// Where the tables go besides stdout (nowhere when absent).
    #[serde(default)]
    pub write: Option<WriteTo>,
}

/// The sequences of a world.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sequences {
    /// The world's run (the scenario's own draw), then its repeats 1..=n.
    #[default]
    RunAndRepeats,
    /// The repeats 1..=n alone.
    Repeats,
}

/// A simulated world: a scenario file and one of its runs.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct World {
    /// The name in tables and file names.
    pub name: String,
    /// Scenario file (`gprflow sim`).
    pub scenario: PathBuf,
    /// The scenario's run to simulate.
    pub run: String,
}

/// A variant of the experiment: every world's run replaced by another of its scenario.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// The scenario run each world simulates instead.
    pub run: String,
    /// The folder instead of the experiment's.
    pub out: PathBuf,
    /// Where its tables go (nowhere when absent: the experiment's `write` is not inherited).
    #[serde(default)]
    pub write: Option<WriteTo>,
}

/// A model: a graph file and its variables. Every run gets `recording=` the sequence's
/// recording; the command line's `--set`s go to each model whose graph declares them.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Model {
    /// The name in tables and file names.
    pub name: String,
    /// Graph file (`gprflow launch`).
    pub graph: PathBuf,
    /// Graph variables (`--set KEY=VALUE`).
    #[serde(default)]
    pub set: BTreeMap<String, String>,
}

/// A table of the results.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Table {
    /// Registration error (along track, cm) per model and world on each world's run, and
    /// combined over the worlds.
    Registration {
        /// The rows.
        models: Vec<String>,
        /// A row's label instead of the model's name.
        #[serde(default)]
        labels: BTreeMap<String, String>,
    },
    /// ATE per model and world over the world's sequences.
    Ate {
        /// The rows.
        models: Vec<String>,
        /// A last row comparing two of the models.
        #[serde(default)]
        ratio: Option<Ratio>,
    },
}

/// The ATE table's comparison of a model with a reference model.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ratio {
    /// The model compared.
    pub model: String,
    /// The model it is compared with.
    pub reference: String,
    /// A sequence counts when the model's ATE is at most this many percent above the
    /// reference's.
    pub within_percent: u32,
    /// What the cell's first figure is.
    pub form: RatioForm,
}

/// The first figure of a ratio cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RatioForm {
    /// The ratio of the two mean ATEs.
    OfMeans,
    /// The mean, min and max of the per-sequence ratios.
    OfRatios,
}

/// A markdown file and the marker whose `<!-- MARKER:begin -->` / `<!-- MARKER:end -->`
/// lines the tables go between.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WriteTo {
    /// The file.
    pub file: PathBuf,
    /// The marker's name.
    pub marker: String,
}

/// An experiment file that cannot be used: where and why.
#[derive(Debug)]
pub struct FileError {
    /// File, line and column, key path.
    pub at: Box<Location>,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for FileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.at, self.message)
    }
}

impl std::error::Error for FileError {}

impl ExperimentFile {
    /// Reads and checks the experiment file at `path`.
    ///
    /// # Errors
    /// The file cannot be read, is not an experiment file, or names a model it does not
    /// declare; the error says where.
    pub fn load(path: &Path) -> Result<Self, FileError> {
        let text = std::fs::read_to_string(path).map_err(|e| FileError {
            at: Box::new(Location {
                file: path.to_owned(),
                position: None,
                key_path: String::new(),
            }),
            message: e.to_string(),
        })?;
        Self::parse(&text, path)
    }

    /// Parses and checks experiment text; `file` names it in errors.
    ///
    /// # Errors
    /// As [`load`](Self::load).
    pub fn parse(text: &str, file: &Path) -> Result<Self, FileError> {
        let experiment: Self = serde_saphyr::from_str(text).map_err(|e| {
            let (at, message) = gprflow::graph::locate_yaml_error(file, text, &e);
            FileError { at, message }
        })?;
        experiment.check().map_err(|(key, message)| FileError {
            at: gprflow::graph::locate_yaml_key(file, text, &key),
            message,
        })?;
        Ok(experiment)
    }

    /// The model named `name`.
    pub fn model(&self, name: &str) -> Option<&Model> {
        self.models.iter().find(|m| m.name == name)
    }

    /// The checks serde cannot make: unique names, tables naming declared models. Errors as
    /// (key path, message).
    fn check(&self) -> Result<(), (String, String)> {
        if self.worlds.is_empty() {
            return Err(("worlds".into(), "no worlds".into()));
        }
        if self.models.is_empty() {
            return Err(("models".into(), "no models".into()));
        }
        unique(self.worlds.iter().map(|w| w.name.as_str()), "worlds", "world")?;
        unique(self.models.iter().map(|m| m.name.as_str()), "models", "model")?;
        for (i, model) in self.models.iter().enumerate() {
            if model.set.contains_key(RECORDING_VAR) {
                return Err((
                    format!("models.{i}.set.{RECORDING_VAR}"),
                    format!("`{RECORDING_VAR}` is each sequence's recording; the runner sets it"),
                ));
            }
        }
        if self.tables.is_empty() {
            return Err(("tables".into(), "no tables".into()));
        }
        let known = |key: String, name: &str| {
            if self.model(name).is_some() {
                Ok(())
            } else {
                let names: Vec<&str> = self.models.iter().map(|m| m.name.as_str()).collect();
                Err((key, format!("no model `{name}` (models: {})", names.join(", "))))
            }
        };
        for (i, table) in self.tables.iter().enumerate() {
            match table {
                Table::Registration { models, labels } => {
                    if self.sequences == Sequences::Repeats {
                        return Err((
                            format!("tables.{i}.kind"),
                            "the registration table is over each world's run, which `sequences: repeats` leaves out"
                                .into(),
                        ));
                    }
                    for (j, m) in models.iter().enumerate() {
                        known(format!("tables.{i}.models.{j}"), m)?;
                    }
                    for m in labels.keys() {
                        if !models.contains(m) {
                            return Err((format!("tables.{i}.labels.{m}"), format!("`{m}` is not a row")));
                        }
                    }
                }
                Table::Ate { models, ratio } => {
                    for (j, m) in models.iter().enumerate() {
                        known(format!("tables.{i}.models.{j}"), m)?;
                    }
                    if let Some(ratio) = ratio {
                        known(format!("tables.{i}.ratio.model"), &ratio.model)?;
                        known(format!("tables.{i}.ratio.reference"), &ratio.reference)?;
                    }
                }
            }
        }
        for write in self
            .write
            .iter()
            .chain(self.variants.values().filter_map(|v| v.write.as_ref()))
        {
            if write.marker.is_empty() || write.marker.contains(['<', '>', '\n']) {
                return Err(("write.marker".into(), format!("`{}` is no marker name", write.marker)));
            }
        }
        Ok(())
    }

    /// The models each sequence needs: on the world's run (`run == true`) every table's, on a
    /// repeat the ATE tables' (rows and ratio).
    pub fn needed_models(&self, run: bool) -> BTreeSet<&str> {
        let mut needed = BTreeSet::new();
        for table in &self.tables {
            match table {
                Table::Registration { models, .. } => {
                    if run {
                        needed.extend(models.iter().map(String::as_str));
                    }
                }
                Table::Ate { models, ratio } => {
                    needed.extend(models.iter().map(String::as_str));
                    if let Some(r) = ratio {
                        needed.insert(r.model.as_str());
                        needed.insert(r.reference.as_str());
                    }
                }
            }
        }
        needed
    }
}

/// The graph variable every run's recording goes in.
pub const RECORDING_VAR: &str = "recording";

fn unique<'a>(names: impl Iterator<Item = &'a str>, key: &str, what: &str) -> Result<(), (String, String)> {
    let mut seen = BTreeSet::new();
    for (i, name) in names.enumerate() {
        if name.is_empty() || name.contains(['/', ' ']) {
            return Err((
                format!("{key}.{i}.name"),
                format!("`{name}` is no {what} name (used in file names)"),
            ));
        }
        if !seen.insert(name) {
            return Err((format!("{key}.{i}.name"), format!("a second {what} `{name}`")));
        }
    }
    Ok(())
}
