//! The trace-chain benchmark on a file of raw traces (int16 little-endian, row-major), as
//! `tools/peer/bench_dsp.sh` runs it; prints a JSON report.
//!
//! usage: bench_dsp <traces.i16> [--samples 201] [--dt-ns 0.2] [--fc-hz 5e8] [--repeat 5]
//!        [--params chain.json] [--output out.f32]

use std::io::Write;

use gprflow_dsp::bench::{process_traces, run_trace_chain};
use gprflow_dsp::chain::ChainParams;

struct Args {
    input: String,
    samples: usize,
    dt_ns: f64,
    fc_hz: f64,
    repeat: usize,
    params: ChainParams,
    output: Option<String>,
}

fn parse() -> Result<Args, Box<dyn std::error::Error>> {
    let mut it = std::env::args().skip(1);
    let mut args = Args {
        input: String::new(),
        samples: 201,
        dt_ns: 0.2,
        fc_hz: 500e6,
        repeat: 5,
        params: ChainParams::default(),
        output: None,
    };
    while let Some(a) = it.next() {
        let mut value = || it.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--samples" => args.samples = value()?.parse()?,
            "--dt-ns" => args.dt_ns = value()?.parse()?,
            "--fc-hz" => args.fc_hz = value()?.parse()?,
            "--repeat" => args.repeat = value()?.parse()?,
            "--params" => args.params = serde_json::from_str(&std::fs::read_to_string(value()?)?)?,
            "--output" => args.output = Some(value()?),
            _ if args.input.is_empty() && !a.starts_with('-') => args.input = a,
            _ => return Err(format!("unknown argument {a}").into()),
        }
    }
    if args.input.is_empty() {
        return Err("usage: bench_dsp <traces.i16> [--samples N] [--repeat R] [--output F]".into());
    }
    Ok(args)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse()?;
    let bytes = std::fs::read(&args.input)?;
    let traces: Vec<i16> = bytes
        .chunks_exact(2)
        .map(|b| i16::from_le_bytes([b[0], b[1]]))
        .collect();
    // Best of `repeat` runs (the first warms the caches).
    let mut best = None;
    for _ in 0..args.repeat.max(1) {
        let r = run_trace_chain(&traces, args.samples, &args.params, args.dt_ns, args.fc_hz)?;
        if best
            .as_ref()
            .is_none_or(|b: &gprflow_dsp::bench::ChainBenchReport| r.elapsed_s < b.elapsed_s)
        {
            best = Some(r);
        }
    }
    if let Some(path) = &args.output {
        let out = process_traces(&traces, args.samples, &args.params, args.dt_ns, args.fc_hz)?;
        let bytes: Vec<u8> = out.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(path, bytes)?;
    }
    writeln!(std::io::stdout().lock(), "{}", serde_json::to_string(&best)?)?;
    Ok(())
}
