//! The processing chains: traces through dsp into submaps resampled by wheel distance,
//! simulated LGPR sweeps into range profiles, a real DZT line into submaps, unusable traces
//! dropped while the run goes on.

use crate::common::stderr;
use crate::ingest::real_gpr;
use crate::{decode_all, launch_recorded};

#[test]
fn submap_pipeline_resamples_a_simulated_run_by_wheel_distance() {
    use gprflow::msg::Submap;
    let dir = tempfile::tempdir().expect("tempdir");
    // a submap every 0.1 m, not 0.02 m: a fifth of the data to write and read
    let (p, _) = launch_recorded(dir.path(), "graphs/submaps.yaml", &["spacing_m=0.1".into()]);
    let raw: Vec<Submap> = decode_all(&p["/submap/submap"]);
    let filtered: Vec<Submap> = decode_all(&p["/filter/submap"]);
    // 60 s, 27 m with three corners: submaps every 0.1 m once 3 m are covered, none across
    // a corner (the gyro rule)
    assert!(raw.len() > 80, "{} submaps", raw.len());
    assert_eq!(raw.len(), filtered.len());
    for (r, f) in raw.iter().zip(&filtered) {
        assert!(r.valid && f.valid);
        assert_eq!((r.rows, r.cols, r.id), (f.rows, f.cols, f.id));
        assert_eq!((r.rows, r.cols), (201, 200));
        assert!((r.resolution_m - 0.015).abs() < 1e-12);
        assert!(
            (r.end_distance_m - r.start_distance_m - 199.0 * 0.015).abs() < 1e-6,
            "{}",
            r.id
        );
        assert!(r.header.stamp.to_ns() > r.start_stamp.to_ns());
        assert!(f.pixels.iter().all(|v| v.is_finite()));
        assert!(f.saliency.is_finite() && f.saliency > 0.0);
    }
    // consecutive valid submaps: 0.1 m apart (to a column)
    let steps: Vec<f64> = raw
        .windows(2)
        .filter(|w| w[1].id == w[0].id + 1)
        .map(|w| w[1].start_distance_m - w[0].start_distance_m)
        .collect();
    assert!(steps.len() > 60);
    assert!(steps.iter().all(|s| (s - 0.1).abs() <= 0.015 + 1e-9), "{steps:?}");
    // the filtered submaps differ from the raw ones (background, wavelet, gaussian ran)
    assert!(raw[0].pixels != filtered[0].pixels);
    // prior-mean background: the first submap's own mean trace is removed
    let f0 = &filtered[0];
    let cols = f0.cols as usize;
    let mean_abs_row_mean = (0..f0.rows as usize)
        .map(|r| (f0.pixels[r * cols..(r + 1) * cols].iter().sum::<f32>() / cols as f32).abs())
        .sum::<f32>()
        / f0.rows as f32;
    let mean_abs = f0.pixels.iter().map(|v| v.abs()).sum::<f32>() / f0.pixels.len() as f32;
    assert!(mean_abs_row_mean < 0.2 * mean_abs, "{mean_abs_row_mean} vs {mean_abs}");
}

#[test]
fn lgpr_sweep_chain_turns_simulated_sweeps_into_high_passed_range_profiles() {
    use gprflow::msg::Sweep;
    let dir = tempfile::tempdir().expect("tempdir");
    let (p, _) = launch_recorded(dir.path(), "graphs/lgpr-sweeps.yaml", &[]);
    let out: Vec<Sweep> = decode_all(&p["/lgpr/sweep"]);
    // every one of the 5 s x 126 Hz sweeps, none waiting on the factory calibration
    assert_eq!(out.len(), 631);
    let t0 = out[0].header.stamp.to_ns();
    let mut still = 0.0f32;
    let mut moving = 0.0f32;
    for s in &out {
        assert_eq!(s.domain, Sweep::DOMAIN_TIME);
        assert_eq!((s.channel_count, s.bin_count), (11, 369));
        assert_eq!(s.values.len(), 11 * 369);
        assert!(s.calibration.is_empty());
        assert!(s.values.iter().all(|v| v.is_finite()));
        let peak = s.values.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let t = (s.header.stamp.to_ns() - t0) as f64 * 1e-9;
        // the vehicle stands for the first 2.3 s, then accelerates
        if t < 2.0 {
            still = still.max(peak);
        } else if t > 3.0 {
            moving = moving.max(peak);
        }
    }
    // standing still, the distance IIR holds its mean (beta = 1): the static scene and the
    // ground bounce cancel and only noise is left; moving, the subsurface features pass
    assert!(moving > 20.0 * still, "moving peak {moving}, still peak {still}");
}

#[test]
fn a_real_dzt_line_runs_through_the_submap_pipeline() {
    use gprflow::msg::Submap;
    let dir = tempfile::tempdir().expect("tempdir");
    let dzt = real_gpr("GSSI_FILE____032.DZT");
    let sets = [
        format!("recording={}", dzt.display()),
        "spacing_m=0.5".into(),
        "hold_first_samples=2".into(),
    ];
    let (p, _) = launch_recorded(dir.path(), "graphs/submaps.yaml", &sets);
    let maps: Vec<Submap> = decode_all(&p["/filter/submap"]);
    // 1040 scans at 50 scans/m: 20.78 m of line, a submap every 0.5 m after the first 3 m
    // (traces 0.02 m apart fill every 0.015 m column but one in four: the rest interpolated)
    assert!((35..=37).contains(&maps.len()), "{} submaps", maps.len());
    assert!(maps.iter().all(|m| m.valid && m.rows == 512 && m.cols == 200));
    assert!(maps.iter().all(|m| m.pixels.iter().all(|v| v.is_finite())));
    let last = maps.last().expect("submaps");
    assert!((last.end_distance_m - 20.78).abs() < 0.5, "{}", last.end_distance_m);
    for w in maps.windows(2) {
        let step = w[1].end_distance_m - w[0].end_distance_m;
        assert!((step - 0.5).abs() < 0.02 + 1e-9, "{step}");
    }
}

