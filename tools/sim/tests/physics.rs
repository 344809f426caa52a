//! The simulator's physics against what the geometry predicts.

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

use gprflow::msg::{self, PoseStamped, Trace};
use gprflow::record::Recording;
use gprflow_sim::impulse::ImpulseGpr;
use gprflow_sim::lgpr::LgprArray;
use gprflow_sim::motion::Kinematics;
use gprflow_sim::rng::Rng;
use gprflow_sim::scenario::{self, ImpulseRadar, ImuConfig, Layer, LgprRadar, PointKind, PointObject, Ringing};
use gprflow_sim::scene::AntennaPose;
use gprflow_sim::sensors::Imu;
use gprflow_sim::world::{C_M_PER_NS, World};
use gprflow_sim::{Scenario, SimOptions, simulate, topics};

/// Two-way time tolerance for picked echoes, ns (the sample interval is 0.2 ns).
const DELAY_TOLERANCE_NS: f64 = 0.05;
/// Allowed relative error of the Allan deviation at 1 s.
const ALLAN_TOLERANCE: f64 = 0.2;

fn one_layer(eps_r: f64, points: Vec<PointObject>) -> scenario::World {
    scenario::World {
        layers: vec![Layer {
            top_depth_m: 0.0,
            eps_r,
            attenuation_db_per_m: 2.0,
            undulation: None,
        }],
        texture: None,
        points,
        random_points: None,
        lines: vec![],
        rebar: None,
        clutter: vec![],
    }
}

fn quiet_radar() -> ImpulseRadar {
    ImpulseRadar {
        ringing: Ringing {
            first: 0.0,
            ..Ringing::default()
        },
        wow_counts: 0.0,
        dc_offset_counts: 0.0,
        dc_walk_counts: 0.0,
        time_zero_jitter_ns: 0.0,
        noise_counts: 0.0,
        direct_coupling_counts: 0.0,
        samples: 301,
        ..ImpulseRadar::default()
    }
}

/// The time of the strongest (negative or positive) peak, refined by a parabola.
fn pick(trace: &[f64], dt_ns: f64, k0: f64) -> (f64, f64) {
    let (k, _) = trace
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .expect("samples");
    let k = k.clamp(1, trace.len() - 2);
    let (a, b, c) = (trace[k - 1], trace[k], trace[k + 1]);
    let offset = 0.5 * (a - c) / (a - 2.0 * b + c);
    ((k as f64 + offset - k0) * dt_ns, b.abs())
}

#[test]
fn a_point_scatterer_draws_the_hyperbola_its_velocity_predicts() {
    let eps_r: f64 = 9.0;
    let (depth, radius) = (0.8, 0.05);
    let void = PointObject {
        at: [5.0, 0.0],
        depth_m: depth,
        radius_m: radius,
        kind: PointKind::Void,
    };
    let cfg = quiet_radar();
    let mut with = World::new(&one_layer(eps_r, vec![void]), 1, 0.0);
    let mut without = World::new(&one_layer(eps_r, vec![]), 1, 0.0);
    let mut gpr_a = ImpulseGpr::new(&cfg, Rng::new(1));
    let mut gpr_b = ImpulseGpr::new(&cfg, Rng::new(1));
    let v = C_M_PER_NS / eps_r.sqrt();
    let top = depth - radius;
    let t0 = 2.0 * top / v;
    let mut apex = (f64::INFINITY, 0.0);
    let mut checked = 0;
    for i in 0..=100 {
        let x = 4.0 + 0.02 * f64::from(i);
        let pose = AntennaPose {
            x,
            y: 0.0,
            height_m: 0.0,
            yaw_rad: 0.0,
        };
        let a = gpr_a.trace(&mut with, pose, 0.02);
        let b = gpr_b.trace(&mut without, pose, 0.02);
        // quantisation aside, the difference holds the scatterer's echo alone
        let echo: Vec<f64> = a.iter().zip(&b).map(|(p, q)| f64::from(*p) - f64::from(*q)).collect();
        let (tau, peak) = pick(&echo, cfg.sample_interval_ns, cfg.time_zero_sample);
        if peak < 50.0 {
            continue; // outside the beam
        }
        let expected = (t0 * t0 + (2.0 * (x - 5.0) / v).powi(2)).sqrt();
        assert!(
            (tau - expected).abs() < DELAY_TOLERANCE_NS,
            "x = {x:.2} m: echo at {tau:.3} ns, geometry says {expected:.3} ns"
        );
        checked += 1;
        if tau < apex.0 {
            apex = (tau, x);
        }
    }
    assert!(
        checked > 40,
        "the echo must be seen over a good part of the hyperbola, saw {checked} traces"
    );
    assert!(
        (apex.1 - 5.0).abs() < 0.021,
        "apex above the scatterer, found at x = {}",
        apex.1
    );
    assert!(
        (apex.0 - t0).abs() < DELAY_TOLERANCE_NS,
        "apex at {} ns, expected {t0}",
        apex.0
    );
}

