//! The SFCW chain against numpy/scipy on the same inputs, step by step (golden files written
//! by `tools/peer/sfcw_fixtures.py`; regenerate with
//! `.venv-peers/bin/python tools/peer/sfcw_fixtures.py`). Run with `--nocapture` to see the
//! largest relative error of every step.

use std::path::PathBuf;

use gprflow_lgpr::sfcw::{
    DistanceHighPass, FactoryCalibration, InverseTransform, RangeGain, SfcwChain, SfcwParams, chebyshev_window,
    self_calibrate, tone_weights,
};
use rustfft::num_complex::Complex64;
use serde::Deserialize;

/// Agreement required with the peer: `max |ours - ref| <= PEER_RTOL * max |ref|`.
const PEER_RTOL: f64 = 1e-5;
/// Agreement required of the window with scipy's `chebwin`.
const WINDOW_RTOL: f64 = 1e-9;

#[derive(Deserialize)]
struct ChainFixture {
    params: SfcwParams,
    channels: usize,
    bins: usize,
    start_frequency_hz: f64,
    frequency_step_hz: f64,
    sample_interval_ns: f64,
    factory_values: Vec<f32>,
    factory_calibration: Vec<f32>,
    range_gain: Vec<f64>,
    sweeps: Vec<SweepFixture>,
}

#[derive(Deserialize)]
struct SweepFixture {
    values: Vec<f32>,
    calibration: Vec<f32>,
    distance_since_last_m: f64,
    self_calibrated: Vec<f64>,
    factory_calibrated: Vec<f64>,
    windowed: Vec<f64>,
    time: Vec<f64>,
    high_passed: Vec<f64>,
    out: Vec<f32>,
    out_self_only: Vec<f32>,
}

#[derive(Deserialize)]
struct WindowFixture {
    cases: Vec<WindowCase>,
}

#[derive(Deserialize)]
struct WindowCase {
    len: usize,
    attenuation_db: f64,
    taps: Vec<f64>,
}

#[derive(Deserialize)]
struct IirFixture {
    iir_distance_m: f64,
    samples: usize,
    input: Vec<f64>,
    constant: IirConstant,
    variable: IirVariable,
}

#[derive(Deserialize)]
struct IirConstant {
    distance_since_last_m: f64,
    output: Vec<f64>,
}

#[derive(Deserialize)]
struct IirVariable {
    distances_since_last_m: Vec<f64>,
    output: Vec<f64>,
}

fn load<T: for<'de> Deserialize<'de>>(name: &str) -> T {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `max |ours - ref| / max |ref|` (0 when both are all zero).
fn relative_error(ours: impl IntoIterator<Item = f64>, reference: impl IntoIterator<Item = f64>) -> f64 {
    let (mut worst, mut scale) = (0.0f64, 0.0f64);
    let mut count = (0usize, 0usize);
    let reference: Vec<f64> = reference.into_iter().collect();
    for (a, b) in ours.into_iter().zip(&reference) {
        worst = worst.max((a - b).abs());
        scale = scale.max(b.abs());
        count.0 += 1;
    }
    count.1 = reference.len();
    assert_eq!(count.0, count.1, "lengths differ");
    if worst == 0.0 { 0.0 } else { worst / scale }
}

fn pairs(z: &[Complex64]) -> impl Iterator<Item = f64> + '_ {
    z.iter().flat_map(|c| [c.re, c.im])
}

/// Tracks the worst relative error of one step over all sweeps.
struct Step {
    name: &'static str,
    worst: f64,
}

impl Step {
    fn new(name: &'static str) -> Self {
        Self { name, worst: 0.0 }
    }

    fn check(&mut self, sweep: usize, error: f64) {
        assert!(
            error <= PEER_RTOL,
            "{} sweep {sweep}: relative error {error:e} > {PEER_RTOL:e}",
            self.name
        );
        self.worst = self.worst.max(error);
    }
}

impl Drop for Step {
    fn drop(&mut self) {
        eprintln!("peer {:<20} max relative error {:.2e}", self.name, self.worst);
    }
}

