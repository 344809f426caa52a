//! Property tests: the filters and the chain never panic on arbitrary lengths and values;
//! bad input is an error.

use gprflow_dsp::Error;
use gprflow_dsp::chain::{ChainParams, TraceChain};
use gprflow_dsp::image::{GaussianParams, Shape, WaveletDenoiseParams, denoise_wavelet, gaussian_smooth};
use gprflow_dsp::trace::{ZeroTimeParams, shift_to_zero_time, zero_time_index};
use proptest::prelude::*;

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        8 => -40_000.0_f32..40_000.0,
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(0.0_f32),
    ]
}

proptest! {
    #[test]
    fn chain_never_panics(
        (samples, trace) in (0_usize..300)
            .prop_flat_map(|n| (Just(n), prop::collection::vec(any_f32(), n.saturating_sub(1)..=n + 1))),
        dt_ns in prop_oneof![Just(0.2), -1.0_f64..2.0],
    ) {
        match TraceChain::new(&ChainParams::default(), samples, dt_ns, 500e6) {
            Ok(mut chain) => {
                let mut t = trace.clone();
                match chain.process(&mut t) {
                    Ok(shift) => {
                        prop_assert_eq!(trace.len(), samples);
                        prop_assert!(trace.iter().all(|v| v.is_finite()));
                        prop_assert!(shift.is_none_or(|k| k < samples));
                        prop_assert!(t.iter().all(|v| v.is_finite()));
                    }
                    Err(Error::Size { .. }) => prop_assert_ne!(trace.len(), samples),
                    Err(Error::NonFinite { index, .. }) => prop_assert!(!trace[index].is_finite()),
                    Err(e) => prop_assert!(false, "unexpected {e}"),
                }
            }
            Err(Error::Param(_)) => {}
            Err(e) => prop_assert!(false, "unexpected {e}"),
        }
    }

    #[test]
    fn zero_time_index_is_in_range(trace in prop::collection::vec(any_f32(), 0..64), threshold in 0.01_f64..1.0) {
        let p = ZeroTimeParams { threshold };
        let mut t = trace.clone();
        if let Some(k) = zero_time_index(&trace, &p) {
            prop_assert!(k < trace.len());
            prop_assert!(trace[k] < 0.0);
            shift_to_zero_time(&mut t, k);
            prop_assert_eq!(t[0].to_bits(), trace[k].to_bits());
        }
    }

    #[test]
    fn image_filters_never_panic(
        rows in 0_usize..40,
        cols in 0_usize..40,
        values in prop::collection::vec(-1.0_f32..1.0, 0..1600),
        wavelet in prop_oneof![Just("haar"), Just("db2"), Just("db4")],
    ) {
        let shape = Shape::new(rows, cols);
        let params = WaveletDenoiseParams {
            wavelet: serde_json::from_value(serde_json::json!(wavelet)).expect("wavelet"),
            levels: None,
        };
        let mut img = values.clone();
        let ok = denoise_wavelet(&mut img, shape, &params).is_ok();
        prop_assert_eq!(ok, values.len() == rows * cols && rows * cols > 0);
        if ok {
            prop_assert!(img.iter().all(|v| v.is_finite()));
        }
        let mut img = values.clone();
        let ok = gaussian_smooth(&mut img, shape, &GaussianParams { sigma_depth_px: Some(1.0), ..GaussianParams::default() }).is_ok();
        prop_assert_eq!(ok, values.len() == rows * cols);
    }
}

/// An image with no rows or no columns (the case the property test above once drew) smooths
/// to nothing instead of dividing by zero in the reflection.
#[test]
fn gaussian_smooth_of_an_empty_image_is_fine() {
    for (rows, cols) in [(0, 5), (5, 0), (0, 0)] {
        let mut img: Vec<f32> = Vec::new();
        let params = GaussianParams {
            sigma_depth_px: Some(1.0),
            sigma_along_track_px: 1.0,
            ..GaussianParams::default()
        };
        assert!(gaussian_smooth(&mut img, Shape::new(rows, cols), &params).is_ok());
    }
}