/// Simulates `run` of `scenario` into `dir/RUN.mcap`; returns that path.
fn simulate_run(scenario: &Scenario, dir: &Path, run: &str) -> PathBuf {
    let output = dir.join(format!("{run}.mcap"));
    let opts = SimOptions {
        run: Some(run.into()),
        output: output.clone(),
        ..SimOptions::default()
    };
    simulate(scenario, &opts, &mut |_| {}).expect("simulate");
    output
}

fn write_scenario(dir: &Path, name: &str, text: &str) -> Scenario {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write scenario");
    Scenario::load(&path).expect("valid scenario")
}

const TEXTURED: &str = r#"
name: shift
seed: 77
world:
  layers:
    - { top_depth_m: 0.0, eps_r: 6.0, attenuation_db_per_m: 4.0 }
  texture: { density_per_m3: 300, max_depth_m: 1.2, strength: 0.05, correlation_length_m: 0.2 }
radar: { kind: impulse, noise_counts: 5.0 }
vibration: { roll_deg: 0.0, pitch_deg: 0.0, height_m: 0.0 }
runs:
  - name: a
    start_pause_s: 0.5
    end_pause_s: 0.5
    trajectory: { kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 8, speed_mps: 0.5 }
  - name: b
    start_pause_s: 0.5
    end_pause_s: 0.5
    trajectory: { kind: long_drive, start: [1, 0], heading_deg: 0, length_m: 8, speed_mps: 0.5 }
"#;

/// (log time, truth x) of every pose and (log time, samples) of every trace.
type TruthXAndTraces = (Vec<(i64, f64)>, Vec<(i64, Vec<f64>)>);

/// A recording's truth x positions and its traces, each with its log time.
fn truth_x_and_traces(path: &Path) -> TruthXAndTraces {
    let rec = Recording::open(path).expect("open");
    let mut poses: Vec<(i64, f64)> = Vec::new();
    let mut traces: Vec<(i64, Vec<f64>)> = Vec::new();
    rec.scan(|m| {
        if m.topic == format!("/{}", topics::TRUTH_POSE) {
            let p: PoseStamped = msg::decode(m.data).expect("pose");
            poses.push((m.log_time as i64, p.pose.position.x));
        } else if m.topic == format!("/{}", topics::TRACE) {
            let t: Trace = msg::decode(m.data).expect("trace");
            traces.push((m.log_time as i64, t.samples_i16.iter().map(|&s| f64::from(s)).collect()));
        }
    });
    (poses, traces)
}

/// The mean of a radargram's non-empty columns.
fn mean_trace(g: &[Vec<f64>]) -> Vec<f64> {
    let valid: Vec<&Vec<f64>> = g.iter().filter(|c| !c.is_empty()).collect();
    (0..valid[0].len())
        .map(|k| valid.iter().map(|c| c[k]).sum::<f64>() / valid.len() as f64)
        .collect()
}

