//! A user's own stage as its own executable: [`ToyGain`] run over iceoryx2 with the gprflow
//! SDK. A graph names such a program with `exec:`; the launcher starts it with
//! `--spec FILE`, exactly as it starts built-in stages.

use std::process::ExitCode;

use gprflow_bus::iox::IoxTransport;
use gprflow_stage::{NodeSpec, bind_signals, run_node};
use gprflow_stage_toy::ToyGain;

fn run(spec_path: &str) -> Result<(), String> {
    let text = std::fs::read_to_string(spec_path).map_err(|e| format!("{spec_path}: {e}"))?;
    let spec: NodeSpec = serde_json::from_str(&text).map_err(|e| format!("{spec_path}: {e}"))?;
    let stop = bind_signals().map_err(|e| e.to_string())?;
    let transport = IoxTransport::new(&spec.node, &spec.prefix, stop.clone()).map_err(|e| e.to_string())?;
    run_node::<ToyGain>(&spec, &transport, &stop).map_err(|e| format!("node `{}`: {e}", spec.node))?;
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let Some(spec) = args.windows(2).find(|w| w[0] == "--spec").map(|w| w[1].clone()) else {
        eprintln!("usage: toy_gain_exec --spec FILE");
        return ExitCode::from(2);
    };
    match run(&spec) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(1)
        }
    }
}
