//! Stage SDK: what a stage declares, and the runtime that feeds it.
//!
//! A stage is a type implementing [`Stage`]: typed `Params` (serde, `deny_unknown_fields`,
//! documented defaults), declared inputs and outputs, and callbacks. The runtime
//! ([`run_node`]) opens its topics, delivers inputs merged in stamp order (a watermark per
//! input, so the output is a deterministic function of the inputs), propagates end of
//! stream, stops cleanly on SIGINT/SIGTERM, and reports counts and latency percentiles.

mod drops;
mod runtime;
mod spec;

pub use drops::Drops;

/// The shared parameter checks ([`gprflow_params::positive`] ...), for `check_params`.
pub use gprflow_params as params;
pub use runtime::{
    Input, InputBinding, InputId, NodeSpec, Output, OutputBinding, Outputs, Ports, Produce, RunReport, StageError,
    bind_signals, process_usage, run_node,
};
pub use spec::{InputPorts, InputSpec, ParamError, PortSpec, StageCatalog, StageInfo, parse_params};

use std::marker::PhantomData;

/// Prefix of the stderr lines by which a stage process reports progress to the launcher
/// that started it: `TAG done total`.
pub const PROGRESS_TAG: &str = "@gprflow-progress";

type ProgressSink = Box<dyn Fn(usize, usize) + Send + Sync>;

static PROGRESS_SINK: std::sync::OnceLock<ProgressSink> = std::sync::OnceLock::new();

/// Reports progress (`done` of `total` units; total 0: not known) to the launcher, which shows
/// it as a bar, or to the sink set by [`show_progress_with`].
pub fn report_progress(done: usize, total: usize) {
    match PROGRESS_SINK.get() {
        Some(sink) => sink(done, total),
        None => eprintln!("{PROGRESS_TAG} {done} {total}"),
    }
}

/// Sends this process's progress reports to `sink` instead of the launcher (a stage run in a
/// command's own process, such as `gprflow replay`). Only the first call takes effect.
pub fn show_progress_with(sink: impl Fn(usize, usize) + Send + Sync + 'static) {
    let _ = PROGRESS_SINK.set(Box::new(sink));
}

/// Prefix of the stderr line by which a stage process hands its [`RunReport`] to the
/// launcher at its end: `TAG {json}`.
pub const REPORT_TAG: &str = "@gprflow-report";

/// Hands `report` to the launcher that started this process (one stderr line).
pub fn hand_report(report: &RunReport) {
    match serde_json::to_string(report) {
        Ok(json) => eprintln!("{REPORT_TAG} {json}"),
        Err(e) => tracing::warn!("cannot encode the run report: {e}"),
    }
}

/// A processing stage. Algorithms live in plain functions; a `Stage` only moves messages.
pub trait Stage: Sized {
    /// Typed parameters, read once at start-up from the graph file's `params`.
    type Params: serde::de::DeserializeOwned + schemars::JsonSchema;
    /// Name used in graph files.
    const NAME: &'static str;
    /// One line saying what the stage does.
    const ABOUT: &'static str;

    /// Declared inputs.
    fn inputs() -> InputPorts {
        InputPorts::Fixed(Vec::new())
    }

    /// Outputs for these parameters.
    ///
    /// # Errors
    /// When the outputs cannot be determined from the parameters.
    fn outputs(params: &Self::Params) -> Result<Vec<PortSpec>, ParamError>;

    /// Checks the parameters' values (finite, positive, in range, consistent), with the
    /// shared checks of [`gprflow_params`]. `gprflow check` runs it, so a bad value is
    /// reported at its line in the graph file before any process starts, and the runtime
    /// runs it before [`create`](Stage::create).
    ///
    /// # Errors
    /// The first bad value, naming its key.
    fn check_params(_params: &Self::Params) -> Result<(), ParamError> {
        Ok(())
    }

    /// Builds the stage; looks up its ports in `ports`.
    ///
    /// # Errors
    /// Any start-up failure.
    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError>;

    /// Handles one input message (delivered in stamp order across inputs).
    ///
    /// # Errors
    /// Any failure; the stage stops and the launcher reports it.
    fn on_message(&mut self, _input: Input<'_>, _out: &mut Outputs) -> Result<(), StageError> {
        Ok(())
    }

    /// For stages without inputs (sources): produces the next messages.
    ///
    /// # Errors
    /// Any failure.
    fn produce(&mut self, _out: &mut Outputs) -> Result<Produce, StageError> {
        Ok(Produce::Done)
    }

    /// Called once every input has ended (or the source is done), before end of stream is
    /// sent downstream.
    ///
    /// # Errors
    /// Any failure.
    fn finish(&mut self, _out: &mut Outputs) -> Result<(), StageError> {
        Ok(())
    }
}

/// [`StageInfo`] of a [`Stage`] type, for catalogs.
pub struct Described<S>(PhantomData<fn() -> S>);

impl<S> std::fmt::Debug for Described<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Described")
    }
}

/// Describes stage `S` for a [`StageCatalog`].
pub fn describe<S: Stage + 'static>() -> Box<dyn StageInfo> {
    Box::new(Described::<S>(PhantomData))
}

impl<S: Stage> StageInfo for Described<S> {
    fn name(&self) -> &str {
        S::NAME
    }
    fn about(&self) -> &str {
        S::ABOUT
    }
    fn inputs(&self) -> InputPorts {
        S::inputs()
    }
    fn outputs(&self, params: &serde_json::Value) -> Result<Vec<PortSpec>, ParamError> {
        S::outputs(&parse_params::<S::Params>(params)?)
    }
    fn params_schema(&self) -> schemars::Schema {
        schemars::schema_for!(S::Params)
    }
    fn check_params(&self, params: &serde_json::Value) -> Result<(), ParamError> {
        S::check_params(&parse_params::<S::Params>(params)?)
    }
}