/// Traces of a recording resampled onto a 1 cm grid of truth x from `x0`.
fn radargram_by_position(path: &Path, x0: f64, columns: usize) -> Vec<Vec<f64>> {
    let (poses, traces) = truth_x_and_traces(path);
    let x_at = |stamp: i64| {
        let i = poses.partition_point(|(s, _)| *s <= stamp).clamp(1, poses.len() - 1);
        let ((s0, x0), (s1, x1)) = (poses[i - 1], poses[i]);
        x0 + (x1 - x0) * (stamp - s0) as f64 / (s1 - s0) as f64
    };
    let mut grid = vec![Vec::new(); columns];
    let mut counts = vec![0usize; columns];
    for (stamp, samples) in &traces {
        let col = ((x_at(*stamp) - x0) / 0.01).round();
        if col >= 0.0 && (col as usize) < columns {
            let c = col as usize;
            if grid[c].is_empty() {
                grid[c] = vec![0.0; samples.len()];
            }
            for (g, s) in grid[c].iter_mut().zip(samples) {
                *g += s;
            }
            counts[c] += 1;
        }
    }
    for (g, n) in grid.iter_mut().zip(counts) {
        g.iter_mut().for_each(|v| *v /= n.max(1) as f64);
    }
    grid
}

#[test]
fn moving_one_metre_along_track_shifts_the_radargram_by_one_metre() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = write_scenario(dir.path(), "shift.yaml", TEXTURED);
    for run in ["a", "b"] {
        simulate_run(&scenario, dir.path(), run);
    }
    // both from x = 1 m (the first metre of a has no partner in b)
    let a = radargram_by_position(&dir.path().join("a.mcap"), 0.0, 900);
    let b = radargram_by_position(&dir.path().join("b.mcap"), 1.0, 700);
    // mean trace removed, below the direct wave
    let demean = |g: &[Vec<f64>]| -> Vec<Vec<f64>> {
        let mean = mean_trace(g);
        g.iter()
            .map(|c| {
                if c.is_empty() {
                    c.clone()
                } else {
                    c.iter().zip(&mean).skip(40).map(|(v, m)| v - m).collect()
                }
            })
            .collect()
    };
    let (a, b) = (demean(&a), demean(&b));
    let score = |shift: usize| {
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (j, cb) in b.iter().enumerate().take(650) {
            let Some(ca) = a.get(j + shift) else { continue };
            if ca.is_empty() || cb.is_empty() {
                continue;
            }
            for (x, y) in ca.iter().zip(cb) {
                sab += x * y;
                saa += x * x;
                sbb += y * y;
            }
        }
        sab / (saa * sbb).sqrt()
    };
    let (best, corr) = (0..=200)
        .map(|s| (s, score(s)))
        .max_by(|x, y| x.1.total_cmp(&y.1))
        .expect("shifts");
    assert!(
        (best as i64 - 100).abs() <= 1,
        "best shift {best} cm, correlation {corr:.3}"
    );
    assert!(corr > 0.9, "the same ground must look the same: correlation {corr:.3}");
    assert!(score(50) < 0.5 * corr, "another place must look different");
}

#[test]
fn same_seed_gives_identical_bytes_and_another_seed_does_not() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario = write_scenario(dir.path(), "shift.yaml", TEXTURED);
    let other = write_scenario(dir.path(), "other.yaml", &TEXTURED.replace("seed: 77", "seed: 78"));
    let mut files = Vec::new();
    for (i, s) in [&scenario, &scenario, &other].into_iter().enumerate() {
        let output = dir.path().join(format!("{i}.mcap"));
        let opts = SimOptions {
            output: output.clone(),
            max_duration_s: Some(6.0),
            ..SimOptions::default()
        };
        simulate(s, &opts, &mut |_| {}).expect("simulate");
        files.push(std::fs::read(output).expect("read"));
    }
    assert!(files[0] == files[1], "same scenario and seed, different bytes");
    assert!(files[0] != files[2], "another seed, same bytes");
}

