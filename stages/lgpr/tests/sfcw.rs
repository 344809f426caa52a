//! The SFCW chain's physics, its window, its high-pass, its errors, and that no input makes it
//! panic.

use std::f64::consts::{PI, TAU};

use gprflow_lgpr::error::ToneIndex;
use gprflow_lgpr::sfcw::{
    DistanceHighPass, FactoryCalibration, InverseTransform, RangeGainParams, SfcwChain, SfcwParams, chebyshev_window,
    tone_weights,
};
use gprflow_lgpr::{Error, Result};
use proptest::prelude::*;
use rustfft::num_complex::Complex64;

const F0_HZ: f64 = 100e6;
const DF_HZ: f64 = 6e6;
const TONES: usize = 51;
const CHANNELS: usize = 11;
/// Round-off allowed on quantities computed exactly in theory.
const EXACT_TOL: f64 = 1e-9;
/// Side-lobe level allowed off the requested attenuation, dB.
const SIDE_LOBE_TOL_DB: f64 = 0.01;

fn frequency_hz(m: usize) -> f64 {
    F0_HZ + m as f64 * DF_HZ
}

fn interleave(tones: impl IntoIterator<Item = Complex64>) -> Vec<f32> {
    tones.into_iter().flat_map(|z| [z.re as f32, z.im as f32]).collect()
}

/// The hardware of a small simulated array: element gain and phase per channel and tone
/// (direct coupling 1), and the calibration path.
struct Hardware {
    gain: Vec<Complex64>,
    cal_path: Vec<Complex64>,
}

impl Hardware {
    fn new() -> Self {
        let gain = (0..CHANNELS * TONES)
            .map(|k| Complex64::from_polar(1.0 + 0.02 * (k / TONES) as f64, 0.3 * (k % TONES) as f64 / TONES as f64))
            .collect();
        let cal_path = (0..TONES)
            .map(|m| Complex64::from_polar(1.0, -TAU * frequency_hz(m) * 1.5e-9))
            .collect();
        Self { gain, cal_path }
    }

    fn factory(&self) -> FactoryCalibration {
        let values = interleave(self.gain.iter().copied());
        FactoryCalibration::new(&values, &interleave(self.cal_path.iter().copied()), CHANNELS, TONES).expect("factory")
    }

    /// A sweep through a receive chain of gain `chain` seeing `scene(m)` on every channel.
    fn sweep(&self, chain: Complex64, scene: impl Fn(usize) -> Complex64) -> (Vec<f32>, Vec<f32>) {
        let values = interleave(
            self.gain
                .iter()
                .enumerate()
                .map(|(k, g)| chain * g * (1.0 + scene(k % TONES))),
        );
        let calibration = interleave(self.cal_path.iter().map(|k| chain * k));
        (values, calibration)
    }
}

/// `a exp(-j 2 pi f_m t)`: a point reflector at two-way time `t_ns`.
fn reflector(amplitude: f64, t_ns: f64) -> impl Fn(usize) -> Complex64 {
    move |m| Complex64::from_polar(amplitude, -TAU * frequency_hz(m) * t_ns * 1e-9)
}

fn chain(params: SfcwParams) -> Result<SfcwChain> {
    SfcwChain::new(params, CHANNELS, TONES, F0_HZ, DF_HZ, Some(Hardware::new().factory()))
}

fn no_gain() -> SfcwParams {
    SfcwParams {
        range_gain: RangeGainParams {
            spreading_exponent: 0.0,
            attenuation_db_per_ns: 0.0,
            ..RangeGainParams::default()
        },
        ..SfcwParams::default()
    }
}

#[test]
fn a_reflector_on_the_sample_grid_peaks_at_its_delay_plus_8_ns_with_its_amplitude() {
    let params = SfcwParams::default();
    let weights = tone_weights(TONES, F0_HZ, DF_HZ, &params).expect("weights");
    let mut transform = InverseTransform::new(TONES, F0_HZ, DF_HZ, 1024, 369).expect("transform");
    let dt = transform.sample_interval_ns();
    assert!((dt - 1e9 / (1024.0 * DF_HZ)).abs() < 1e-12);
    let sample = 200;
    let t_ns = sample as f64 * dt - params.delay_ns;
    let spectrum: Vec<Complex64> = weights
        .iter()
        .enumerate()
        .map(|(m, w)| w * reflector(0.7, t_ns)(m))
        .collect();
    let mut time = vec![0.0; 369];
    transform.process(&spectrum, &mut time).expect("process");
    let peak = (0..time.len())
        .max_by(|&a, &b| time[a].abs().total_cmp(&time[b].abs()))
        .expect("samples");
    assert_eq!(peak, sample);
    assert!(
        (time[sample] - 0.7).abs() < EXACT_TOL,
        "unit-sum window: peak {} != 0.7",
        time[sample]
    );
}

