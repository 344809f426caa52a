//! Each filter against its reference implementation on the same input: scipy.signal (firwin,
//! filtfilt), scipy.ndimage (uniform_filter1d, gaussian_filter1d), PyWavelets and
//! scikit-image (denoise_wavelet). The golden files come from `tools/peer/dsp_fixtures.py`
//! (`--verify` proves they still do). Run with `--nocapture` to see the errors.

use std::path::PathBuf;

use gprflow_dsp::chain::{ChainParams, TraceChain};
use gprflow_dsp::image::{GaussianParams, Shape, Wavelet, WaveletDenoiseParams, denoise_wavelet, gaussian_smooth};
use gprflow_dsp::trace::{
    Bandpass, BandpassParams, Dewow, DewowParams, SecGain, SecGainParams, TraceFormat, ZeroTimeParams, firwin_bandpass,
    shift_to_zero_time, zero_time_index,
};
use serde_json::Value;

/// Acceptance: `max |ours - ref| <= PEER_RTOL · max |ref|`.
const PEER_RTOL: f64 = 1e-5;
/// firwin taps and the wavelet statistics are computed in f64 on both sides.
const F64_RTOL: f64 = 1e-12;
/// An exact operation on f32 values: only the fixture's shortest-repr decimals differ.
const F32_REPR_RTOL: f64 = f32::EPSILON as f64;

fn fixture(name: &str) -> Value {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path:?}: {e}"));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{path:?}: {e}"))
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_f64().expect("number"))
        .collect()
}

fn f32s(v: &Value) -> Vec<f32> {
    floats(v).into_iter().map(|x| x as f32).collect()
}

fn num(v: &Value) -> f64 {
    v.as_f64().expect("number")
}

fn count(v: &Value) -> usize {
    v.as_u64().expect("unsigned") as usize
}

/// `max |ours - ref| / max |ref|`.
fn relative_error(ours: &[f64], reference: &[f64]) -> f64 {
    assert_eq!(ours.len(), reference.len(), "lengths");
    let scale = reference.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    let worst = ours
        .iter()
        .zip(reference)
        .fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
    if scale == 0.0 { worst } else { worst / scale }
}

fn assert_close(what: &str, ours: &[f32], reference: &[f64], tolerance: f64) {
    let ours: Vec<f64> = ours.iter().map(|&v| f64::from(v)).collect();
    let err = relative_error(&ours, reference);
    eprintln!("{what}: max relative error {err:.2e}");
    assert!(err <= tolerance, "{what}: {err:.3e} > {tolerance:e}");
}

struct Traces {
    fx: Value,
    format: TraceFormat,
    raw: Vec<f32>,
}

impl Traces {
    fn load() -> Self {
        let fx = fixture("dsp_trace.json");
        let format = TraceFormat::new(
            count(&fx["samples"]),
            num(&fx["sample_interval_ns"]),
            num(&fx["center_frequency_hz"]),
        );
        let raw = f32s(&fx["traces"]);
        Self { fx, format, raw }
    }

    fn rows<'a>(&self, values: &'a mut [f32]) -> std::slice::ChunksExactMut<'a, f32> {
        values.chunks_exact_mut(self.format.samples)
    }
}

#[test]
fn dewow_matches_uniform_filter1d() {
    let t = Traces::load();
    for case in t.fx["dewow"].as_array().expect("cases") {
        let params = DewowParams {
            window_periods: num(&case["window_periods"]),
        };
        let mut dewow = Dewow::new(&params, &t.format).expect("valid");
        assert_eq!(dewow.window_samples(), count(&case["window_samples"]));
        let mut ours = t.raw.clone();
        for trace in t.rows(&mut ours) {
            dewow.apply(trace).expect("length");
        }
        let what = format!("dewow {} periods", params.window_periods);
        assert_close(&what, &ours, &floats(&case["expected"]), PEER_RTOL);
    }
}

#[test]
fn zero_time_matches_the_reference_definition() {
    let t = Traces::load();
    let case = &t.fx["zero_time"];
    let params = ZeroTimeParams {
        threshold: num(&case["threshold"]),
    };
    let want: Vec<i64> = case["index"]
        .as_array()
        .expect("indices")
        .iter()
        .map(|v| v.as_i64().expect("int"))
        .collect();
    let mut ours = f32s(&t.fx["dewowed"]);
    for (trace, &want) in t.rows(&mut ours).zip(&want) {
        let got = zero_time_index(trace, &params);
        assert_eq!(got.map_or(-1, |k| k as i64), want);
        if let Some(k) = got {
            shift_to_zero_time(trace, k);
        }
    }
    assert_close("zero-time shift", &ours, &floats(&case["expected"]), F32_REPR_RTOL);
}

