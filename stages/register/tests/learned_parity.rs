//! Parity of the learned registration model with its training side (tools/train/SPEC.md): the
//! encoder's features (ONNX Runtime through `ort` vs Python onnxruntime), the correlation vector
//! and both heads' outputs, on the committed fixtures; and clear errors on bad input.
//!
//! Needs ONNX Runtime's library: `GPRFLOW_ONNXRUNTIME`, else `.onnxruntime/` at the repository
//! root, where `tools/scripts/ensure-onnxruntime.sh` puts it. Without it these tests fail.

mod common;

use std::path::{Path, PathBuf};

use common::{ort_library, read_f32, repo_root};
use gprflow_register::Error;
use gprflow_register::SubmapView;
use gprflow_register::learned::{CorrelationParams, Correlator, Encoder, Features, Head, Model, correlate};
use serde_json::Value;

/// The end-to-end head output (our features, our correlation vector, the head) may differ from
/// the fixture's by the encoder's f32 differences carried through the argmax refinement: m.
const END_TO_END_M: f64 = 1e-4;

/// A stand-in model with random weights: the same contract on files of a few kilobytes.
const TINY: &str = "stages/register/tests/fixtures/tiny/manifest.json";

/// The trained model's parity fixtures (tools/train/train.py writes them).
const LEARNED: &str = "stages/register/tests/fixtures/learned/manifest.json";

/// `max |got - want| <= tolerance * max |want|` (the fixtures' rule), with the worst index.
fn assert_close(what: &str, got: &[f64], want: &[f64], tolerance: f64) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let (worst, err) = got
        .iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs())
        .enumerate()
        .fold((0, 0.0), |(bi, be), (i, e)| if e > be { (i, e) } else { (bi, be) });
    assert!(
        err <= tolerance * scale,
        "{what}: max error {err:.3e} at [{worst}] (got {}, want {}) over {tolerance:.0e} x {scale:.3e}",
        got[worst],
        want[worst]
    );
}

fn as_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

fn number(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("manifest: {key}"))
}

fn count(v: &Value, key: &str) -> usize {
    v[key].as_u64().unwrap_or_else(|| panic!("manifest: {key}")) as usize
}

/// Every case of a fixture manifest: features, correlation vector, both heads, the decision.
fn check_manifest(manifest: &Path) {
    let root = repo_root();
    let dir = manifest.parent().expect("a folder");
    let text = std::fs::read_to_string(manifest).unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
    let m: Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
    assert_eq!(m["format"], "gprflow-learned-fixtures");
    let tolerance = number(&m, "tolerance");
    let onnx = root.join(m["model"].as_str().expect("model"));
    let linear = root.join(m["heads"]["linear"].as_str().expect("heads.linear"));
    let nonlinear = Head::from_json(&root.join(m["heads"]["nonlinear"].as_str().expect("heads.nonlinear")))
        .expect("nonlinear head");
    let lib = ort_library();
    let mut model = Model::load(&onnx, &linear, Some(&lib)).expect("model");
    let cases = m["cases"].as_array().expect("cases");
    assert!(!cases.is_empty());
    for case in cases {
        let name = case["name"].as_str().expect("name");
        let (rows, cols, resolution_m) = (count(case, "rows"), count(case, "cols"), number(case, "resolution_m"));
        let shape: Vec<usize> = case["features_shape"]
            .as_array()
            .expect("features_shape")
            .iter()
            .map(|d| d.as_u64().expect("dim") as usize)
            .collect();
        let file = |role: &str| dir.join(case[role]["file"].as_str().unwrap_or_else(|| panic!("{name}: {role}")));
        let expected_features = |role: &str| Features {
            channels: shape[0],
            rows: shape[1],
            cols: shape[2],
            data: read_f32(&file(role)),
        };
        let mut ours = Vec::new();
        for role in ["reference", "query"] {
            let pixels = read_f32(&file(role));
            let submap = SubmapView {
                pixels: &pixels,
                rows,
                cols,
                resolution_m,
            };
            let got = model.encode(&submap).unwrap_or_else(|e| panic!("{name} {role}: {e}"));
            let want = expected_features(&format!("{role}_features"));
            assert_eq!(
                (got.channels, got.rows, got.cols),
                (want.channels, want.rows, want.cols),
                "{name} {role}: feature shape"
            );
            assert_close(
                &format!("{name} {role} features"),
                &as_f64(&got.data),
                &as_f64(&want.data),
                tolerance,
            );
            ours.push(got);
        }
        let want_v: Vec<f64> = case["correlation"]
            .as_array()
            .expect("correlation")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect();
        // the correlation of the fixture's own features: the Rust correlation alone
        let (fr, fq) = (
            expected_features("reference_features"),
            expected_features("query_features"),
        );
        let v = model.correlate(&fr, &fq, resolution_m).expect("correlate");
        assert_close(&format!("{name} correlation vector"), &v.values, &want_v, tolerance);
        // both heads alone, on the fixture's vector
        let (want_linear, want_nonlinear) = (number(case, "linear_m"), number(case, "nonlinear_m"));
        assert_close(
            &format!("{name} linear head"),
            &[model.head.predict(&want_v)],
            &[want_linear],
            tolerance,
        );
        assert_close(
            &format!("{name} nonlinear head"),
            &[nonlinear.predict(&want_v)],
            &[want_nonlinear],
            tolerance,
        );
        // end to end: our features, our correlation, the decision and the shift
        let ours_v = model.correlate(&ours[0], &ours[1], resolution_m).expect("correlate");
        assert_close(
            &format!("{name} correlation of our features"),
            &ours_v.values,
            &want_v,
            tolerance,
        );
        let registered = model.register(&ours[0], &ours[1], resolution_m).expect("register");
        // `registered`: both checks (share threshold and channel agreement); fixtures of heads
        // without an agreement check have only `shares`
        let want = case.get("registered").unwrap_or(&case["shares"]);
        assert_eq!(
            registered.is_some(),
            want.as_bool().expect("registered"),
            "{name}: registered"
        );
        if let (Some(check), Some(want_agreement)) = (model.head.agreement, case.get("agreement")) {
            let fraction = check.fraction(&ours_v, want_linear);
            let want_agreement = want_agreement.as_f64().expect("agreement");
            assert_eq!(fraction, want_agreement, "{name}: agreement");
        }
        if let Some(r) = registered {
            assert!(
                (r.shift_m - want_linear).abs() <= END_TO_END_M,
                "{name}: {} vs {want_linear}",
                r.shift_m
            );
            assert!((r.share_score - number(case, "mean_peak")).abs() <= tolerance);
            assert_eq!(r.variance_m2, model.head.sigma_m.powi(2));
        }
    }
}

