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
        other => Err(StageError::Failed(format!(
            "unknown stage `{other}` (known: {})",
            catalog()
                .iter()
                .map(|s| s.name().to_owned())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}