#[test]
fn unusable_traces_are_dropped_counted_and_named_while_the_run_goes_on() {
    use gprflow::msg::{Header, Message, Submap, Trace, WheelOdometry, encode};
    use std::borrow::Cow;
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("bad-traces.mcap");
    {
        let mut w =
            gprflow::record::Recorder::create(&rec, &gprflow::record::RunMetadata::this_build()).expect("create");
        let tr = w.add_topic("/gpr/trace", Trace::TYPE_NAME).expect("topic");
        let wh = w.add_topic("/wheel/odometry", WheelOdometry::TYPE_NAME).expect("topic");
        // 4 m at 1 m/s, 100 traces/s, 201 samples; trace 50 holds a NaN, trace 60 is short
        for k in 0..400i64 {
            let stamp = 1_000_000_000 + k * 10_000_000;
            let mut samples: Vec<f32> = (0..201)
                .map(|i| ((i as f32) * 0.3 + (k as f32) * 0.05).sin() * 1000.0)
                .collect();
            if k == 50 {
                samples[5] = f32::NAN;
            }
            if k == 60 {
                samples.truncate(150);
            }
            let t = Trace {
                header: Header::new(stamp, "gpr"),
                sample_interval_ns: 0.2,
                center_frequency_hz: 5e8,
                distance_m: f64::NAN,
                samples_f32: Cow::Owned(samples),
                ..Trace::default()
            };
            w.write(tr, k as u64, stamp, &encode(&t)).expect("write");
            if k % 2 == 0 {
                let m = WheelOdometry {
                    header: Header::new(stamp, "odom"),
                    distance_m: k as f64 * 0.01,
                    ticks: 0,
                    speed_mps: 1.0,
                };
                w.write(wh, (k / 2) as u64, stamp, &encode(&m)).expect("write");
            }
        }
        w.finish().expect("finish");
    }
    let graph = dir.path().join("g.yaml");
    std::fs::write(
        &graph,
        "name: bad\nnodes:\n  ingest: { stage: ingest, params: { source: \"".to_owned()
            + rec.to_str().expect("utf8")
            + "\" } }\n  dsp: { stage: dsp, inputs: { trace: ingest/gpr } }\n  submap: { stage: submap, inputs: { trace: dsp/trace, wheel: ingest/wheel } }\nrecord: { topics: [\"dsp/*\", \"submap/*\"] }\n",
    )
    .expect("graph");
    let (p, o) = launch_recorded(dir.path(), graph.to_str().expect("utf8"), &[]);
    let err = stderr(&o);
    assert!(
        err.contains("topic=\"ingest/gpr\" seq=50") && err.contains("trace: value 5 is not finite"),
        "{err}"
    );
    assert!(
        err.contains("seq=60") && err.contains("expected 201 values, got 150"),
        "{err}"
    );
    assert!(err.contains("dsp: messages dropped as unusable messages=2"), "{err}");
    assert_eq!(p["/dsp/trace"].len(), 398);
    let maps: Vec<Submap> = decode_all(&p["/submap/submap"]);
    // 3.98 m of travel: submaps from 3 m on, every 0.02 m
    assert!((45..=52).contains(&maps.len()), "{}", maps.len());
}

#[test]
fn holding_the_dzt_counter_samples_lets_zero_time_find_the_first_negative_peak() {
    use gprflow::msg::Trace;
    let dir = tempfile::tempdir().expect("tempdir");
    let dzt = real_gpr("GSSI_FILE____032.DZT");
    let run = |hold: usize| -> Vec<Vec<f32>> {
        let graph = dir.path().join(format!("hold{hold}.yaml"));
        let run_dir = dir.path().join(format!("hold{hold}"));
        std::fs::create_dir(&run_dir).expect("mkdir");
        std::fs::write(
            &graph,
            format!(
                "name: hold\nnodes:\n  ingest: {{ stage: ingest, params: {{ source: \"{}\" }} }}\n  dsp: {{ stage: dsp, inputs: {{ trace: ingest/gpr }}, params: {{ hold_first_samples: {hold}, dewow: null, bandpass: null, sec_gain: null }} }}\nrecord: {{ topics: [\"dsp/*\", \"ingest/gpr\"] }}\n",
                dzt.display()
            ),
        )
        .expect("graph");
        let (p, _) = launch_recorded(&run_dir, graph.to_str().expect("utf8"), &[]);
        decode_all::<Trace>(&p["/dsp/trace"])
            .iter()
            .map(|t| t.samples_f32.to_vec())
            .collect()
    };
    let raw = run(0);
    let held = run(2);
    assert_eq!((raw.len(), held.len()), (1040, 1040));
    // sample 0 of a DZT trace is a scan counter (about -32768 after the unsigned offset): left
    // in, it is the "first negative peak" and nothing moves
    assert!(raw.iter().all(|t| t[0] < -30_000.0), "{}", raw[0][0]);
    // held, zero time finds the direct wave: the trace starts at a negative lobe that is the
    // minimum of its first run below half the peak, well above the counter's value
    for t in &held {
        assert!(t[0] < 0.0 && t[0] > -30_000.0, "{}", t[0]);
        assert!(t[1] >= t[0], "{} {}", t[0], t[1]);
    }
}
