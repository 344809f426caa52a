//! Running a scenario: every sensor on its own clock, merged in stamp order into one MCAP
//! recording (and optionally the CMU-GPR folder layout), plus the world's truth.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use gprflow::msg::{
    self, Covariance6, Header, HoughLine, Imu as ImuMsg, LineMap, Odometry, Point, Pose, PoseStamped,
    PoseWithCovariance, Quaternion, Sweep, Trace, Twist, TwistWithCovariance, Vector3 as Vec3Msg, WheelOdometry,
};
use gprflow::record::{ChannelId, Recorder, RunMetadata};
use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;

use crate::impulse::ImpulseGpr;
use crate::lgpr::LgprArray;
use crate::motion::{Kinematics, Motion};
use crate::rng::Rng;
use crate::scenario::{LineKind, PointObject, Radar, Run, Scenario, SurfaceObject};
use crate::scene::AntennaPose;
use crate::sensors::{Gps, Imu, TotalStation, WheelEncoder};
use crate::world::World;
use crate::{SimError, topics};

/// How to run a scenario.
#[derive(Debug, Clone, Default)]
pub struct SimOptions {
    /// The run to simulate (`None`: the first).
    pub run: Option<String>,
    /// The MCAP file to write.
    pub output: PathBuf,
    /// Also write the CMU-GPR folder layout into this directory (impulse radar only).
    pub cmu_gpr: Option<PathBuf>,
    /// Stop after this many seconds of sensor time.
    pub max_duration_s: Option<f64>,
    /// Draws the run's sensor noise and vibration afresh: repeat `k` of the same run in the
    /// same world (0: the scenario's own draw).
    pub repeat: u32,
    /// The scenario file's text, carried in the recording as an attachment.
    pub scenario_text: String,
}

/// What a simulation wrote.
#[derive(Debug, Clone, Serialize)]
pub struct SimSummary {
    /// Scenario name.
    pub scenario: String,
    /// Run name.
    pub run: String,
    /// Sensor time covered, s.
    pub duration_s: f64,
    /// Messages per topic.
    pub messages: BTreeMap<String, u64>,
    /// Distance driven (path length), m.
    pub distance_m: f64,
}

/// A linear object as the truth carries it: its segment and its Hough line.
#[derive(Debug, Clone, Serialize)]
pub struct TruthLine {
    /// Index (the `id` of the `HoughLine` on `truth/lines`).
    pub id: u32,
    /// One end [x, y, depth], m.
    pub from: [f64; 3],
    /// Other end [x, y, depth], m.
    pub to: [f64; 3],
    /// Radius, m.
    pub radius_m: f64,
    /// Material.
    pub kind: LineKind,
    /// Hough distance of the line's ground projection, m (>= 0).
    pub rho_m: f64,
    /// Hough angle of its normal, rad.
    pub theta_rad: f64,
}

/// Soil moisture levels closer than this share one world (0.05 % water: travel times differ
/// by about 0.15 %).
const MOISTURE_STEP: f64 = 0.0005;

/// The subsurface as the radar sees it at each moment of a run: one world while the soil
/// moisture is constant; while it dries or wets, the world of the current moisture level
/// (`MOISTURE_STEP`), made anew when the level changes (moisture only goes one way in a run).
struct Ground<'a> {
    decl: &'a crate::scenario::World,
    seed: u64,
    moisture: f64,
    per_s: f64,
    current: Option<(i64, World)>,
}

impl<'a> Ground<'a> {
    fn new(decl: &'a crate::scenario::World, seed: u64, run: &Run) -> Self {
        Self {
            decl,
            seed,
            moisture: run.soil_moisture,
            per_s: run.soil_moisture_per_min / 60.0,
            current: None,
        }
    }

    /// The world `t_s` seconds into the run.
    fn at(&mut self, t_s: f64) -> &mut World {
        let (key, moisture) = if self.per_s == 0.0 {
            (0, self.moisture)
        } else {
            let m = (self.moisture + self.per_s * t_s).clamp(0.0, 0.5);
            let key = (m / MOISTURE_STEP).round() as i64;
            (key, key as f64 * MOISTURE_STEP)
        };
        if self.current.as_ref().is_some_and(|(k, _)| *k != key) {
            self.current = None;
        }
        let (decl, seed) = (self.decl, self.seed);
        &mut self
            .current
            .get_or_insert_with(|| (key, World::new(decl, seed, moisture)))
            .1
    }
}

