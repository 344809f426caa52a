//! Throughput of the SFCW chain on one thread: sweeps of 11 channels x 51 tones (100 MHz in
//! 6 MHz steps) through calibration, delay, window, the 1024-point inverse transform, the
//! IIR high-pass and the range gain. Prints one JSON object.
//!
//! usage: cargo run --release -p gprflow-lgpr --no-default-features --example bench_sfcw [sweeps (20000)]

use std::f64::consts::TAU;
use std::io::Write;
use std::time::Instant;

use gprflow_lgpr::sfcw::{FactoryCalibration, SfcwChain, SfcwParams};

const CHANNELS: usize = 11;
const TONES: usize = 51;
const F0_HZ: f64 = 100e6;
const DF_HZ: f64 = 6e6;
/// Distinct input sweeps cycled through (so the branch predictor cannot learn one).
const DISTINCT: usize = 64;
/// Untimed sweeps first (caches, the FFT's twiddles, the high-pass state).
const WARM_UP: usize = 4 * DISTINCT;
/// Sweeps summed into the checksum, the same in `tools/peer/bench_sfcw.py`.
const CHECKSUM_SWEEPS: usize = 1000;

/// A sweep of sim-like tones: coupling plus a reflector whose delay moves with `i`.
fn sweep(i: usize) -> (Vec<f32>, Vec<f32>) {
    let mut values = Vec::with_capacity(CHANNELS * TONES * 2);
    for ch in 0..CHANNELS {
        for m in 0..TONES {
            let f_ghz = (F0_HZ + m as f64 * DF_HZ) * 1e-9;
            let delay_ns = 10.0 + 0.05 * i as f64 + 0.3 * ch as f64;
            let re = 1.0 + 0.1 * (TAU * f_ghz * delay_ns).cos();
            let im = -0.1 * (TAU * f_ghz * delay_ns).sin();
            values.extend([re as f32, im as f32]);
        }
    }
    let calibration = (0..TONES)
        .flat_map(|m| {
            let phase = -TAU * (F0_HZ + m as f64 * DF_HZ) * 1.5e-9;
            [phase.cos() as f32, phase.sin() as f32]
        })
        .collect();
    (values, calibration)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let sweeps: usize = match std::env::args().nth(1) {
        Some(arg) => arg.parse()?,
        None => 20_000,
    };
    let (factory_values, factory_cal) = sweep(0);
    let factory = FactoryCalibration::new(&factory_values, &factory_cal, CHANNELS, TONES)?;
    let params = SfcwParams::default();
    let mut chain = SfcwChain::new(params, CHANNELS, TONES, F0_HZ, DF_HZ, Some(factory))?;
    let inputs: Vec<_> = (1..=DISTINCT).map(sweep).collect();
    let mut out = vec![0.0f32; CHANNELS * chain.out_samples()];
    for (values, cal) in inputs.iter().cycle().take(WARM_UP) {
        chain.process(values, cal, 0.1, &mut out)?;
    }
    let start = Instant::now();
    let mut checksum = 0.0f64;
    for (k, (values, cal)) in inputs.iter().cycle().take(sweeps).enumerate() {
        chain.process(values, cal, 0.1, &mut out)?;
        if k < CHECKSUM_SWEEPS {
            checksum += f64::from(out[out.len() / 2]);
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let report = serde_json::json!({
        "implementation": "gprflow-lgpr (Rust, rustfft, f64)",
        "channels": CHANNELS,
        "tones": TONES,
        "time_samples": chain.params().time_samples,
        "out_samples": chain.out_samples(),
        "sweeps": sweeps,
        "seconds": seconds,
        "sweeps_per_s": sweeps as f64 / seconds,
        "ns_per_sweep": seconds * 1e9 / sweeps as f64,
        "realtime_factor_126hz": sweeps as f64 / seconds / 126.0,
        "checksum": checksum,
    });
    writeln!(std::io::stdout().lock(), "{report}")?;
    Ok(())
}
