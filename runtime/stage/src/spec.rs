//! What a stage declares about itself, so that graph files can be checked before any
//! process starts: its inputs, outputs and parameters.

use std::fmt;

pub use gprflow_params::ParamError;

/// One input or output port: a name and a message type (`gprflow_msgs/msg/Trace`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PortSpec {
    /// Port name as used in graph files.
    pub name: String,
    /// Full ROS 2 message type name.
    pub msg_type: String,
}

impl PortSpec {
    /// A port named `name` carrying `msg_type`.
    pub fn new(name: &str, msg_type: &str) -> Self {
        Self {
            name: name.to_owned(),
            msg_type: msg_type.to_owned(),
        }
    }
}

/// The inputs a stage accepts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InputPorts {
    /// Exactly these named inputs (each must be wired unless `optional`).
    Fixed(Vec<InputSpec>),
    /// Any number of inputs of any names and types (the recorder).
    Any,
}

/// One declared input.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputSpec {
    /// Name and type.
    pub port: PortSpec,
    /// The graph may leave it unwired.
    pub optional: bool,
}

/// What the graph checker and the launcher need to know about a stage kind.
/// Implemented for every [`Stage`](super::Stage) by [`describe`](super::describe).
pub trait StageInfo: Send + Sync {
    /// Name used in graph files (`stage: dsp`).
    fn name(&self) -> &str;
    /// One line saying what the stage does.
    fn about(&self) -> &str;
    /// Declared inputs.
    fn inputs(&self) -> InputPorts;
    /// Outputs for these (already checked) parameters; most stages ignore `params`, a
    /// replay stage reads its recording's channels.
    ///
    /// # Errors
    /// A parameter error when the outputs cannot be determined (missing recording...).
    fn outputs(&self, params: &serde_json::Value) -> Result<Vec<PortSpec>, ParamError>;
    /// JSON schema of the `params` map.
    fn params_schema(&self) -> schemars::Schema;
    /// Checks `params` by deserialising them into the stage's typed `Params` and checking
    /// their values ([`Stage::check_params`](super::Stage::check_params)).
    ///
    /// # Errors
    /// The first problem found, with the path of the key.
    fn check_params(&self, params: &serde_json::Value) -> Result<(), ParamError>;
}

/// Deserialises typed params from a JSON value, turning serde's error into a [`ParamError`]
/// with the key path when serde names an unknown or missing field.
///
/// # Errors
/// The deserialisation error.
pub fn parse_params<P: serde::de::DeserializeOwned>(params: &serde_json::Value) -> Result<P, ParamError> {
    let value = if params.is_null() {
        serde_json::Value::Object(serde_json::Map::new())
    } else {
        params.clone()
    };
    serde_json::from_value(value).map_err(|e| {
        let message = e.to_string();
        // serde names the field in backticks: "unknown field `foo`, expected ..."
        let path = message
            .split('`')
            .nth(1)
            .filter(|_| message.starts_with("unknown field") || message.starts_with("missing field"))
            .map(|k| vec![k.to_owned()])
            .unwrap_or_default();
        ParamError { path, message }
    })
}

/// All stage kinds a launcher knows, by name.
#[derive(Default)]
pub struct StageCatalog {
    stages: Vec<Box<dyn StageInfo>>,
}

impl fmt::Debug for StageCatalog {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_list().entries(self.stages.iter().map(|s| s.name())).finish()
    }
}

impl StageCatalog {
    /// An empty catalog.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a stage kind (builder style).
    #[must_use]
    pub fn with(mut self, stage: Box<dyn StageInfo>) -> Self {
        self.stages.push(stage);
        self
    }

    /// Looks a stage kind up by name.
    pub fn get(&self, name: &str) -> Option<&dyn StageInfo> {
        self.stages.iter().find(|s| s.name() == name).map(|s| s.as_ref())
    }

    /// All stage kinds, in registration order.
    pub fn iter(&self) -> impl Iterator<Item = &dyn StageInfo> {
        self.stages.iter().map(|s| s.as_ref())
    }
}
