//! The `gprflow` command's library: the catalog of stages this build knows and the
//! commands, so that `main.rs` only parses arguments.

pub mod bench_estimate;
pub mod calibrate;
pub mod commands;
pub mod convert;
pub mod eval;
pub mod plot;
pub mod sim;

use gprflow::record::{RecordStage, ReplayStage};
use gprflow::stage::{NodeSpec, RunReport, Stage, StageCatalog, StageError, describe, run_node};
use gprflow_dsp::node::{DspStage, DspSubmapStage};
use gprflow_estimate::node::EstimateStage;
use gprflow_ingest::node::IngestStage;
use gprflow_lgpr::node::LgprDspStage;
use gprflow_lines::node::LinesStage;
use gprflow_register::node::RegisterStage;
use gprflow_stage_toy::{ToyGain, ToySource};
use gprflow_submap::node::SubmapStage;

/// An error and its causes on one line, `outer: cause: ...`, leaving out a cause whose text
/// ends the message of the error it explains (error types that name their source in their own
/// message, such as `RecordError::Io`, would otherwise print it twice).
#[must_use]
pub fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    let mut outer = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if !outer.ends_with(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
        outer = text;
    }
    line
}

/// Every stage kind this build can run.
pub fn catalog() -> StageCatalog {
    StageCatalog::new()
        .with(describe::<ToySource>())
        .with(describe::<ToyGain>())
        .with(describe::<EstimateStage>())
        .with(describe::<SubmapStage>())
        .with(describe::<IngestStage>())
        .with(describe::<DspStage>())
        .with(describe::<DspSubmapStage>())
        .with(describe::<LgprDspStage>())
        .with(describe::<RegisterStage>())
        .with(describe::<LinesStage>())
        .with(describe::<RecordStage>())
        .with(describe::<ReplayStage>())
}

/// Runs the stage named in `spec` in this process over iceoryx2.
///
/// # Errors
/// Unknown stage, or the stage's error.
pub fn run_stage(
    kind: &str,
    spec: &NodeSpec,
    stop: &std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Result<RunReport, StageError> {
    if kind == gprflow::bridge::BRIDGE_STAGE {
        let started = std::time::Instant::now();
        let routes = gprflow::bridge::run_bridge(spec, stop)?;
        return Ok(RunReport {
            node: spec.node.clone(),
            received: Vec::new(),
            dropped: Vec::new(),
            sent: routes.into_iter().map(|r| (r.route, r.frames)).collect(),
            callback_us: [0; 3],
            decode_errors: 0,
            wall_s: started.elapsed().as_secs_f64(),
            interrupted: false,
        });
    }
    let transport = gprflow::bus::iox::IoxTransport::new(&spec.node, &spec.prefix, stop.clone())?;
    fn run<S: Stage>(
        spec: &NodeSpec,
        t: &gprflow::bus::iox::IoxTransport,
        stop: &std::sync::Arc<std::sync::atomic::AtomicBool>,
    ) -> Result<RunReport, StageError> {
        run_node::<S>(spec, t, stop)
    }
    match kind {
        ToySource::NAME => run::<ToySource>(spec, &transport, stop),
        ToyGain::NAME => run::<ToyGain>(spec, &transport, stop),
        EstimateStage::NAME => run::<EstimateStage>(spec, &transport, stop),
        SubmapStage::NAME => run::<SubmapStage>(spec, &transport, stop),
        IngestStage::NAME => run::<IngestStage>(spec, &transport, stop),
        DspStage::NAME => run::<DspStage>(spec, &transport, stop),
        DspSubmapStage::NAME => run::<DspSubmapStage>(spec, &transport, stop),
        LgprDspStage::NAME => run::<LgprDspStage>(spec, &transport, stop),
        RegisterStage::NAME => run::<RegisterStage>(spec, &transport, stop),
        LinesStage::NAME => run::<LinesStage>(spec, &transport, stop),
        RecordStage::NAME => run::<RecordStage>(spec, &transport, stop),
        ReplayStage::NAME => run::<ReplayStage>(spec, &transport, stop),
        other => Err(StageError::failed(format!(
            "unknown stage `{other}` (known: {})",
            catalog()
                .iter()
                .map(|s| s.name().to_owned())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::error_line;
    use anyhow::Context;

    #[test]
    fn error_line_names_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let record = gprflow::record::RecordError::Io {
            path: "/x.mcap".into(),
            source: io,
        };
        let e = anyhow::Error::new(record);
        assert_eq!(error_line(&e), "/x.mcap: no such file");
        let e = e.context("cannot evaluate");
        assert_eq!(error_line(&e), "cannot evaluate: /x.mcap: no such file");
        // causes that are not repeated all show, outermost first
        let e = Err::<(), _>(std::io::Error::other("disk full"))
            .context("writing out.mcap")
            .context("recording")
            .expect_err("an error");
        assert_eq!(error_line(&e), "recording: writing out.mcap: disk full");
    }
}