fn allan_deviation_at(samples: &[f64], per_cluster: usize) -> f64 {
    let means: Vec<f64> = samples
        .chunks_exact(per_cluster)
        .map(|c| c.iter().sum::<f64>() / per_cluster as f64)
        .collect();
    let s: f64 = means.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
    (s / (2.0 * (means.len() - 1) as f64)).sqrt()
}

#[test]
fn imu_noise_matches_the_configured_densities() {
    let cfg = ImuConfig::default();
    let mut imu = Imu::new(&cfg, Rng::new(11));
    let rest = Kinematics::at_rest();
    let n = (cfg.rate_hz * 1200.0) as usize;
    let mut gyro: Vec<Vec<f64>> = (0..3).map(|_| Vec::with_capacity(n)).collect();
    let mut accel: Vec<Vec<f64>> = (0..3).map(|_| Vec::with_capacity(n)).collect();
    for _ in 0..n {
        let s = imu.sample(&rest);
        for axis in 0..3 {
            gyro[axis].push(s.gyro_radps[axis]);
            accel[axis].push(s.accel_mps2[axis]);
        }
    }
    let per_second = cfg.rate_hz as usize;
    for axis in 0..3 {
        for (name, series, density) in [
            ("gyro", &gyro[axis], cfg.gyro_noise_density),
            ("accel", &accel[axis], cfg.accel_noise_density),
        ] {
            // white noise of density N has Allan deviation N / sqrt(tau)
            let adev = allan_deviation_at(series, per_second);
            assert!(
                (adev / density - 1.0).abs() < ALLAN_TOLERANCE,
                "{name} axis {axis}: Allan deviation at 1 s {adev:.3e}, density {density:.3e}"
            );
        }
    }
}

#[test]
fn sfcw_sweeps_put_a_reflector_at_its_delay() {
    let eps_r: f64 = 6.0;
    let cfg = LgprRadar {
        noise: 0.0,
        ..LgprRadar::default()
    };
    let mut probe = LgprArray::new(&cfg, 5, Rng::new(2));
    let channel = 5;
    let offset = probe.channel_offset_m(channel);
    let depth = 1.0;
    let rock = PointObject {
        at: [0.0, offset],
        depth_m: depth,
        radius_m: 0.1,
        kind: PointKind::Void,
    };
    let mut with = World::new(&one_layer(eps_r, vec![rock]), 1, 0.0);
    let mut without = World::new(&one_layer(eps_r, vec![]), 1, 0.0);
    let body = Kinematics::at_rest();
    let (factory, factory_cal) = probe.factory_calibration();
    let tones = cfg.tones as usize;
    let complex = |v: &[f32], i: usize| nalgebra::Complex::new(f64::from(v[2 * i]), f64::from(v[2 * i + 1]));
    // seed 001 eq. 2-4 on one channel: (S_ant / S_cal) / (S_fac / S_fac_cal) - 1
    let calibrated = |values: &[f32], cal: &[f32]| -> Vec<nalgebra::Complex<f64>> {
        (0..tones)
            .map(|m| {
                let i = channel * tones + m;
                (complex(values, i) / complex(cal, m)) / (complex(&factory, i) / complex(&factory_cal, m))
                    - nalgebra::Complex::new(1.0, 0.0)
            })
            .collect()
    };
    let (va, ca) = probe.sweep(&mut with, &body, 30.0);
    let mut twin = LgprArray::new(&cfg, 5, Rng::new(2));
    let (vb, cb) = twin.sweep(&mut without, &body, 30.0);
    let a = calibrated(&va, &ca);
    let b = calibrated(&vb, &cb);
    let diff: Vec<_> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
    // back to time: inverse DFT on a fine grid, the envelope peaks at the echo's delay
    let f0 = cfg.start_frequency_hz * 1e-9;
    let df = cfg.frequency_step_hz * 1e-9;
    let envelope = |t: f64| -> f64 {
        diff.iter()
            .enumerate()
            .map(|(m, s)| s * nalgebra::Complex::from_polar(1.0, TAU * (f0 + m as f64 * df) * t))
            .sum::<nalgebra::Complex<f64>>()
            .norm()
    };
    let (t_peak, _) = (0..4000)
        .map(|i| {
            let t = f64::from(i) * 0.005;
            (t, envelope(t))
        })
        .max_by(|x, y| x.1.total_cmp(&y.1))
        .expect("grid");
    let v = C_M_PER_NS / eps_r.sqrt();
    let expected = 2.0 * cfg.height_m / C_M_PER_NS + 2.0 * (depth - 0.1) / v;
    assert!(
        (t_peak - expected).abs() < 0.1,
        "reflector at {t_peak:.3} ns after calibration and IDFT, expected {expected:.3} ns"
    );
    // and the calibration removed the hardware: the raw sweep alone would not say so
    assert!(probe.channels() == 11);
}

