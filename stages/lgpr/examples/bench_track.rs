//! Throughput of the LGPR tracker on one thread, and of the gridding, on a real map store
//! (`graphs/lgpr-map.yaml`'s output). Sweeps are read off the local grid at planted 5-DOF
//! poses near the mapped track (with noise), and registered from seeds a tracking step off,
//! in the tracker's smallest search box; the same problem is dumped for the numpy reference
//! (`tools/peer/bench_track.py`). Prints one JSON object.
//!
//! usage: cargo run --release -p gprflow-lgpr --no-default-features --example bench_track MAP_DIR DUMP_DIR [sweeps (4000)]

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use gprflow_lgpr::array::ArrayGeometry;
use gprflow_lgpr::map::{GridSpec, LocalGrid, MapReader};
use gprflow_lgpr::track::{C_M_PER_NS, Correlator, Pose5, PreparedSweep, SplitMix, Swarm, SwarmParams, TrackParams};

const CHANNELS: usize = 11;
/// Noise added to the sweeps read off the grid, relative to the grid's RMS.
const NOISE: f64 = 0.1;

fn gaussian(rng: &mut SplitMix) -> f64 {
    let (u, v) = (rng.unit().max(1e-12), rng.unit());
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn write_f64(path: &Path, v: &[f64]) -> std::io::Result<()> {
    std::fs::write(path, v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(map_dir), Some(dump)) = (args.get(1), args.get(2)) else {
        return Err("usage: bench_track MAP_DIR DUMP_DIR [sweeps]".into());
    };
    let n: usize = args.get(3).map_or(Ok(4000), |s| s.parse())?;
    let map = MapReader::open(Path::new(map_dir))?;
    let samples = map.info().samples as usize;
    let dt = map.info().sample_interval_ns;
    let spec = GridSpec::default();
    let params = TrackParams::default();
    let geometry = ArrayGeometry::default();

    // the centre channel's columns, in stamp order: the mapped track and its heading
    let tiles = map.tiles()?;
    let mut track: Vec<(i64, [f64; 2])> = Vec::new();
    for key in tiles.keys() {
        let t = map.read_tile(*key, None)?;
        for i in 0..t.columns.len() {
            if usize::from(t.columns.channels[i]) == CHANNELS / 2 {
                track.push((t.columns.stamps_ns[i], t.columns.positions[i]));
            }
        }
    }
    track.sort_by_key(|c| c.0);
    if track.len() < 1000 {
        return Err(format!("{map_dir}: too short a map ({} sweeps)", track.len()).into());
    }

    // gridding: grids every 20 m along the track, timed
    let mut grid_ms = Vec::new();
    let step = (track.len() / 40).max(1);
    for c in track.iter().step_by(step) {
        let start = Instant::now();
        let (g, _) = LocalGrid::from_map_with_window(&map, &spec, c.1, params.window_len)?;
        grid_ms.push(start.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(g.occupied());
    }
    grid_ms.sort_by(f64::total_cmp);

    // one grid, sweeps planted on the track inside its usable part
    let centre_idx = track.len() / 3;
    let centre = track[centre_idx].1;
    let (grid, _) = LocalGrid::from_map_with_window(&map, &spec, centre, params.window_len)?;
    let rms = {
        let (_, v) = grid.raw();
        (v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt()
    };
    let mut rng = SplitMix::new(2015);
    let near: Vec<usize> = (1..track.len() - 1)
        .filter(|&i| grid.distance_from_centre(track[i].1[0], track[i].1[1]) < 15.0)
        .collect();
    let (mut truths, mut seeds, mut sweeps) = (Vec::new(), Vec::new(), Vec::new());
    let offsets = geometry.channel_offsets_m(CHANNELS);
    let per_m = 2.0 / C_M_PER_NS / dt;
    while truths.len() < n {
        let i = near[(rng.unit() * near.len() as f64) as usize];
        let (a, b) = (track[i - 1].1, track[i + 1].1);
        let yaw = (b[1] - a[1]).atan2(b[0] - a[0]);
        let lateral = 0.3 * rng.signed();
        let truth: Pose5 = [
            track[i].1[0] - yaw.sin() * lateral,
            track[i].1[1] + yaw.cos() * lateral,
            0.01 * rng.signed(),
            yaw + 0.3_f64.to_radians() * rng.signed(),
            0.8_f64.to_radians() * rng.signed(),
        ];
        let mut values = Vec::with_capacity(CHANNELS * samples);
        let mut ok = true;
        for &o in &offsets {
            let (x, y) = ArrayGeometry::to_world(truth[0], truth[1], truth[3], 0.0, o);
            let Some(slot) = grid.slot_at(x, y) else {
                ok = false;
                break;
            };
            let shift = ((truth[2] + o * truth[4].sin()) * per_m + 0.5).floor() as i64;
            let col = grid.column(slot);
            values.extend((0..samples as i64).map(|d| {
                let v = f64::from(col[(d - shift).clamp(0, samples as i64 - 1) as usize]);
                (v + NOISE * rms * gaussian(&mut rng)) as f32
            }));
        }
        if !ok {
            continue;
        }
        let seed: Pose5 = [
            truth[0] + 0.05 * rng.signed(),
            truth[1] + 0.05 * rng.signed(),
            0.0,
            truth[3] + 0.2_f64.to_radians() * rng.signed(),
            0.0,
        ];
        truths.push(truth);
        seeds.push(seed);
        sweeps.push(values);
    }

    let lo = &params.search_min;
    let half_width: Pose5 = [
        lo.xy_m,
        lo.xy_m,
        lo.height_m,
        lo.heading_deg.to_radians(),
        lo.roll_deg.to_radians(),
    ];
    let correlator = Correlator::new(&grid, dt);
    let mut prepared = PreparedSweep::new(&geometry, CHANNELS, params.window_start, params.window_len);
    let mut configs = Vec::new();
    for (particles, iterations) in [
        (params.particles_min, params.iterations_min),
        (48, 24),
        (100, 50),
        (params.particles_max, params.iterations_max),
    ] {
        // fewer sweeps for the big swarms: the cost per sweep is what is reported
        let count = if particles * iterations > 2000 {
            (n / 10).max(50)
        } else {
            n
        };
        let mut swarm = Swarm::new(SwarmParams::default(), 7);
        let mut times = Vec::with_capacity(count);
        let (mut err2, mut within, mut corr_sum) = (0.0, 0, 0.0);
        for k in 0..count {
            let start = Instant::now();
            prepared.load(&sweeps[k], samples);
            let r = swarm.search(&seeds[k], &half_width, particles, iterations, |p| {
                correlator.correlate(&prepared, p).value
            });
            times.push(start.elapsed().as_secs_f64() * 1e6);
            let e = (r.best[0] - truths[k][0]).hypot(r.best[1] - truths[k][1]);
            err2 += e * e;
            within += usize::from(e <= 0.05);
            corr_sum += r.value;
        }
        let total_s: f64 = times.iter().sum::<f64>() * 1e-6;
        times.sort_by(f64::total_cmp);
        configs.push(serde_json::json!({
            "particles": particles,
            "iterations": iterations,
            "evaluations": particles * iterations,
            "sweeps": count,
            "sweeps_per_s": count as f64 / total_s,
            "p50_us": percentile(&times, 0.5),
            "p99_us": percentile(&times, 0.99),
            "position_rms_m": (err2 / count as f64).sqrt(),
            "found_xy_within_5cm": within as f64 / count as f64,
            "mean_correlation": corr_sum / count as f64,
        }));
    }

    // the problem, for the numpy reference (same grid, sweeps, seeds, box and schedule)
    let dump = Path::new(dump);
    std::fs::create_dir_all(dump)?;
    let (nn, spacing, origin) = grid.layout();
    let (index, values) = grid.raw();
    let idx: Vec<u8> = index
        .iter()
        .flat_map(|&s| if s == u32::MAX { -1_i32 } else { s as i32 }.to_le_bytes())
        .collect();
    std::fs::write(dump.join("index.i32"), idx)?;
    std::fs::write(
        dump.join("columns.f32"),
        values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>(),
    )?;
    let flat: Vec<u8> = sweeps.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dump.join("sweeps.f32"), flat)?;
    write_f64(
        &dump.join("seeds.f64"),
        &seeds.iter().flatten().copied().collect::<Vec<_>>(),
    )?;
    write_f64(
        &dump.join("truth.f64"),
        &truths.iter().flatten().copied().collect::<Vec<_>>(),
    )?;
    // poses for the correlation check: the truth and points around it
    let mut poses = Vec::new();
    let mut check = Vec::new();
    for k in 0..200 {
        let mut p = truths[k % n];
        if k >= n.min(100) {
            p[0] += 0.3 * rng.signed();
            p[1] += 0.3 * rng.signed();
            p[2] += 0.03 * rng.signed();
            p[4] += 0.02 * rng.signed();
        }
        prepared.load(&sweeps[k % n], samples);
        let c = correlator.correlate(&prepared, &p);
        check.push(serde_json::json!({"correlation": c.value, "overlap": c.overlap}));
        poses.extend_from_slice(&p);
    }
    write_f64(&dump.join("poses.f64"), &poses)?;
    std::fs::write(dump.join("ours_check.json"), serde_json::to_string(&check)?)?;
    let first = &configs[0];
    let problem = serde_json::json!({
        "nx": nn, "ny": nn, "spacing_m": spacing, "origin_m": origin, "samples": samples,
        "corr_start": params.window_start, "corr_len": params.window_len, "sample_interval_ns": dt,
        "channels": CHANNELS, "offsets_m": offsets, "mount_x_m": geometry.mount_m[0], "sweeps": n,
        "pso": {
            "particles": first["particles"], "iterations": first["iterations"],
            "inertia_start": 0.9, "inertia_end": 0.4, "cognitive": 1.5, "social": 1.5
        },
        "half_width": half_width,
    });
    std::fs::write(dump.join("problem.json"), serde_json::to_string_pretty(&problem)?)?;

    let out = serde_json::json!({
        "implementation": "gprflow-lgpr (Rust), one thread",
        "map": map_dir,
        "grid": { "occupied_points": grid.occupied(), "bytes": grid.bytes(),
                  "gridding_ms_p50": percentile(&grid_ms, 0.5), "gridding_ms_max": percentile(&grid_ms, 1.0),
                  "grids_timed": grid_ms.len() },
        "noise_relative": NOISE,
        "configs": configs,
    });
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{}", serde_json::to_string_pretty(&out)?)?;
    Ok(())
}