#[test]
fn a_reflector_through_the_chain_appears_at_tau_plus_8_ns() {
    // sweep 0 sees only the direct coupling (the IIR starts from it); sweep 1 a reflector at
    // 20 ns through a receive chain that has drifted: calibration removes the drift, the
    // high-pass the coupling; what is left is beta times the reflector
    let hw = Hardware::new();
    let mut chain = chain(no_gain()).expect("chain");
    let dt = chain.sample_interval_ns();
    let mut out = vec![0.0f32; CHANNELS * chain.out_samples()];
    let (values, cal) = hw.sweep(Complex64::new(1.0, 0.0), |_| Complex64::default());
    chain.process(&values, &cal, 0.0, &mut out).expect("sweep 0");
    assert!(out.iter().all(|&v| v == 0.0), "M_0 = C_0: the first sweep is removed");
    let (t_ns, amplitude, distance_m) = (20.0, 0.05, 0.1);
    let (values, cal) = hw.sweep(Complex64::from_polar(1.05, 0.4), reflector(amplitude, t_ns));
    chain.process(&values, &cal, distance_m, &mut out).expect("sweep 1");
    let beta = (-distance_m / 5.0f64).exp2();
    let expected = ((t_ns + chain.time_zero_ns()) / dt).round() as usize;
    for (ch, trace) in out.chunks_exact(chain.out_samples()).enumerate() {
        let peak = (0..trace.len())
            .max_by(|&a, &b| trace[a].abs().total_cmp(&trace[b].abs()))
            .expect("samples");
        assert!(
            peak.abs_diff(expected) <= 1,
            "channel {ch}: peak at {peak}, expected {expected}"
        );
        let ratio = f64::from(trace[peak]) / (beta * amplitude);
        assert!(
            (0.95..=1.0 + 1e-4).contains(&ratio),
            "channel {ch}: peak {} of {}",
            trace[peak],
            beta * amplitude
        );
    }
}

/// |sum_n w_n exp(-j 2 pi nu n)| at `nu` cycles per tap.
fn window_response(taps: &[f64], nu: f64) -> f64 {
    let z: Complex64 = taps
        .iter()
        .enumerate()
        .map(|(n, w)| Complex64::from_polar(*w, -TAU * nu * n as f64))
        .sum();
    z.norm()
}

#[test]
fn the_chebyshev_window_has_equal_side_lobes_45_db_down() {
    for len in [TONES, 50, 11] {
        let taps = chebyshev_window(len, 45.0).expect("window");
        assert!((taps[len / 2] - 1.0).abs() < EXACT_TOL || (taps[(len - 1) / 2] - 1.0).abs() < EXACT_TOL);
        assert!(
            (0..len).all(|i| (taps[i] - taps[len - 1 - i]).abs() < EXACT_TOL),
            "symmetric"
        );
        let grid = 1 << 14;
        let response: Vec<f64> = (0..=grid)
            .map(|k| window_response(&taps, 0.5 * k as f64 / grid as f64))
            .collect();
        let first_null = (1..grid)
            .find(|&k| response[k + 1] > response[k])
            .expect("main lobe ends");
        let side = response[first_null..].iter().copied().fold(0.0, f64::max);
        let level_db = 20.0 * (side / response[0]).log10();
        assert!(
            (level_db + 45.0).abs() < SIDE_LOBE_TOL_DB,
            "len {len}: side lobes at {level_db} dB"
        );
        // the response is T_n(x0 cos(pi nu)), n = len - 1: its first null is where
        // x0 cos(pi nu) = cos(pi / 2n), the largest zero of T_n
        let order = (len - 1) as f64;
        let x0 = ((10f64.powf(45.0 / 20.0)).acosh() / order).cosh();
        let null_nu = ((PI / (2.0 * order)).cos() / x0).acos() / PI;
        assert!(
            (0.5 * first_null as f64 / grid as f64 - null_nu).abs() < 1e-3,
            "len {len}: first null"
        );
    }
}