fn correlation(a: &[i16], b: &[i16]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b).skip(40) {
        let (x, y) = (f64::from(*x), f64::from(*y));
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    ab / (aa * bb).sqrt()
}

#[test]
fn polarised_ground_depends_on_heading_but_not_on_direction() {
    let mut decl = one_layer(6.0, vec![]);
    decl.texture = Some(scenario::Texture {
        density_per_m3: 300.0,
        max_depth_m: 1.2,
        strength: 0.05,
        correlation_length_m: 0.2,
        correlation: 0.0,
        polarisation: 0.6,
    });
    let mut world = World::new(&decl, 3, 0.0);
    let mut gpr = ImpulseGpr::new(&quiet_radar(), Rng::new(1));
    let at = |yaw_rad: f64| AntennaPose {
        x: 2.0,
        y: 1.0,
        height_m: 0.0,
        yaw_rad,
    };
    let east = gpr.trace(&mut world, at(0.0), 0.02);
    let west = gpr.trace(&mut world, at(std::f64::consts::PI), 0.02);
    let north = gpr.trace(&mut world, at(std::f64::consts::FRAC_PI_2), 0.02);
    assert!(
        correlation(&east, &west) > 0.999,
        "driving the other way sees the same ground"
    );
    let across = correlation(&east, &north);
    assert!(
        across < 0.9,
        "a crossing heading must see the ground differently: {across:.3}"
    );
    assert!(across > 0.2, "but still the same ground: {across:.3}");
}

#[test]
fn wetter_soil_stretches_travel_times() {
    let void = PointObject {
        at: [0.0, 0.0],
        depth_m: 0.6,
        radius_m: 0.05,
        kind: PointKind::Void,
    };
    let cfg = quiet_radar();
    let pose = AntennaPose {
        x: 0.0,
        y: 0.0,
        height_m: 0.0,
        yaw_rad: 0.0,
    };
    let mut delays = Vec::new();
    for moisture in [0.0, 0.1] {
        let mut with = World::new(&one_layer(6.0, vec![void.clone()]), 1, moisture);
        let trace = ImpulseGpr::new(&cfg, Rng::new(1)).trace(&mut with, pose, 0.02);
        let samples: Vec<f64> = trace.iter().map(|&s| f64::from(s)).collect();
        delays.push(pick(&samples, cfg.sample_interval_ns, cfg.time_zero_sample));
    }
    let (dry, wet) = (delays[0], delays[1]);
    // CRIM: sqrt(eps) grows by 0.1 * (sqrt(80) - 1)
    let expected = dry.0 * (6f64.sqrt() + 0.1 * (80f64.sqrt() - 1.0)) / 6f64.sqrt();
    assert!(
        (wet.0 - expected).abs() < DELAY_TOLERANCE_NS,
        "wet echo at {:.3} ns, expected {expected:.3}",
        wet.0
    );
    assert!(wet.1 < dry.1, "wetter soil attenuates more");
}