/// The world's truth, attached to the recording as `world.json`.
#[derive(Debug, Clone, Serialize)]
pub struct WorldTruth {
    /// Scenario name.
    pub scenario: String,
    /// Run name.
    pub run: String,
    /// World seed.
    pub seed: u64,
    /// Extra soil moisture in this run.
    pub soil_moisture: f64,
    /// Point objects (declared and random).
    pub points: Vec<PointObject>,
    /// Linear objects (declared pipes and rebar).
    pub lines: Vec<TruthLine>,
    /// Surface clutter.
    pub clutter: Vec<SurfaceObject>,
}

/// The Hough form (rho >= 0, theta) of the line through two ground points.
pub fn hough_of(a: [f64; 2], b: [f64; 2]) -> (f64, f64) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len = (dx * dx + dy * dy).sqrt().max(1e-12);
    let (mut nx, mut ny) = (-dy / len, dx / len);
    let mut rho = nx * a[0] + ny * a[1];
    if rho < 0.0 {
        rho = -rho;
        nx = -nx;
        ny = -ny;
    }
    (rho, ny.atan2(nx))
}

fn truth_lines(scenario: &Scenario) -> Vec<TruthLine> {
    let mut decls = scenario.world.lines.clone();
    if let Some(g) = &scenario.world.rebar {
        decls.extend(crate::world::rebar_lines(g));
    }
    decls
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let (rho_m, theta_rad) = hough_of([l.from[0], l.from[1]], [l.to[0], l.to[1]]);
            TruthLine {
                id: i as u32,
                from: l.from,
                to: l.to,
                radius_m: l.radius_m,
                kind: l.kind,
                rho_m,
                theta_rad,
            }
        })
        .collect()
}

/// A sensor's clock: sample `i` at `start + round(i / rate)`.
#[derive(Debug, Clone, Copy)]
struct Clock {
    start_ns: i64,
    rate_hz: f64,
    next: u64,
}

impl Clock {
    fn new(start_ns: i64, rate_hz: f64) -> Self {
        Self {
            start_ns,
            rate_hz,
            next: 0,
        }
    }

    fn stamp(&self) -> i64 {
        self.start_ns + (self.next as f64 * 1e9 / self.rate_hz).round() as i64
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Truth,
    Imu,
    Wheel,
    Gps,
    Radar,
}

fn point(v: &Vector3<f64>) -> Point {
    Point { x: v.x, y: v.y, z: v.z }
}

fn vec3(v: &Vector3<f64>) -> Vec3Msg {
    Vec3Msg { x: v.x, y: v.y, z: v.z }
}

fn quat(q: &UnitQuaternion<f64>) -> Quaternion {
    Quaternion {
        x: q.i,
        y: q.j,
        z: q.k,
        w: q.w,
    }
}

fn diag3(v: f64) -> [f64; 9] {
    [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]
}

fn diag6(v: [f64; 6]) -> Covariance6 {
    let mut c = [0.0; 36];
    for (i, x) in v.iter().enumerate() {
        c[i * 7] = *x;
    }
    Covariance6(c)
}

/// The CMU-GPR folder layout (seed 000 Fig. 3.9), written alongside the recording.
#[derive(Debug)]
struct CmuWriter {
    dir: PathBuf,
    gpr: BufWriter<File>,
    imu: BufWriter<File>,
    wheel: BufWriter<File>,
    truth: BufWriter<File>,
}

/// A stamp as decimal seconds with nine decimals (`-1.500000000` for -1.5 s).
fn seconds(stamp_ns: i64) -> String {
    let sign = if stamp_ns < 0 { "-" } else { "" };
    let magnitude = stamp_ns.unsigned_abs();
    format!("{sign}{}.{:09}", magnitude / 1_000_000_000, magnitude % 1_000_000_000)
}

impl CmuWriter {
    fn create(dir: &Path, samples: u32) -> Result<Self, SimError> {
        let err = |path: &Path| {
            let path = path.to_owned();
            move |source| SimError::Write { path, source }
        };
        std::fs::create_dir_all(dir).map_err(err(dir))?;
        let open = |name: &str, header: String| -> Result<BufWriter<File>, SimError> {
            let path = dir.join(name);
            let mut w = BufWriter::new(File::create(&path).map_err(err(&path))?);
            writeln!(w, "{header}").map_err(err(&path))?;
            Ok(w)
        };
        let amp: Vec<String> = (1..=samples).map(|i| format!("amp_{i}")).collect();
        Ok(Self {
            dir: dir.to_owned(),
            gpr: open("gpr_meas.csv", format!("t,{}", amp.join(",")))?,
            imu: open("imu_meas.csv", "t,ax,ay,az,gx,gy,gz,qw,qx,qy,qz".into())?,
            wheel: open("we_odom_meas.csv", "t,dist".into())?,
            truth: open("ts_meas.csv", "t,px,py,pz".into())?,
        })
    }