#[test]
fn the_high_pass_removes_the_ground_bounce_and_keeps_a_short_feature() {
    // 20 m at 5 cm per sweep; sample 0: a constant (ground bounce); sample 1: the same plus a
    // feature 0.5 m long at 10 m
    let mut filter = DistanceHighPass::new(2, 5.0).expect("filter");
    let (spacing_m, feature) = (0.05, 0.2);
    let mut kept = 0.0f64;
    for i in 0..400 {
        let x_m = i as f64 * spacing_m;
        let bump = if (10.0..10.5).contains(&x_m) { feature } else { 0.0 };
        let mut sweep = [3.0, 3.0 + bump];
        filter.apply(&mut sweep, spacing_m).expect("apply");
        assert!(
            sweep[0].abs() < EXACT_TOL,
            "ground bounce left at {x_m} m: {}",
            sweep[0]
        );
        if bump > 0.0 {
            kept = kept.max(sweep[1]);
        } else if x_m < 10.0 {
            assert!(sweep[1].abs() < EXACT_TOL);
        }
    }
    assert!(kept > 0.9 * feature, "feature kept at {kept} of {feature}");
    // half-life: after 5 m the mean has moved half-way to a new level
    let mut filter = DistanceHighPass::new(1, 5.0).expect("filter");
    filter.apply(&mut [0.0], 0.0).expect("first");
    let mut step = [1.0];
    filter.apply(&mut step, 5.0).expect("5 m");
    assert!((step[0] - 0.5).abs() < EXACT_TOL);
    // at rest (d = 0) the mean holds
    let mut again = [1.0];
    filter.apply(&mut again, 0.0).expect("stopped");
    assert!((again[0] - 0.5).abs() < EXACT_TOL);
}

#[test]
fn the_same_sweeps_give_the_same_output_and_reset_starts_over() {
    let hw = Hardware::new();
    let sweeps: Vec<_> = (0..5)
        .map(|i| {
            hw.sweep(
                Complex64::from_polar(1.0, 0.01 * f64::from(i)),
                reflector(0.02, 10.0 + f64::from(i)),
            )
        })
        .collect();
    let record = |chain: &mut SfcwChain| {
        let mut all = Vec::new();
        for (v, c) in &sweeps {
            let mut out = vec![0.0f32; CHANNELS * chain.out_samples()];
            chain.process(v, c, 0.1, &mut out).expect("process");
            all.extend(out);
        }
        all
    };
    let mut a = chain(SfcwParams::default()).expect("chain");
    let first = record(&mut a);
    a.reset();
    assert_eq!(a.sweeps(), 0);
    assert_eq!(record(&mut a), first);
    let mut b = chain(SfcwParams::default()).expect("chain");
    assert_eq!(record(&mut b), first);
}

