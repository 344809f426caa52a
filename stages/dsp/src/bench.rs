//! The trace-chain benchmark behind `gprflow bench dsp`: the full single-channel chain on a
//! batch of raw traces, one trace at a time on one thread, as the `dsp` stage runs it.
//! `tools/peer/bench_dsp.sh` runs it next to the same chain in numpy/scipy.

use std::time::Instant;

use serde::Serialize;

use crate::Result;
use crate::chain::{ChainParams, TraceChain};
use crate::trace::check_len;

/// What one benchmark run measured.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ChainBenchReport {
    /// Traces processed.
    pub traces: usize,
    /// Samples per trace.
    pub samples: usize,
    /// Wall time of the processing loop (conversion from int16 included), s.
    pub elapsed_s: f64,
    /// Traces per second on one core.
    pub traces_per_s: f64,
    /// Mean time per trace, ns.
    pub ns_per_trace: f64,
    /// `Σ |y|` over every output sample (f64), to compare runs and implementations.
    pub checksum_abs: f64,
    /// Traces whose zero time was found.
    pub zero_time_found: usize,
}

/// Runs the chain over `traces` (row-major, `samples` per trace, int16 counts converted to
/// f32) and times it; the output is only summarised (see [`process_traces`] to keep it).
pub fn run_trace_chain(
    traces: &[i16],
    samples: usize,
    params: &ChainParams,
    sample_interval_ns: f64,
    center_frequency_hz: f64,
) -> Result<ChainBenchReport> {
    let mut chain = TraceChain::new(params, samples, sample_interval_ns, center_frequency_hz)?;
    check_whole_traces(traces, samples)?;
    let mut buffer = vec![0.0_f32; samples];
    let (mut checksum_abs, mut zero_time_found) = (0.0_f64, 0);
    let start = Instant::now();
    for raw in traces.chunks_exact(samples) {
        buffer.iter_mut().zip(raw).for_each(|(y, &x)| *y = f32::from(x));
        zero_time_found += usize::from(chain.process(&mut buffer)?.is_some());
        checksum_abs += abs_sum(&buffer);
    }
    let elapsed_s = start.elapsed().as_secs_f64();
    let n = traces.len() / samples;
    Ok(ChainBenchReport {
        traces: n,
        samples,
        elapsed_s,
        traces_per_s: n as f64 / elapsed_s,
        ns_per_trace: elapsed_s * 1e9 / n.max(1) as f64,
        checksum_abs,
        zero_time_found,
    })
}

/// Runs the chain over `traces` (as [`run_trace_chain`], untimed) and returns the processed
/// traces, row-major.
pub fn process_traces(
    traces: &[i16],
    samples: usize,
    params: &ChainParams,
    sample_interval_ns: f64,
    center_frequency_hz: f64,
) -> Result<Vec<f32>> {
    let mut chain = TraceChain::new(params, samples, sample_interval_ns, center_frequency_hz)?;
    check_whole_traces(traces, samples)?;
    let mut out: Vec<f32> = traces.iter().map(|&x| f32::from(x)).collect();
    for trace in out.chunks_exact_mut(samples) {
        chain.process(trace)?;
    }
    Ok(out)
}

/// `samples >= 2` is checked by [`TraceChain::new`] before this runs.
fn check_whole_traces(traces: &[i16], samples: usize) -> Result<()> {
    check_len(
        "bench traces (a multiple of samples)",
        traces.len() / samples * samples,
        traces.len(),
    )
}

/// `Σ |x|` with eight f32 partial sums (it vectorises; a serial f64 sum would cost the
/// benchmark a third of a trace's time), added up in f64.
fn abs_sum(x: &[f32]) -> f64 {
    let mut lanes = [0.0_f32; 8];
    let chunks = x.chunks_exact(8);
    let tail: f64 = chunks.remainder().iter().map(|v| f64::from(v.abs())).sum();
    for chunk in chunks {
        lanes.iter_mut().zip(chunk).for_each(|(l, v)| *l += v.abs());
    }
    tail + lanes.iter().map(|&l| f64::from(l)).sum::<f64>()
}