#[test]
fn tiny_model_matches_its_fixtures() {
    check_manifest(&repo_root().join(TINY));
}

#[test]
fn trained_model_matches_its_fixtures() {
    check_manifest(&repo_root().join(LEARNED));
}

fn tiny(name: &str) -> PathBuf {
    repo_root().join("stages/register/tests/fixtures/tiny").join(name)
}

#[test]
fn a_missing_or_foreign_model_file_is_a_clear_error() {
    let lib = ort_library();
    let missing = tiny("no_such_model.onnx");
    let e = Encoder::load(&missing, Some(&lib)).expect_err("missing");
    assert!(matches!(e, Error::Onnx { .. }), "{e:?}");
    assert!(e.to_string().contains("no_such_model.onnx: no such model file"), "{e}");
    // a JSON file is no ONNX model
    let foreign = tiny("tiny.head.json");
    let e = Encoder::load(&foreign, Some(&lib)).expect_err("not ONNX");
    assert!(matches!(e, Error::Onnx { .. }), "{e:?}");
    assert!(e.to_string().contains("tiny.head.json: ONNX Runtime:"), "{e}");
    let e = Model::load(&tiny("tiny_encoder.onnx"), &tiny("nope.json"), Some(&lib)).expect_err("no head");
    assert!(matches!(e, Error::Io { .. }), "{e:?}");
    assert!(e.to_string().contains("nope.json"), "{e}");
}

#[test]
fn a_head_fitted_on_another_encoder_is_refused() {
    let lib = ort_library();
    let root = repo_root();
    let head = root.join("stages/register/models/ground_encoding.head.json");
    let text = std::fs::read_to_string(&head).expect("head");
    let json: Value = serde_json::from_str(&text).expect("head JSON");
    let crc = json["encoder_crc32"]
        .as_str()
        .expect("the committed head names its encoder's CRC-32");
    // with its own encoder it loads (trained_model_matches_its_fixtures runs it)
    Model::load(
        &root.join("stages/register/models/ground_encoding.onnx"),
        &head,
        Some(&lib),
    )
    .expect("own encoder");
    // with another encoder file (same shape or not) it is refused, naming both files
    let e = Model::load(&tiny("tiny_encoder.onnx"), &head, Some(&lib)).expect_err("another encoder");
    assert!(matches!(e, Error::Head { .. }), "{e:?}");
    let message = e.to_string();
    assert!(
        message.contains("ground_encoding.head.json: encoder_crc32"),
        "{message}"
    );
    assert!(
        message.contains(crc) && message.contains("tiny_encoder.onnx has "),
        "{message}"
    );
    // a head naming no encoder is not checked (heads written before the field existed)
    let unchecked = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("head_without_encoder_crc32.json");
    let mut json = json;
    json.as_object_mut().expect("object").remove("encoder_crc32");
    std::fs::write(&unchecked, serde_json::to_string(&json).expect("JSON")).expect("write");
    Model::load(&tiny("tiny_encoder.onnx"), &unchecked, Some(&lib))
        .expect("a head without the field loads with any encoder");
}