#[test]
fn bad_sweeps_are_errors_that_name_the_place_and_leave_the_chain_unchanged() {
    let hw = Hardware::new();
    let mut chain = chain(SfcwParams::default()).expect("chain");
    let mut out = vec![0.0f32; CHANNELS * chain.out_samples()];
    let (values, cal) = hw.sweep(Complex64::new(1.0, 0.0), reflector(0.02, 12.0));

    let err = chain
        .process(&values[1..], &cal, 0.1, &mut out)
        .expect_err("must be refused");
    assert!(matches!(err, Error::Size { what: "values", .. }), "{err}");
    let err = chain
        .process(&values, &cal[2..], 0.1, &mut out)
        .expect_err("must be refused");
    assert!(
        matches!(
            err,
            Error::Size {
                what: "calibration",
                ..
            }
        ),
        "{err}"
    );
    let err = chain
        .process(&values, &cal, 0.1, &mut out[1..])
        .expect_err("must be refused");
    assert!(matches!(err, Error::Size { what: "out", .. }), "{err}");

    let mut bad = values.clone();
    bad[(2 * TONES + 7) * 2 + 1] = f32::NAN;
    let err = chain.process(&bad, &cal, 0.1, &mut out).expect_err("must be refused");
    let at = ToneIndex {
        channel: Some(2),
        tone: 7,
    };
    assert!(
        matches!(err, Error::NonFinite { what: "values", at: a, .. } if a == at),
        "{err}"
    );
    assert!(err.to_string().contains("channel 2 tone 7"), "{err}");

    let mut bad = cal.clone();
    bad[6] = f32::INFINITY;
    let err = chain
        .process(&values, &bad, 0.1, &mut out)
        .expect_err("must be refused");
    assert!(
        matches!(
            err,
            Error::NonFinite {
                what: "calibration",
                at: ToneIndex { channel: None, tone: 3 },
                ..
            }
        ),
        "{err}"
    );
    bad[6] = 0.0;
    bad[7] = 0.0;
    let err = chain
        .process(&values, &bad, 0.1, &mut out)
        .expect_err("must be refused");
    assert!(
        matches!(
            err,
            Error::ZeroDivisor {
                at: ToneIndex { channel: None, tone: 3 },
                ..
            }
        ),
        "{err}"
    );

    chain.process(&values, &cal, 0.0, &mut out).expect("sweep 0");
    for d in [-0.01, f64::NAN, f64::INFINITY] {
        let err = chain.process(&values, &cal, d, &mut out).expect_err("must be refused");
        assert!(matches!(err, Error::Distance { sweep: 1, .. }), "{err}");
        assert!(err.to_string().contains("sweep 1"), "{err}");
    }
    assert_eq!(chain.sweeps(), 1, "errors leave the chain as it was");
    let (moved, cal2) = hw.sweep(Complex64::new(1.0, 0.0), reflector(0.02, 13.0));
    chain.process(&moved, &cal2, 0.1, &mut out).expect("sweep 1");
    let mut clean = self::chain(SfcwParams::default()).expect("chain");
    let mut reference = vec![0.0f32; out.len()];
    clean.process(&values, &cal, 0.0, &mut reference).expect("sweep 0");
    clean.process(&moved, &cal2, 0.1, &mut reference).expect("sweep 1");
    assert_eq!(out, reference);
}

fn param_key(result: Result<SfcwChain>) -> String {
    match result {
        Err(Error::Param(e)) => e.key(),
        other => panic!("expected a parameter error, got {other:?}"),
    }
}

#[test]
fn bad_parameters_are_errors_that_name_the_key() {
    let with = |f: fn(&mut SfcwParams)| {
        let mut p = SfcwParams::default();
        f(&mut p);
        chain(p)
    };
    assert_eq!(param_key(with(|p| p.keep_samples = 0)), "keep_samples");
    assert_eq!(param_key(with(|p| p.keep_samples = 2000)), "keep_samples");
    assert_eq!(param_key(with(|p| p.time_samples = 50)), "time_samples");
    assert_eq!(param_key(with(|p| p.iir_distance_m = 0.0)), "iir_distance_m");
    assert_eq!(param_key(with(|p| p.iir_distance_m = f64::NAN)), "iir_distance_m");
    assert_eq!(
        param_key(with(|p| p.window_attenuation_db = -3.0)),
        "window_attenuation_db"
    );
    assert_eq!(param_key(with(|p| p.delay_ns = f64::INFINITY)), "delay_ns");
    assert_eq!(
        param_key(with(|p| p.range_gain.reference_ns = 0.0)),
        "range_gain.reference_ns"
    );
    assert_eq!(
        param_key(with(|p| p.range_gain.spreading_exponent = -1.0)),
        "range_gain.spreading_exponent"
    );
    assert_eq!(
        param_key(with(|p| p.range_gain.attenuation_db_per_ns = 1e6)),
        "range_gain"
    );
    let factory = Some(Hardware::new().factory());
    assert_eq!(
        param_key(SfcwChain::new(SfcwParams::default(), 10, TONES, F0_HZ, DF_HZ, factory)),
        "factory"
    );
    assert_eq!(
        param_key(SfcwChain::new(SfcwParams::default(), 0, TONES, F0_HZ, DF_HZ, None)),
        "channel_count"
    );
    assert_eq!(
        param_key(SfcwChain::new(SfcwParams::default(), 1, TONES, F0_HZ, 0.0, None)),
        "frequency_step_hz"
    );
    assert_eq!(
        param_key(SfcwChain::new(SfcwParams::default(), 1, 0, F0_HZ, DF_HZ, None)),
        "bin_count"
    );
    assert_eq!(
        param_key(SfcwChain::new(SfcwParams::default(), 2000, TONES, F0_HZ, DF_HZ, None)),
        "channel_count"
    );
    assert_eq!(
        param_key(SfcwChain::new(
            SfcwParams {
                time_samples: 8192,
                ..SfcwParams::default()
            },
            1,
            5000,
            F0_HZ,
            DF_HZ,
            None
        )),
        "bin_count"
    );
}