/// Zero-lag correlation of two radargrams on the same grid, the mean trace of each removed,
/// below the direct wave.
fn radargram_correlation(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    let (ma, mb) = (mean_trace(a), mean_trace(b));
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (ca, cb) in a.iter().zip(b) {
        if ca.is_empty() || cb.is_empty() {
            continue;
        }
        for k in 40..ca.len() {
            let (x, y) = (ca[k] - ma[k], cb[k] - mb[k]);
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
    }
    ab / (aa * bb).sqrt()
}

#[test]
fn a_wandering_rig_sees_the_same_ground_less_alike() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = format!(
        "{TEXTURED}  - name: again\n    start_pause_s: 0.5\n    end_pause_s: 0.5\n    trajectory: {{ kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 8, speed_mps: 0.5 }}\n  - name: wander\n    start_pause_s: 0.5\n    end_pause_s: 0.5\n    wander: {{ sigma_m: 0.1, wavelength_m: 3 }}\n    trajectory: {{ kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 8, speed_mps: 0.5 }}\n"
    );
    let scenario = write_scenario(dir.path(), "wander.yaml", &text);
    let mut grams = Vec::new();
    for run in ["a", "again", "wander"] {
        let output = simulate_run(&scenario, dir.path(), run);
        // the middle 6 m, where the wander has faded in
        grams.push(radargram_by_position(&output, 1.0, 600));
    }
    let same = radargram_correlation(&grams[0], &grams[1]);
    let wandered = radargram_correlation(&grams[0], &grams[2]);
    assert!(same > 0.9, "the same path twice: correlation {same:.3}");
    assert!(
        wandered < same - WANDER_DECORRELATION,
        "10 cm of wander must change what the radar sees: {wandered:.3} against {same:.3}"
    );
    assert!(wandered > 0.2, "but it is still the same ground: {wandered:.3}");
}

/// How much less alike (correlation) two passes over textured ground are at 10 cm RMS of
/// sideways wander than on the same path.
const WANDER_DECORRELATION: f64 = 0.2;

#[test]
fn drying_soil_moves_the_echoes_of_later_passes_earlier() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = r#"
name: drying
seed: 5
world:
  layers:
    - { top_depth_m: 0.0, eps_r: 6.0, attenuation_db_per_m: 2.0 }
  points:
    - { at: [3.0, 0.0], depth_m: 0.6, radius_m: 0.05, kind: void }
radar: { kind: impulse, samples: 301, noise_counts: 0.0, wow_counts: 0.0, dc_offset_counts: 0.0, dc_walk_counts: 0.0, time_zero_jitter_ns: 0.0, direct_coupling_counts: 0.0, antenna_height_m: 0.0, mount_m: [0.0, 0.0], ringing: { first: 0.0 } }
vibration: { roll_deg: 0.0, pitch_deg: 0.0, height_m: 0.0 }
runs:
  - name: drying
    soil_moisture: 0.1
    soil_moisture_per_min: -0.05
    trajectory: { kind: forward_backward, start: [0, 0], heading_deg: 0, length_m: 6, repeats: 2, speed_mps: 0.5 }
"#;
    let scenario = write_scenario(dir.path(), "drying.yaml", text);
    let output = simulate_run(&scenario, dir.path(), "drying");
    // the trace nearest above the void on each of the four passes
    let (poses, traces) = truth_x_and_traces(&output);
    let x_at = |stamp: i64| poses[poses.partition_point(|(s, _)| *s <= stamp).clamp(1, poses.len()) - 1].1;
    let start = poses[0].0;
    let mut passes: Vec<(f64, Vec<f64>)> = Vec::new(); // (time into the run, trace)
    let mut last_x = x_at(traces[0].0);
    for (stamp, samples) in &traces {
        let x = x_at(*stamp);
        if (last_x - 3.0) * (x - 3.0) <= 0.0 && last_x != x {
            passes.push(((stamp - start) as f64 * 1e-9, samples.clone()));
        }
        last_x = x;
    }
    assert_eq!(passes.len(), 4, "four passes over the void");
    let cfg = &scenario.radar;
    let gprflow_sim::scenario::Radar::Impulse(cfg) = cfg else {
        panic!("impulse radar")
    };
    let mut last = f64::INFINITY;
    for (t, samples) in &passes {
        let (delay, _) = pick(samples, cfg.sample_interval_ns, cfg.time_zero_sample);
        let moisture = 0.1 - 0.05 * t / 60.0;
        // the echo comes from the top of the void
        let expected = World::new(&scenario.world, scenario.seed, moisture)
            .column(3.0, 0.0, 0.55)
            .t0_ns;
        assert!(
            (delay - expected).abs() < 4.0 * DELAY_TOLERANCE_NS,
            "echo at {delay:.3} ns after {t:.1} s, expected {expected:.3} ns (moisture {moisture:.4})"
        );
        assert!(delay < last, "each later pass sees drier, faster soil");
        last = delay;
    }
}

