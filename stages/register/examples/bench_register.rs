//! The learned registration model's benchmark, as `tools/peer/bench_register.sh` runs it: on
//! one thread, the encoder (standardisation, front end, ONNX Runtime through `ort`, copy-out)
//! per submap, the front end alone, and the correlation plus head (`Model::register`) per pair, each the median over many
//! iterations; prints a JSON report.
//!
//! usage: bench_register <submaps.f32> [--rows 201] [--cols 200] [--resolution-m 0.015]
//!        [--model stages/register/models/ground_encoding.onnx]
//!        [--head stages/register/models/ground_encoding.head.json] [--ort-library PATH]
//!        [--iterations 2000] [--output features.f32]
//!
//! `submaps.f32`: raw little-endian f32 submaps (`rows x cols` each, row-major, ground order);
//! the pairs are consecutive submaps (0, 1), (1, 2), ... `--output` writes the features of
//! every submap there, for the Python side to compare.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use gprflow_register::SubmapView;
use gprflow_register::front_end::FrontEndScratch;
use gprflow_register::learned::{Features, Model};

struct Args {
    input: PathBuf,
    rows: usize,
    cols: usize,
    resolution_m: f64,
    model: PathBuf,
    head: PathBuf,
    ort_library: Option<PathBuf>,
    iterations: usize,
    output: Option<PathBuf>,
}

fn parse() -> Result<Args, Box<dyn std::error::Error>> {
    let mut it = std::env::args().skip(1);
    let mut input = None;
    let mut args = Args {
        input: PathBuf::new(),
        rows: 201,
        cols: 200,
        resolution_m: 0.015,
        model: "stages/register/models/ground_encoding.onnx".into(),
        head: "stages/register/models/ground_encoding.head.json".into(),
        ort_library: None,
        iterations: 2000,
        output: None,
    };
    while let Some(a) = it.next() {
        let mut value = || it.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--rows" => args.rows = value()?.parse()?,
            "--cols" => args.cols = value()?.parse()?,
            "--resolution-m" => args.resolution_m = value()?.parse()?,
            "--model" => args.model = value()?.into(),
            "--head" => args.head = value()?.into(),
            "--ort-library" => args.ort_library = Some(value()?.into()),
            "--iterations" => args.iterations = value()?.parse()?,
            "--output" => args.output = Some(value()?.into()),
            _ if input.is_none() && !a.starts_with('-') => input = Some(PathBuf::from(a)),
            _ => return Err(format!("unknown argument {a}").into()),
        }
    }
    args.input = input.ok_or("usage: bench_register <submaps.f32> [--rows N] [--cols N] [--model F] [--head F]")?;
    Ok(args)
}

/// Median, 90th percentile and minimum of `samples_ms`, ms.
fn summary(mut samples_ms: Vec<f64>) -> serde_json::Value {
    samples_ms.sort_by(f64::total_cmp);
    let at = |q: f64| samples_ms[((samples_ms.len() - 1) as f64 * q).round() as usize];
    serde_json::json!({
        "median_ms": at(0.5), "p90_ms": at(0.9), "min_ms": at(0.0), "iterations": samples_ms.len(),
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse()?;
    let bytes = std::fs::read(&args.input)?;
    let pixels: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let per = args.rows * args.cols;
    if per == 0 || !pixels.len().is_multiple_of(per) || pixels.len() < 2 * per {
        return Err(format!(
            "{}: {} values, not two or more {} x {} submaps",
            args.input.display(),
            pixels.len(),
            args.rows,
            args.cols
        )
        .into());
    }
    let submaps: Vec<SubmapView<'_>> = pixels
        .chunks_exact(per)
        .map(|p| SubmapView {
            pixels: p,
            rows: args.rows,
            cols: args.cols,
            resolution_m: args.resolution_m,
        })
        .collect();
    let mut model = Model::load(&args.model, &args.head, args.ort_library.as_deref())?;
    let iterations = args.iterations.max(1);

    // encoder: warm up, then one submap per iteration, cycling through them
    let mut features: Vec<Features> = submaps.iter().map(|s| model.encode(s)).collect::<Result<_, _>>()?;
    let mut scratch = Features::default();
    for s in submaps.iter().cycle().take(50) {
        model.encode_into(s, &mut scratch)?;
    }
    let mut encode_ms = Vec::with_capacity(iterations);
    for s in submaps.iter().cycle().take(iterations) {
        let t = Instant::now();
        model.encode_into(s, &mut scratch)?;
        encode_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    std::hint::black_box(&scratch);

    // the front end alone (part of the encoder's time above), on standardised copies
    let front_end = model.encoder.front_end();
    let mut front = FrontEndScratch::default();
    let mut image: Vec<f32> = Vec::with_capacity(per);
    let mut front_end_ms = Vec::with_capacity(iterations);
    for s in submaps.iter().cycle().take(iterations) {
        image.clear();
        image.extend_from_slice(s.pixels);
        let t = Instant::now();
        front.apply(front_end, &mut image, args.rows, args.cols)?;
        front_end_ms.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(&image);
    }

    // correlation + head, and the correlation alone, per consecutive pair
    let pairs: Vec<(usize, usize)> = (0..features.len() - 1).map(|i| (i, i + 1)).collect();
    let mut registered = 0usize;
    for &(a, b) in pairs.iter().cycle().take(50) {
        std::hint::black_box(model.register(&features[a], &features[b], args.resolution_m)?);
    }
    let mut register_ms = Vec::with_capacity(iterations);
    for &(a, b) in pairs.iter().cycle().take(iterations) {
        let t = Instant::now();
        let m = model.register(&features[a], &features[b], args.resolution_m)?;
        register_ms.push(t.elapsed().as_secs_f64() * 1e3);
        registered += usize::from(m.is_some());
    }
    let mut correlate_ms = Vec::with_capacity(iterations);
    for &(a, b) in pairs.iter().cycle().take(iterations) {
        let t = Instant::now();
        std::hint::black_box(model.correlate(&features[a], &features[b], args.resolution_m)?);
        correlate_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let first = model.register(&features[0], &features[1], args.resolution_m)?;

    if let Some(path) = &args.output {
        let out: Vec<u8> = features
            .iter_mut()
            .flat_map(|f| std::mem::take(&mut f.data))
            .flat_map(f32::to_le_bytes)
            .collect();
        std::fs::write(path, out)?;
    }
    let f = &scratch;
    let report = serde_json::json!({
        "model": args.model, "head": args.head, "submaps": submaps.len(),
        "submap": [args.rows, args.cols], "features": [f.channels, f.rows, f.cols],
        "feature_values": f.channels * f.rows * f.cols,
        "shifts_tried": 2 * model.head.correlation_params(args.resolution_m).max_shift_cols(f.cols) + 1,
        "threads": 1,
        "encoder": summary(encode_ms),
        "front_end": format!("{front_end:?}"),
        "front_end_only": summary(front_end_ms),
        "correlation_and_head": summary(register_ms),
        "correlation_only": summary(correlate_ms),
        "pairs_registered": registered, "pairs_timed": iterations,
        "first_pair": first.map(|m| serde_json::json!({"shift_m": m.shift_m, "share_score": m.share_score})),
    });
    writeln!(std::io::stdout().lock(), "{}", serde_json::to_string(&report)?)?;
    Ok(())
}