#[test]
fn a_zero_factory_ratio_is_an_error() {
    let hw = Hardware::new();
    let mut values = interleave(hw.gain.iter().copied());
    values[(4 * TONES + 9) * 2] = 0.0;
    values[(4 * TONES + 9) * 2 + 1] = 0.0;
    let err = FactoryCalibration::new(&values, &interleave(hw.cal_path.iter().copied()), CHANNELS, TONES)
        .expect_err("must be refused");
    assert!(
        matches!(
            err,
            Error::ZeroDivisor {
                at: ToneIndex {
                    channel: Some(4),
                    tone: 9
                },
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn params_parse_with_defaults_and_refuse_unknown_keys() {
    let p: SfcwParams =
        serde_json::from_str(r#"{"keep_samples": 512, "range_gain": {"reference_ns": 3}}"#).expect("parse");
    assert_eq!(p.keep_samples, 512);
    assert_eq!(p.range_gain.reference_ns, 3.0);
    assert_eq!(p.range_gain.spreading_exponent, 1.0);
    assert_eq!(p.delay_ns, 8.0);
    assert_eq!(
        serde_json::from_str::<SfcwParams>("{}").expect("empty"),
        SfcwParams::default()
    );
    let err = serde_json::from_str::<SfcwParams>(r#"{"delay": 8}"#).expect_err("must be refused");
    assert!(err.to_string().contains("delay"), "{err}");
    assert!(serde_json::from_str::<SfcwParams>(r#"{"range_gain": {"alpha": 1}}"#).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn no_sweep_makes_the_chain_panic(
        values in prop::collection::vec(any::<f32>(), 0..1300),
        calibration in prop::collection::vec(any::<f32>(), 0..120),
        distance_m in any::<f64>(),
        out_len in 0usize..5000,
    ) {
        let mut chain = chain(SfcwParams::default()).expect("chain");
        let mut out = vec![0.0f32; out_len];
        let _ = chain.process(&values, &calibration, distance_m, &mut out);
    }

    #[test]
    fn sweeps_of_the_right_shape_give_finite_output_or_an_error(
        values in prop::collection::vec(-1e30f32..1e30, CHANNELS * TONES * 2),
        calibration in prop::collection::vec(-1e3f32..1e3, TONES * 2),
        distance_m in 0.0f64..10.0,
    ) {
        let mut chain = chain(SfcwParams::default()).expect("chain");
        let mut out = vec![0.0f32; CHANNELS * chain.out_samples()];
        for _ in 0..2 {
            if chain.process(&values, &calibration, distance_m, &mut out).is_ok() {
                prop_assert!(out.iter().all(|v| v.is_finite()));
            }
        }
    }

    #[test]
    fn no_parameters_make_the_chain_panic(
        channels in 0usize..4,
        bins in 0usize..80,
        start_hz in any::<f64>(),
        step_hz in any::<f64>(),
        time_samples in 0usize..3000,
        keep_samples in 0usize..3000,
        delay_ns in any::<f64>(),
        attenuation_db in any::<f64>(),
        iir_distance_m in any::<f64>(),
        exponent in any::<f64>(),
        reference_ns in any::<f64>(),
        alpha in any::<f64>(),
    ) {
        let params = SfcwParams {
            delay_ns,
            window_attenuation_db: attenuation_db,
            time_samples,
            keep_samples,
            iir_distance_m,
            range_gain: RangeGainParams { spreading_exponent: exponent, reference_ns, attenuation_db_per_ns: alpha },
        };
        let _ = SfcwChain::new(params, channels, bins, start_hz, step_hz, None);
        let _ = chebyshev_window(bins, attenuation_db);
    }

    #[test]
    fn no_factory_sweep_makes_it_panic(
        values in prop::collection::vec(any::<f32>(), 0..300),
        calibration in prop::collection::vec(any::<f32>(), 0..40),
        channels in 0usize..6,
        bins in 0usize..30,
    ) {
        let _ = FactoryCalibration::new(&values, &calibration, channels, bins);
    }
}