#[test]
fn uneven_ground_contact_makes_the_ringing_wax_and_wane_along_the_track() {
    let dir = tempfile::tempdir().expect("tempdir");
    // nothing in the ground and a quiet radar: what changes from trace to trace is the ringing
    let base = r#"
name: contact
seed: 11
world:
  layers:
    - { top_depth_m: 0.0, eps_r: 6.0, attenuation_db_per_m: 4.0 }
radar: { kind: impulse, noise_counts: 0.0, wow_counts: 0.0, dc_offset_counts: 0.0, dc_walk_counts: 0.0, time_zero_jitter_ns: 0.0 }
vibration: { roll_deg: 0.0, pitch_deg: 0.0, height_m: 0.0 }
runs:
  - name: even
    trajectory: { kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 20, speed_mps: 0.5 }
  - name: uneven
    ground_contact: { ringing_sigma: 0.3, correlation_s: 1.0 }
    trajectory: { kind: long_drive, start: [0, 0], heading_deg: 0, length_m: 20, speed_mps: 0.5 }
"#;
    let scenario = write_scenario(dir.path(), "contact.yaml", base);
    let gprflow_sim::scenario::Radar::Impulse(cfg) = &scenario.radar else {
        panic!("impulse radar")
    };
    // the first copy of the direct coupling, one ringing period after time zero
    let first_copy = (cfg.time_zero_sample + cfg.ringing.period_ns / cfg.sample_interval_ns).round() as usize;
    let mut strength = Vec::new();
    for run in ["even", "uneven"] {
        let (_, traces) = truth_x_and_traces(&simulate_run(&scenario, dir.path(), run));
        strength.push(traces.iter().map(|(_, s)| s[first_copy]).collect::<Vec<f64>>());
    }
    // the log strength of the first copy, minus its mean over the run
    let log_deviation = |v: &[f64]| {
        let logs: Vec<f64> = v.iter().map(|x| x.abs().max(1.0).ln()).collect();
        let mean = logs.iter().sum::<f64>() / logs.len() as f64;
        logs.iter().map(|l| l - mean).collect::<Vec<f64>>()
    };
    let uneven = log_deviation(&strength[1]);
    let sd = |d: &[f64]| (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    let (even, uneven_sd) = (sd(&log_deviation(&strength[0])), sd(&uneven));
    assert!(
        even < 0.05,
        "even contact: the ringing holds its strength (log sd {even:.3})"
    );
    assert!(
        (0.15..0.45).contains(&uneven_sd),
        "uneven contact: the ringing's log strength varies by about 0.3 (log sd {uneven_sd:.3})"
    );
    // slow changes: alike from one trace to the next, unrelated 5 s (250 traces) apart
    let lag_correlation = |lag: usize| {
        let num: f64 = uneven.iter().zip(&uneven[lag..]).map(|(a, b)| a * b).sum();
        num / uneven.iter().map(|a| a * a).sum::<f64>()
    };
    let (next, apart) = (lag_correlation(1), lag_correlation(250));
    assert!(next > 0.9, "trace to trace correlation {next:.3}");
    assert!(apart.abs() < 0.3, "5 s apart correlation {apart:.3}");
}