#[test]
fn a_missing_runtime_library_names_the_path_and_the_script() {
    let e = Encoder::load(
        &tiny("tiny_encoder.onnx"),
        Some(Path::new("/nonexistent/libonnxruntime.so.1.31.1")),
    )
    .expect_err("no library");
    assert!(matches!(e, Error::OnnxRuntime { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(msg.contains("/nonexistent/libonnxruntime.so.1.31.1"), "{msg}");
    assert!(msg.contains("tools/scripts/ensure-onnxruntime.sh"), "{msg}");
}

#[test]
fn bad_submaps_and_mismatched_heads_are_refused() {
    let lib = ort_library();
    let mut model = Model::load(&tiny("tiny_encoder.onnx"), &tiny("tiny.head.json"), Some(&lib)).expect("model");
    let mut pixels = vec![1.0f32; 24 * 40];
    for (i, p) in pixels.iter_mut().enumerate() {
        *p = (i % 7) as f32;
    }
    let ok = SubmapView {
        pixels: &pixels,
        rows: 24,
        cols: 40,
        resolution_m: 0.015,
    };
    let features = model.encode(&ok).expect("encodes");
    assert_eq!((features.channels, features.rows, features.cols), (3, 12, 20));
    // an odd width: ceil(41 / 2) columns
    let wide = vec![0.5f32; 24 * 41];
    let f = model
        .encode(&SubmapView {
            pixels: &wide,
            cols: 41,
            ..ok
        })
        .expect("encodes");
    assert_eq!(f.cols, 21);
    // NaN and infinite pixels
    let mut bad = pixels.clone();
    bad[3 * 40 + 7] = f32::NAN;
    let e = model.encode(&SubmapView { pixels: &bad, ..ok }).expect_err("NaN");
    assert!(matches!(e, Error::Pixels { row: 3, col: 7, .. }), "{e:?}");
    assert!(
        e.to_string().contains("submap pixels[127] (row 3, col 7) is NaN"),
        "{e}"
    );
    bad[3 * 40 + 7] = f32::INFINITY;
    assert!(matches!(
        model.encode(&SubmapView { pixels: &bad, ..ok }),
        Err(Error::Pixels { .. })
    ));
    // a pixel count that is not rows x cols
    let e = model
        .encode(&SubmapView {
            pixels: &pixels[..100],
            ..ok
        })
        .expect_err("short");
    assert!(e.to_string().contains("submap: 100 pixels for 24 x 40"), "{e}");
    // features the head was not made for
    let other = Features {
        channels: 2,
        rows: 12,
        cols: 20,
        data: vec![0.0; 2 * 12 * 20],
    };
    let e = model.register(&other, &other, 0.015).expect_err("channels");
    assert!(e.to_string().contains("2 channels, the head 3"), "{e}");
    let e = model.register(&features, &f, 0.015).expect_err("widths");
    assert!(
        e.to_string().contains("3 x 12 x 20") && e.to_string().contains("3 x 12 x 21"),
        "{e}"
    );
    // a head whose channel count the encoder does not give
    let text = std::fs::read_to_string(tiny("tiny.head.json"))
        .expect("head")
        .replace("\"channels\": 3", "\"channels\": 2");
    assert!(text.contains("\"channels\": 2"));
    let e = Head::parse(&text, Path::new("tiny.head.json")).expect_err("2K inputs");
    assert!(
        e.to_string()
            .contains("tiny.head.json: normalise.mean: 6 values, expected 4"),
        "{e}"
    );
}

#[test]
fn registering_a_submap_on_itself_gives_no_shift() {
    let mut model = Model::load(
        &tiny("tiny_encoder.onnx"),
        &tiny("tiny.head.json"),
        Some(&ort_library()),
    )
    .expect("model");
    let pixels = read_f32(&tiny("shifted.reference.f32"));
    let submap = SubmapView {
        pixels: &pixels,
        rows: 24,
        cols: 40,
        resolution_m: 0.015,
    };
    let f = model.encode(&submap).expect("encodes");
    let v = model.correlate(&f, &f, 0.015).expect("correlates");
    assert!(v.tau_m().iter().all(|&t| t.abs() < 1e-12), "{:?}", v.tau_m());
    assert!(v.peaks().iter().all(|&m| (m - 1.0).abs() < 1e-9), "{:?}", v.peaks());
    let r = model.register(&f, &f, 0.015).expect("valid").expect("shares");
    assert_eq!(r.corr, v.values);
    // the free function and a reused correlator agree with the model's
    let p = CorrelationParams {
        column_m: 0.03,
        max_shift_m: model.head.max_shift_m,
        min_overlap: model.head.min_overlap,
    };
    assert_eq!(correlate(&f, &f, &p).expect("valid").values, v.values);
    assert_eq!(
        Correlator::default().correlate(&f, &f, &p).expect("valid").values,
        v.values
    );
}