    fn io(&self, source: std::io::Error) -> SimError {
        SimError::Write {
            path: self.dir.clone(),
            source,
        }
    }

    fn finish(mut self) -> Result<(), SimError> {
        for w in [&mut self.gpr, &mut self.imu, &mut self.wheel, &mut self.truth] {
            w.flush().map_err(|source| SimError::Write {
                path: self.dir.clone(),
                source,
            })?;
        }
        Ok(())
    }
}

/// Channels of the recording.
#[derive(Debug)]
struct Channels {
    radar: ChannelId,
    imu: ChannelId,
    wheel: ChannelId,
    truth: ChannelId,
    gps: Option<ChannelId>,
}

/// Writes `opts.run` of `scenario` to `opts.output`; `progress` is told the fraction done.
///
/// # Errors
/// [`SimError::UnknownRun`], or write errors naming the file.
pub fn simulate(scenario: &Scenario, opts: &SimOptions, progress: &mut dyn FnMut(f64)) -> Result<SimSummary, SimError> {
    let run = scenario.run(opts.run.as_deref())?;
    let seed = scenario.seed;
    let run_seed = {
        let mut r = Rng::derive(seed, &format!("run:{}", run.name), i64::from(opts.repeat));
        r.next_u64()
    };
    let motion = Motion::new(run, &scenario.vibration, &mut Rng::derive(run_seed, "vibration", 0));
    let duration_s = opts
        .max_duration_s
        .map_or(motion.duration_s(), |d| d.min(motion.duration_s()));
    let mut ground = Ground::new(&scenario.world, seed, run);
    let start_ns = scenario.start_time_ns;
    let end_ns = start_ns + (duration_s * 1e9).round() as i64;

    let mut meta = RunMetadata::this_build();
    meta.run_id = match opts.repeat {
        0 => format!("sim-{}-{}", scenario.name, run.name),
        k => format!("sim-{}-{}-repeat{k}", scenario.name, run.name),
    };
    let mut rec = Recorder::create_reproducible(&opts.output, &meta, u64::try_from(start_ns).unwrap_or(0))?;
    let mut fields = BTreeMap::new();
    fields.insert("scenario".to_owned(), scenario.name.clone());
    fields.insert("run".to_owned(), run.name.clone());
    fields.insert("seed".to_owned(), seed.to_string());
    fields.insert("soil_moisture".to_owned(), run.soil_moisture.to_string());
    if run.soil_moisture_per_min != 0.0 {
        fields.insert(
            "soil_moisture_per_min".to_owned(),
            run.soil_moisture_per_min.to_string(),
        );
    }
    fields.insert("duration_s".to_owned(), duration_s.to_string());
    rec.write_metadata("gprflow.sim", fields)?;
    if !opts.scenario_text.is_empty() {
        rec.attach("scenario.yaml", "application/yaml", opts.scenario_text.as_bytes())?;
    }
    let lines = truth_lines(scenario);
    let truth = WorldTruth {
        scenario: scenario.name.clone(),
        run: run.name.clone(),
        seed,
        soil_moisture: run.soil_moisture,
        points: ground.at(0.0).points.clone(),
        lines: lines.clone(),
        clutter: scenario.world.clutter.clone(),
    };
    let truth_json = serde_json::to_vec_pretty(&truth).unwrap_or_default();
    rec.attach("world.json", "application/json", &truth_json)?;

    let (radar_topic, radar_type, radar_rate) = match &scenario.radar {
        Radar::Impulse(r) => (topics::TRACE, Trace::ROS_NAME, r.trace_rate_hz),
        Radar::Lgpr(r) => (topics::SWEEP, Sweep::ROS_NAME, r.sweep_rate_hz),
    };
    let ch = Channels {
        radar: rec.add_topic(radar_topic, radar_type)?,
        imu: rec.add_topic(topics::IMU, ImuMsg::ROS_NAME)?,
        wheel: rec.add_topic(topics::WHEEL, WheelOdometry::ROS_NAME)?,
        truth: rec.add_topic(topics::TRUTH_POSE, PoseStamped::ROS_NAME)?,
        gps: match scenario.gps {
            Some(_) => Some(rec.add_topic(topics::GPS, Odometry::ROS_NAME)?),
            None => None,
        },
    };
    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    let mut count = |topic: &str| *counts.entry(topic.to_owned()).or_default() += 1;

    // once, at the start: the truth lines and (LGPR) the factory calibration
    let lines_ch = rec.add_topic(topics::TRUTH_LINES, LineMap::ROS_NAME)?;
    let line_map = LineMap {
        header: Header::new(start_ns, "world"),
        lines: lines
            .iter()
            .map(|l| HoughLine {
                id: l.id,
                rho_m: l.rho_m,
                theta_rad: l.theta_rad,
                covariance: [0.0; 4],
            })
            .collect(),
    };
    rec.write(lines_ch, 0, start_ns, &msg::encode(&line_map))?;
    count(topics::TRUTH_LINES);

    let mut impulse = None;
    let mut array = None;
    match &scenario.radar {
        Radar::Impulse(r) => {
            let mut gpr = ImpulseGpr::new(r, Rng::derive(run_seed, "gpr", 0));
            if let Some(c) = &run.ground_contact {
                gpr = gpr.with_ground_contact(c, Rng::derive(run_seed, "ground_contact", 0));
            }
            impulse = Some((gpr, r.clone()));
        }
        Radar::Lgpr(r) => {
            let a = LgprArray::new(r, seed, Rng::derive(run_seed, "lgpr", 0));
            let (values, calibration) = a.factory_calibration();
            let fc = Sweep {
                header: Header::new(start_ns, "lgpr"),
                domain: Sweep::DOMAIN_FREQUENCY,
                channel_count: a.channels() as u32,
                bin_count: r.tones,
                start_frequency_hz: r.start_frequency_hz,
                frequency_step_hz: r.frequency_step_hz,
                sample_interval_ns: 0.0,
                values: Cow::Owned(values),
                calibration: Cow::Owned(calibration),
            };
            let fc_ch = rec.add_topic(topics::FACTORY_CALIBRATION, Sweep::ROS_NAME)?;
            rec.write(fc_ch, 0, start_ns, &msg::encode(&fc))?;
            count(topics::FACTORY_CALIBRATION);
            array = Some((a, r.clone()));
        }
    }
    let mut cmu = match (&opts.cmu_gpr, &scenario.radar) {
        (Some(dir), Radar::Impulse(r)) => Some(CmuWriter::create(dir, r.samples)?),
        _ => None,
    };

    let mut imu = Imu::new(&scenario.imu, Rng::derive(run_seed, "imu", 0));
    let mut wheel = WheelEncoder::new(&scenario.wheel, Rng::derive(run_seed, "wheel", 0));
    let mut station = TotalStation::new(&scenario.truth, Rng::derive(run_seed, "truth", 0));
    let mut gps = scenario
        .gps
        .as_ref()
        .map(|g| (Gps::new(g, Rng::derive(run_seed, "gps", 0)), g.rate_hz));
    let (imu_var_gyro, imu_var_accel, imu_var_orient) = imu.variances();

    let mut clocks = vec![
        (Source::Truth, Clock::new(start_ns, scenario.truth.rate_hz)),
        (Source::Imu, Clock::new(start_ns, scenario.imu.rate_hz)),
        (Source::Wheel, Clock::new(start_ns, scenario.wheel.rate_hz)),
        (Source::Radar, Clock::new(start_ns, radar_rate)),
    ];
    if let Some((_, rate)) = &gps {
        clocks.push((Source::Gps, Clock::new(start_ns, *rate)));
    }
    let mut last_progress = 0.0;
    let mut distance_m = 0.0;
    let mut last_position: Option<Vector3<f64>> = None;
    // the earliest due sensor each time; ties go to the order above
    while let Some((slot, stamp)) = clocks
        .iter()
        .enumerate()
        .map(|(i, (_, c))| (i, c.stamp()))
        .min_by_key(|&(i, s)| (s, i))
    {
        if stamp > end_ns {
            break;
        }
        let (source, clock) = &mut clocks[slot];
        let seq = clock.next;
        clock.next += 1;
        let dt_s = 1.0 / clock.rate_hz;
        let t_s = (stamp - start_ns) as f64 * 1e-9;
        let k: Kinematics = motion.at(t_s);
        match source {
            Source::Truth => {
                let p = station.measure(&k);
                if let Some(last) = last_position {
                    distance_m += (k.position_m - last).xy().norm();
                }
                last_position = Some(k.position_m);
                let m = PoseStamped {
                    header: Header::new(stamp, "world"),
                    pose: Pose {
                        position: point(&p),
                        orientation: quat(&k.world_from_body),
                    },
                };
                rec.write(ch.truth, seq, stamp, &msg::encode(&m))?;
                count(topics::TRUTH_POSE);
                if let Some(c) = cmu.as_mut() {
                    writeln!(c.truth, "{},{:.6},{:.6},{:.6}", seconds(stamp), p.x, p.y, p.z).map_err(|e| c.io(e))?;
                }
            }
            Source::Imu => {
                let s = imu.sample(&k);
                let m = ImuMsg {
                    header: Header::new(stamp, "imu"),
                    orientation: quat(&s.orientation),
                    orientation_covariance: diag3(imu_var_orient),
                    angular_velocity: vec3(&s.gyro_radps),
                    angular_velocity_covariance: diag3(imu_var_gyro),
                    linear_acceleration: vec3(&s.accel_mps2),
                    linear_acceleration_covariance: diag3(imu_var_accel),
                };
                rec.write(ch.imu, seq, stamp, &msg::encode(&m))?;
                count(topics::IMU);
                if let Some(c) = cmu.as_mut() {
                    let (a, g, q) = (s.accel_mps2, s.gyro_radps, s.orientation);
                    writeln!(
                        c.imu,
                        "{},{:.7},{:.7},{:.7},{:.7},{:.7},{:.7},{:.7},{:.7},{:.7},{:.7}",
                        seconds(stamp),
                        a.x,
                        a.y,
                        a.z,
                        g.x,
                        g.y,
                        g.z,
                        q.w,
                        q.i,
                        q.j,
                        q.k
                    )
                    .map_err(|e| c.io(e))?;
                }
            }
            Source::Wheel => {
                let r = wheel.read(&k, dt_s);
                let m = WheelOdometry {
                    header: Header::new(stamp, "base_link"),
                    distance_m: r.distance_m,
                    ticks: r.ticks,
                    speed_mps: r.speed_mps,
                };
                rec.write(ch.wheel, seq, stamp, &msg::encode(&m))?;
                count(topics::WHEEL);
                if let Some(c) = cmu.as_mut() {
                    writeln!(c.wheel, "{},{:.6}", seconds(stamp), r.distance_m).map_err(|e| c.io(e))?;
                }
            }
            Source::Gps => {
                if let (Some((g, _)), Some(gps_ch)) = (gps.as_mut(), ch.gps) {
                    let f = g.fix(&k, dt_s);
                    let s = g.sigma_m();
                    let m = Odometry {
                        header: Header::new(stamp, "world"),
                        child_frame_id: "base_link".into(),
                        pose: PoseWithCovariance {
                            pose: Pose {
                                position: point(&f.position_m),
                                orientation: quat(&f.orientation),
                            },
                            covariance: diag6([s.x * s.x, s.y * s.y, s.z * s.z, 3e-6, 3e-6, 3e-6]),
                        },
                        twist: TwistWithCovariance {
                            twist: Twist {
                                linear: vec3(&f.velocity_body_mps),
                                angular: vec3(&k.angular_rate_radps),
                            },
                            covariance: diag6([4e-4, 4e-4, 4e-4, 1e-4, 1e-4, 1e-4]),
                        },
                    };
                    rec.write(gps_ch, seq, stamp, &msg::encode(&m))?;
                    count(topics::GPS);
                }
            }
            Source::Radar => {
                if let Some((gpr, cfg)) = impulse.as_mut() {
                    let mount = k.world_from_body * Vector3::new(cfg.mount_m[0], cfg.mount_m[1], 0.0);
                    let p = k.position_m + mount;
                    let pose = AntennaPose {
                        x: p.x,
                        y: p.y,
                        height_m: cfg.antenna_height_m + p.z.max(-cfg.antenna_height_m),
                        yaw_rad: k.yaw_rad,
                    };
                    let samples = gpr.trace(ground.at(t_s), pose, dt_s);
                    if let Some(c) = cmu.as_mut() {
                        let mut line = seconds(stamp);
                        for s in &samples {
                            line.push(',');
                            line.push_str(&s.to_string());
                        }
                        writeln!(c.gpr, "{line}").map_err(|e| c.io(e))?;
                    }
                    let m = Trace {
                        header: Header::new(stamp, "gpr"),
                        channel: 0,
                        sample_interval_ns: cfg.sample_interval_ns,
                        time_zero_ns: -cfg.time_zero_sample * cfg.sample_interval_ns,
                        center_frequency_hz: cfg.center_frequency_hz,
                        distance_m: f64::NAN,
                        samples_i16: Cow::Owned(samples),
                        samples_i32: Cow::Borrowed(&[]),
                        samples_f32: Cow::Borrowed(&[]),
                    };
                    rec.write(ch.radar, seq, stamp, &msg::encode(&m))?;
                    count(topics::TRACE);
                } else if let Some((a, cfg)) = array.as_mut() {
                    let (values, calibration) = a.sweep(ground.at(t_s), &k, t_s);
                    let m = Sweep {
                        header: Header::new(stamp, "lgpr"),
                        domain: Sweep::DOMAIN_FREQUENCY,
                        channel_count: a.channels() as u32,
                        bin_count: cfg.tones,
                        start_frequency_hz: cfg.start_frequency_hz,
                        frequency_step_hz: cfg.frequency_step_hz,
                        sample_interval_ns: 0.0,
                        values: Cow::Owned(values),
                        calibration: Cow::Owned(calibration),
                    };
                    rec.write(ch.radar, seq, stamp, &msg::encode(&m))?;
                    count(topics::SWEEP);
                }
            }
        }
        let done = t_s / duration_s.max(1e-9);
        if done - last_progress >= 0.01 {
            last_progress = done;
            progress(done);
        }
    }
    rec.finish()?;
    if let Some(c) = cmu {
        c.finish()?;
    }
    progress(1.0);
    Ok(SimSummary {
        scenario: scenario.name.clone(),
        run: run.name.clone(),
        duration_s,
        messages: counts,
        distance_m,
    })
}

#[cfg(test)]
mod seconds_tests {
    #[test]
    fn seconds_writes_negative_stamps_with_their_sign() {
        assert_eq!(super::seconds(1_600_000_000_020_000_000), "1600000000.020000000");
        assert_eq!(super::seconds(-1_500_000_000), "-1.500000000");
        assert_eq!(super::seconds(-5), "-0.000000005");
        assert_eq!(super::seconds(i64::MIN), "-9223372036.854775808");
    }
}