#[test]
fn bandpass_matches_firwin_and_filtfilt() {
    let t = Traces::load();
    let dewowed = f32s(&t.fx["dewowed"]);
    for case in t.fx["bandpass"].as_array().expect("cases") {
        let params = BandpassParams {
            taps: count(&case["taps"]),
            low_cutoff_ratio: num(&case["low_cutoff_ratio"]),
            high_cutoff_ratio: num(&case["high_cutoff_ratio"]),
        };
        let fc = t.format.center_frequency_hz;
        let taps = firwin_bandpass(
            params.taps,
            params.low_cutoff_ratio * fc,
            params.high_cutoff_ratio * fc,
            t.format.sampling_frequency_hz(),
        )
        .expect("valid");
        let err = relative_error(&taps, &floats(&case["firwin"]));
        eprintln!("firwin {} taps: max relative error {err:.2e}", params.taps);
        assert!(err <= F64_RTOL, "firwin {} taps: {err:e}", params.taps);
        let mut bandpass = Bandpass::new(&params, &t.format).expect("valid");
        let mut ours = dewowed.clone();
        for trace in t.rows(&mut ours) {
            bandpass.apply(trace).expect("length");
        }
        let what = format!("filtfilt {} taps", params.taps);
        assert_close(&what, &ours, &floats(&case["expected"]), PEER_RTOL);
    }
}

#[test]
fn sec_gain_matches_the_dataset_tools_formula() {
    let t = Traces::load();
    for case in t.fx["sec_gain"].as_array().expect("cases") {
        let params = SecGainParams {
            a: num(&case["a"]),
            b: num(&case["b"]),
            threshold: count(&case["threshold"]),
        };
        let gain = SecGain::new(&params, t.format.samples).expect("valid");
        let what = format!("SEC gain {}", case["site"]);
        assert_close(&what, gain.gain(), &floats(&case["expected"]), PEER_RTOL);
    }
}

#[test]
fn chain_matches_the_scipy_chain() {
    let t = Traces::load();
    let case = &t.fx["chain"];
    let params: ChainParams = serde_json::from_value(case["params"].clone()).expect("params");
    assert_eq!(params, ChainParams::default(), "the fixture uses the defaults");
    let f = t.format;
    let mut chain = TraceChain::new(&params, f.samples, f.sample_interval_ns, f.center_frequency_hz).expect("valid");
    let want: Vec<i64> = case["zero_time_index"]
        .as_array()
        .expect("indices")
        .iter()
        .map(|v| v.as_i64().expect("int"))
        .collect();
    let mut ours = t.raw.clone();
    for (trace, &want) in t.rows(&mut ours).zip(&want) {
        let k = chain.process(trace).expect("finite");
        assert_eq!(k.map_or(-1, |k| k as i64), want);
    }
    assert_close("chain", &ours, &floats(&case["expected"]), PEER_RTOL);
}

struct Image {
    shape: Shape,
    values: Vec<f32>,
}

impl Image {
    fn load() -> Self {
        let fx = fixture("dsp_image_input.json");
        let shape = Shape::new(count(&fx["rows"]), count(&fx["cols"]));
        let values = floats(&fx["counts"])
            .into_iter()
            .map(|q| (q / 32767.0) as f32)
            .collect();
        Self { shape, values }
    }

    /// The values at the fixture's grid of rows and columns.
    fn pick(&self, values: &[f32], fx: &Value) -> Vec<f32> {
        let rows: Vec<usize> = floats(&fx["grid_rows"]).iter().map(|&r| r as usize).collect();
        let cols: Vec<usize> = floats(&fx["grid_cols"]).iter().map(|&c| c as usize).collect();
        rows.iter()
            .flat_map(|r| cols.iter().map(move |c| values[r * self.shape.cols + c]))
            .collect()
    }
}

#[test]
fn wavelet_denoising_matches_skimage() {
    let img = Image::load();
    let fx = fixture("dsp_wavelet.json");
    for case in fx["cases"].as_array().expect("cases") {
        let name = case["wavelet"].as_str().expect("name");
        let wavelet: Wavelet = serde_json::from_value(case["wavelet"].clone()).expect("wavelet");
        let params = WaveletDenoiseParams { wavelet, levels: None };
        let mut ours = img.values.clone();
        let summary = denoise_wavelet(&mut ours, img.shape, &params).expect("valid");
        assert_eq!(summary.levels, count(&case["levels"]), "{name} levels");
        let sigma_err = relative_error(&[summary.sigma], &[num(&case["sigma"])]);
        assert!(sigma_err <= F64_RTOL, "{name} sigma: {sigma_err:e}");
        let want: Vec<f64> = case["thresholds"]
            .as_array()
            .expect("levels")
            .iter()
            .flat_map(floats)
            .collect();
        let got: Vec<f64> = summary.thresholds.iter().flatten().copied().collect();
        let t_err = relative_error(&got, &want);
        assert!(t_err <= F64_RTOL, "{name} thresholds: {t_err:e}");
        let what = format!("denoise_wavelet {name}");
        assert_close(&what, &img.pick(&ours, &fx), &floats(&case["expected"]), PEER_RTOL);
    }
}

#[test]
fn gaussian_matches_gaussian_filter1d() {
    let img = Image::load();
    let fx = fixture("dsp_gaussian.json");
    for case in fx["cases"].as_array().expect("cases") {
        let params = GaussianParams {
            sigma_along_track_px: num(&case["sigma_along_track_px"]),
            sigma_depth_px: case["sigma_depth_px"].as_f64(),
            truncate: num(&case["truncate"]),
        };
        let mut ours = img.values.clone();
        gaussian_smooth(&mut ours, img.shape, &params).expect("valid");
        let what = format!(
            "gaussian_filter1d track {} depth {:?}",
            params.sigma_along_track_px, params.sigma_depth_px
        );
        assert_close(&what, &img.pick(&ours, &fx), &floats(&case["expected"]), PEER_RTOL);
    }
}