#[test]
fn chain_matches_numpy_step_by_step() {
    let fx: ChainFixture = load("sfcw_chain.json");
    let (channels, bins, keep) = (fx.channels, fx.bins, fx.params.keep_samples);
    let factory = FactoryCalibration::new(&fx.factory_values, &fx.factory_calibration, channels, bins)
        .expect("factory calibration");
    let weights = tone_weights(bins, fx.start_frequency_hz, fx.frequency_step_hz, &fx.params).expect("weights");
    let mut transform = InverseTransform::new(
        bins,
        fx.start_frequency_hz,
        fx.frequency_step_hz,
        fx.params.time_samples,
        keep,
    )
    .expect("transform");
    let mut high_pass = DistanceHighPass::new(channels * keep, fx.params.iir_distance_m).expect("high-pass");
    let gain = RangeGain::new(
        &fx.params.range_gain,
        fx.params.delay_ns,
        transform.sample_interval_ns(),
        keep,
    )
    .expect("gain");
    let chain_for = |factory| {
        SfcwChain::new(
            fx.params.clone(),
            channels,
            bins,
            fx.start_frequency_hz,
            fx.frequency_step_hz,
            factory,
        )
        .expect("chain")
    };
    let mut chain = chain_for(Some(factory.clone()));
    let mut chain_self_only = chain_for(None);
    assert!((chain.sample_interval_ns() - fx.sample_interval_ns).abs() <= 1e-12 * fx.sample_interval_ns);
    Step::new("range gain").check(
        0,
        relative_error(gain.gains().iter().copied(), fx.range_gain.iter().copied()),
    );

    let mut steps = [
        "self calibration",
        "factory calibration",
        "delay + window",
        "time domain",
        "IIR high-pass",
        "chain output",
        "chain, no factory",
    ]
    .map(Step::new);
    let mut spectrum = vec![Complex64::default(); channels * bins];
    let mut time = vec![0.0; channels * keep];
    let mut out = vec![0.0f32; channels * keep];
    for (i, sw) in fx.sweeps.iter().enumerate() {
        self_calibrate(&sw.values, &sw.calibration, channels, bins, &mut spectrum).expect("eq. 2");
        steps[0].check(i, relative_error(pairs(&spectrum), sw.self_calibrated.iter().copied()));
        factory.apply(&mut spectrum).expect("eq. 4");
        steps[1].check(
            i,
            relative_error(pairs(&spectrum), sw.factory_calibrated.iter().copied()),
        );
        for (k, s) in spectrum.iter_mut().enumerate() {
            *s *= weights[k % bins];
        }
        steps[2].check(i, relative_error(pairs(&spectrum), sw.windowed.iter().copied()));
        for (tones, samples) in spectrum.chunks_exact(bins).zip(time.chunks_exact_mut(keep)) {
            transform.process(tones, samples).expect("transform");
        }
        steps[3].check(i, relative_error(time.iter().copied(), sw.time.iter().copied()));
        high_pass.apply(&mut time, sw.distance_since_last_m).expect("eq. 5-7");
        steps[4].check(i, relative_error(time.iter().copied(), sw.high_passed.iter().copied()));

        chain
            .process(&sw.values, &sw.calibration, sw.distance_since_last_m, &mut out)
            .expect("chain");
        let reference = sw.out.iter().map(|&v| f64::from(v));
        steps[5].check(i, relative_error(out.iter().map(|&v| f64::from(v)), reference));
        chain_self_only
            .process(&sw.values, &sw.calibration, sw.distance_since_last_m, &mut out)
            .expect("chain without factory");
        let reference = sw.out_self_only.iter().map(|&v| f64::from(v));
        steps[6].check(i, relative_error(out.iter().map(|&v| f64::from(v)), reference));
    }
}

#[test]
fn chebyshev_window_matches_scipy() {
    let fx: WindowFixture = load("sfcw_window.json");
    let mut worst = 0.0f64;
    for case in &fx.cases {
        let taps = chebyshev_window(case.len, case.attenuation_db).expect("window");
        let error = relative_error(taps.iter().copied(), case.taps.iter().copied());
        assert!(
            error <= WINDOW_RTOL,
            "chebwin({}, {}): relative error {error:e}",
            case.len,
            case.attenuation_db
        );
        worst = worst.max(error);
    }
    eprintln!("peer {:<20} max relative error {worst:.2e}", "chebwin");
}

#[test]
fn high_pass_matches_lfilter_and_loop() {
    let fx: IirFixture = load("sfcw_iir.json");
    let run = |distances: &mut dyn Iterator<Item = f64>| {
        let mut filter = DistanceHighPass::new(fx.samples, fx.iir_distance_m).expect("filter");
        let mut out = fx.input.clone();
        for (sweep, d) in out.chunks_exact_mut(fx.samples).zip(distances) {
            filter.apply(sweep, d).expect("apply");
        }
        out
    };
    let constant = run(&mut std::iter::repeat(fx.constant.distance_since_last_m));
    let error = relative_error(constant, fx.constant.output.iter().copied());
    assert!(error <= PEER_RTOL, "constant spacing (lfilter): {error:e}");
    eprintln!("peer {:<20} max relative error {error:.2e}", "IIR vs lfilter");
    let variable = run(&mut fx.variable.distances_since_last_m.iter().copied());
    let error = relative_error(variable, fx.variable.output.iter().copied());
    assert!(error <= PEER_RTOL, "variable spacing: {error:e}");
    eprintln!("peer {:<20} max relative error {error:.2e}", "IIR variable d_i");
}
