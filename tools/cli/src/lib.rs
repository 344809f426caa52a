//! The `gprflow` command's library: the catalog of stages this build knows and the
//! commands, so that `main.rs` only parses arguments.

pub mod bench_estimate;
pub mod bus;
pub mod calibrate;
pub mod commands;
pub mod convert;
pub mod diff;
pub mod eval;
pub mod experiment;
pub mod lgpr_eval;
pub mod plot;
pub mod radargram;
pub mod sim;

use gprflow::record::{RecordStage, ReplayStage};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use gprflow::bus::Transport;
use gprflow::stage::{NodeSpec, RunReport, Stage, StageCatalog, StageError, StageInfo, describe, run_node};
use gprflow_dsp::node::{DspStage, DspSubmapStage};
use gprflow_estimate::node::EstimateStage;
use gprflow_ingest::node::IngestStage;
use gprflow_lgpr::node::{LgprDspStage, LgprMapStage, LgprTrackStage};
use gprflow_lines::node::LinesStage;
use gprflow_register::node::RegisterStage;
use gprflow_stage_toy::{ToyGain, ToySource};
use gprflow_submap::node::SubmapStage;
use gprflow_viz::VizStage;

/// Whether a `gprflow stage KIND` process runs with one malloc arena. The LGPR tracker grids
/// the map ahead on a worker thread and tracks on (then drops) those grids, tens of MiB each,
/// on its own: with a malloc arena per thread and freed memory kept (the CLI's
/// `keep_freed_memory`), the memory the arenas keep fragmented grew with the route, 321 / 348 /
/// 451 MiB peak after 5 / 20 / 57 laps of the highway (`tools/bench/scale.sh lgpr:5 lgpr:20
/// lgpr:60`), against 315 / 314 / 329 MiB in one arena with the same fixes.
#[must_use]
pub fn one_malloc_arena(kind: &str) -> bool {
    kind == <LgprTrackStage as Stage>::NAME
}

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

/// A stage kind this build can run: its name, its description and its runner.
struct Kind {
    name: &'static str,
    describe: fn() -> Box<dyn StageInfo>,
    run: fn(&NodeSpec, &dyn Transport, &Arc<AtomicBool>) -> Result<RunReport, StageError>,
}

const fn kind<S: Stage + 'static>() -> Kind {
    Kind {
        name: S::NAME,
        describe: describe::<S>,
        run: run_node::<S>,
    }
}

/// Every stage kind this build can run, written once: [`catalog`] describes them and
/// [`run_stage`] runs them.
const STAGES: &[Kind] = &[
    kind::<ToySource>(),
    kind::<ToyGain>(),
    kind::<EstimateStage>(),
    kind::<SubmapStage>(),
    kind::<IngestStage>(),
    kind::<DspStage>(),
    kind::<DspSubmapStage>(),
    kind::<LgprDspStage>(),
    kind::<LgprMapStage>(),
    kind::<LgprTrackStage>(),
    kind::<RegisterStage>(),
    kind::<LinesStage>(),
    kind::<VizStage>(),
    kind::<RecordStage>(),
    kind::<ReplayStage>(),
];

/// Every stage kind this build can run.
pub fn catalog() -> StageCatalog {
    STAGES
        .iter()
        .fold(StageCatalog::new(), |catalog, kind| catalog.with((kind.describe)()))
}

/// Runs the stage named in `spec` in this process over iceoryx2.
///
/// # Errors
/// Unknown stage, or the stage's error.
pub fn run_stage(kind: &str, spec: &NodeSpec, stop: &Arc<AtomicBool>) -> Result<RunReport, StageError> {
    if kind == gprflow::bridge::BRIDGE_STAGE {
        let started = std::time::Instant::now();
        let routes = gprflow::bridge::run_bridge(spec, stop)?;
        let (cpu_s, peak_rss_bytes) = gprflow::stage::process_usage();
        return Ok(RunReport {
            node: spec.node.clone(),
            received: Vec::new(),
            dropped: Vec::new(),
            sent: routes.into_iter().map(|r| (r.route, r.frames)).collect(),
            callback_us: [0; 3],
            decode_errors: 0,
            wall_s: started.elapsed().as_secs_f64(),
            cpu_s,
            peak_rss_bytes,
            interrupted: false,
        });
    }
    let Some(kind) = STAGES.iter().find(|k| k.name == kind) else {
        let known: Vec<&str> = STAGES.iter().map(|k| k.name).collect();
        return Err(StageError::failed(format!(
            "unknown stage `{kind}` (known: {})",
            known.join(", ")
        )));
    };
    let transport = gprflow::bus::iox::IoxTransport::new(&spec.node, &spec.prefix, stop.clone())?;
    (kind.run)(spec, &transport, stop)
}

#[cfg(test)]
mod tests {
    use super::{error_line, one_malloc_arena};
    use anyhow::Context;

    #[test]
    fn the_lgpr_tracker_alone_runs_in_one_malloc_arena() {
        assert!(one_malloc_arena("lgpr_track"));
        for kind in ["lgpr_map", "lgpr_dsp", "estimate", "register", "ingest"] {
            assert!(!one_malloc_arena(kind), "{kind}");
        }
    }

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
