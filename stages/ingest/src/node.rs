//! The `ingest` stage: reads a recording (MCAP, CMU-GPR folder, DZT, DT1/HD) and publishes
//! its raw traces, sweeps, IMU, wheel odometry and ground truth as runtime messages, in stamp
//! order. [`load`] is the same conversion as plain code (`gprflow convert` uses it).

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use gprflow_msg::{
    Header, Imu, Message, Point, Pose, PoseStamped, Quaternion, Sweep, Trace, Vector3, WheelOdometry, decode, encode,
};
use gprflow_record::{Pace, Player, Recording};
use gprflow_stage::{Outputs, ParamError, PortSpec, Ports, Produce, Stage, StageError};

use crate::cmu::CmuSequence;
use crate::radargram::{Format, Radargram, RawSamples};

/// What the source is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum SourceFormat {
    /// From the path: a folder is a CMU-GPR sequence, else by extension (`.mcap`, `.dzt`, `.dt1`).
    #[default]
    Auto,
    /// An MCAP recording (ours or any ROS 2 recording with these message types).
    Mcap,
    /// A CMU-GPR sequence folder.
    CmuGpr,
    /// GSSI SIR `.DZT`.
    Dzt,
    /// Sensors & Software `.DT1` with its `.HD`.
    Dt1,
}

/// Parameters of the `ingest` stage.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IngestParams {
    /// The recording: an MCAP file, a CMU-GPR sequence folder, a `.DZT` or a `.DT1`.
    pub source: String,
    /// Its format (default `auto`).
    #[serde(default)]
    pub format: SourceFormat,
    /// `max` (default) or `recorded`.
    #[serde(default)]
    pub pace: Pace,
    /// Speed factor for `recorded` pace (default 1.0).
    #[serde(default = "one")]
    pub speed: f64,
    /// Time between traces when the file has no clock (DZT in wheel mode), s (default 0.01).
    #[serde(default = "default_trace_interval")]
    pub trace_interval_s: f64,
    /// Antenna centre frequency, Hz, when the file does not say (default: 500 MHz for CMU-GPR
    /// folders, the thesis rig's Noggin 500; NaN otherwise).
    #[serde(default)]
    pub center_frequency_hz: Option<f64>,
    /// MCAP sources: the topic behind each output (default: the recording's topic of the
    /// output's type; for sweeps the calibration topic is the one whose name has `calibration`,
    /// for truth the pose topic whose name has `truth`).
    #[serde(default)]
    pub topics: TopicMap,
    /// The wheel's calibration: every wheel distance and speed is multiplied by this (the true
    /// distance per recorded metre; `gprflow calibrate-wheel` measures it on recordings with
    /// ground truth). Default 1: the source's own distances.
    #[serde(default = "one")]
    pub wheel_scale: f64,
}

fn one() -> f64 {
    1.0
}

fn default_trace_interval() -> f64 {
    0.01
}

/// MCAP topics behind the outputs; unset ones are found by type.
#[derive(Debug, Clone, Default, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TopicMap {
    /// `gpr` output (Trace).
    pub gpr: Option<String>,
    /// `sweep` output (Sweep).
    pub sweep: Option<String>,
    /// `sweep_calibration` output (Sweep: the factory calibration).
    pub sweep_calibration: Option<String>,
    /// `imu` output (Imu).
    pub imu: Option<String>,
    /// `wheel` output (WheelOdometry).
    pub wheel: Option<String>,
    /// `truth` output (PoseStamped).
    pub truth: Option<String>,
}

/// The outputs; the declaration order is the output index (`port as usize`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Port {
    /// Raw traces.
    Gpr,
    /// SFCW sweeps.
    Sweep,
    /// The SFCW factory calibration.
    SweepCalibration,
    /// IMU samples.
    Imu,
    /// Wheel odometry.
    Wheel,
    /// Ground truth poses.
    Truth,
}

impl Port {
    /// Every port, in output order.
    pub const ALL: [Port; 6] = [
        Port::Gpr,
        Port::Sweep,
        Port::SweepCalibration,
        Port::Imu,
        Port::Wheel,
        Port::Truth,
    ];

    /// The output's name.
    pub fn name(self) -> &'static str {
        match self {
            Port::Gpr => "gpr",
            Port::Sweep => "sweep",
            Port::SweepCalibration => "sweep_calibration",
            Port::Imu => "imu",
            Port::Wheel => "wheel",
            Port::Truth => "truth",
        }
    }

    /// The output's message type.
    pub fn msg_type(self) -> &'static str {
        match self {
            Port::Gpr => Trace::TYPE_NAME,
            Port::Sweep | Port::SweepCalibration => Sweep::TYPE_NAME,
            Port::Imu => Imu::TYPE_NAME,
            Port::Wheel => WheelOdometry::TYPE_NAME,
            Port::Truth => PoseStamped::TYPE_NAME,
        }
    }

    /// The topic `gprflow convert` and the simulator use for it.
    pub fn topic(self) -> &'static str {
        match self {
            Port::Gpr => "/gpr/trace",
            Port::Sweep => "/lgpr/sweep",
            Port::SweepCalibration => "/lgpr/factory_calibration",
            Port::Imu => "/imu/data",
            Port::Wheel => "/wheel/odometry",
            Port::Truth => "/truth/pose",
        }
    }
}

/// A loaded source: encoded messages in stamp order, and what the reader skipped.
#[derive(Debug, Default)]
pub struct Loaded {
    /// (port, stamp ns, CDR payload), sorted by stamp (stable: file order among equal stamps).
    pub messages: Vec<(Port, i64, Vec<u8>)>,
    /// Records the reader skipped, or published with a corrected stamp: one line each (file,
    /// record, reason).
    pub dropped: Vec<String>,
    /// What was read, for logs: format and a short summary.
    pub summary: String,
}

/// Errors of [`load`].
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The reader refused the file.
    #[error(transparent)]
    Read(#[from] crate::Error),
    /// The MCAP recording cannot be opened.
    #[error("{0}")]
    Mcap(String),
    /// The format cannot be told from the path.
    #[error("{path}: cannot tell the format (a folder is a CMU-GPR sequence; files: .mcap, .dzt, .dt1); set `format`")]
    UnknownFormat {
        /// The source.
        path: PathBuf,
    },
    /// A parameter is out of range.
    #[error("{key}: {message}")]
    Param {
        /// The parameter.
        key: String,
        /// What is wrong.
        message: String,
    },
}

fn detect(path: &Path, format: SourceFormat) -> Result<SourceFormat, LoadError> {
    if format != SourceFormat::Auto {
        return Ok(format);
    }
    if path.is_dir() {
        return Ok(SourceFormat::CmuGpr);
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    match ext.as_str() {
        "mcap" => Ok(SourceFormat::Mcap),
        "dzt" => Ok(SourceFormat::Dzt),
        "dt1" => Ok(SourceFormat::Dt1),
        _ => Err(LoadError::UnknownFormat { path: path.into() }),
    }
}

/// Reads the source named in `params` into messages.
///
/// # Errors
/// The reader's error (naming the file, record and field), or an unknown format.
pub fn load(params: &IngestParams) -> Result<Loaded, LoadError> {
    if !(params.trace_interval_s.is_finite() && params.trace_interval_s > 0.0) {
        return Err(LoadError::Param {
            key: "trace_interval_s".into(),
            message: format!("must be finite and > 0, got {}", params.trace_interval_s),
        });
    }
    if !(params.wheel_scale.is_finite() && params.wheel_scale > 0.0) {
        return Err(LoadError::Param {
            key: "wheel_scale".into(),
            message: format!("must be finite and > 0, got {}", params.wheel_scale),
        });
    }
    let path = Path::new(&params.source);
    let mut loaded = match detect(path, params.format)? {
        SourceFormat::Mcap | SourceFormat::Auto => load_mcap(path, &params.topics)?,
        SourceFormat::CmuGpr => {
            let seq = crate::cmu::read_cmu_sequence(path)?;
            load_cmu(&seq, params)
        }
        SourceFormat::Dzt => {
            let (h, r) = crate::dzt::read_dzt(path)?;
            let mut l = load_radargram(&r, params);
            l.summary = format!(
                "DZT: {} traces x {} samples, {} channel(s), {} ns range, antenna {:?}",
                r.traces.len(),
                r.samples_per_trace,
                r.channels,
                h.range_ns,
                h.antenna_name
            );
            l
        }
        SourceFormat::Dt1 => {
            let (_, r) = crate::dt1::read_dt1(path)?;
            let mut l = load_radargram(&r, params);
            l.summary = format!(
                "DT1: {} traces x {} samples, {:.1} ns window",
                r.traces.len(),
                r.samples_per_trace,
                r.sample_interval_ns * r.samples_per_trace as f64
            );
            l
        }
    };
    if params.wheel_scale != 1.0 {
        scale_wheel(&mut loaded, path, params.wheel_scale);
    }
    loaded.messages.sort_by_key(|m| m.1);
    Ok(loaded)
}

/// Multiplies every wheel message's distance and speed by `scale`. A wheel payload that does
/// not decode is left out, with a line in `dropped` (its consumers could not read it either).
fn scale_wheel(loaded: &mut Loaded, path: &Path, scale: f64) {
    let mut dropped = Vec::new();
    loaded.messages.retain_mut(|(port, stamp, payload)| {
        if *port != Port::Wheel {
            return true;
        }
        match decode::<WheelOdometry>(payload) {
            Ok(mut w) => {
                w.distance_m *= scale;
                w.speed_mps *= scale;
                *payload = encode(&w);
                true
            }
            Err(e) => {
                dropped.push(format!(
                    "{}: wheel message at {stamp} ns: cannot be read to apply wheel_scale ({e}); left out",
                    path.display()
                ));
                false
            }
        }
    });
    loaded.dropped.extend(dropped);
}

fn center_frequency(r: &Radargram, params: &IngestParams) -> f64 {
    match params.center_frequency_hz {
        Some(f) => f,
        None if r.center_frequency_hz.is_finite() => r.center_frequency_hz,
        None if r.format == Format::CmuGpr => 500e6,
        None => f64::NAN,
    }
}

/// Traces of a radargram; a wheel message per trace when the file gives distances.
fn load_radargram(r: &Radargram, params: &IngestParams) -> Loaded {
    let fc = center_frequency(r, params);
    let mut loaded = Loaded {
        dropped: r.dropped.iter().map(ToString::to_string).collect(),
        ..Loaded::default()
    };
    let period_ns = params.trace_interval_s * 1e9;
    // scan index per channel: traces of one scan share a stamp
    let channels = usize::from(r.channels.max(1));
    let mut last_distance: Option<f64> = None;
    let mut last_stamp = i64::MIN;
    for (i, t) in r.traces.iter().enumerate() {
        let scan = i / channels;
        let mut stamp = t.stamp_ns.unwrap_or((scan as f64 * period_ns).round() as i64);
        if stamp < last_stamp {
            // a clock going back (a DT1's time of day past midnight): the trace keeps its
            // place in the line, published at the previous stamp, and is reported
            loaded.dropped.push(format!(
                "{}: trace {i}: stamp goes back from {last_stamp} to {stamp} ns: published at {last_stamp} ns",
                r.source.display()
            ));
            stamp = last_stamp;
        }
        last_stamp = stamp;
        let (i16s, i32s): (Cow<'_, [i16]>, Cow<'_, [i32]>) = match &t.samples {
            RawSamples::I16(v) => (Cow::Borrowed(v), Cow::Borrowed(&[])),
            RawSamples::I32(v) => (Cow::Borrowed(&[]), Cow::Borrowed(v)),
        };
        let msg = Trace {
            header: Header::new(stamp, "gpr"),
            channel: t.channel,
            sample_interval_ns: r.sample_interval_ns,
            time_zero_ns: r.time_zero_ns,
            center_frequency_hz: fc,
            distance_m: t.distance_m,
            samples_i16: i16s,
            samples_i32: i32s,
            samples_f32: Cow::Borrowed(&[]),
        };
        loaded.messages.push((Port::Gpr, stamp, encode(&msg)));
        if t.channel == 0 && t.distance_m.is_finite() {
            let speed = match last_distance {
                Some(d) => (t.distance_m - d) / params.trace_interval_s,
                None => 0.0,
            };
            last_distance = Some(t.distance_m);
            let w = WheelOdometry {
                header: Header::new(stamp, "odom"),
                distance_m: t.distance_m,
                ticks: 0,
                speed_mps: speed,
            };
            loaded.messages.push((Port::Wheel, stamp, encode(&w)));
        }
    }
    loaded
}

fn load_cmu(seq: &CmuSequence, params: &IngestParams) -> Loaded {
    let mut loaded = load_radargram(&seq.gpr, params);
    loaded.dropped.extend(seq.dropped.iter().map(ToString::to_string));
    let mut last: Option<(i64, f64)> = None;
    for w in &seq.wheel {
        let speed = match last {
            Some((t0, d0)) if w.stamp_ns > t0 => (w.distance_m - d0) / ((w.stamp_ns - t0) as f64 * 1e-9),
            _ => 0.0,
        };
        last = Some((w.stamp_ns, w.distance_m));
        let m = WheelOdometry {
            header: Header::new(w.stamp_ns, "odom"),
            distance_m: w.distance_m,
            ticks: 0,
            speed_mps: speed,
        };
        loaded.messages.push((Port::Wheel, w.stamp_ns, encode(&m)));
    }
    for s in seq.imu.iter().flatten() {
        let [qw, qx, qy, qz] = s.orientation_wxyz;
        let m = Imu {
            header: Header::new(s.stamp_ns, "imu"),
            orientation: Quaternion {
                x: qx,
                y: qy,
                z: qz,
                w: qw,
            },
            angular_velocity: Vector3 {
                x: s.gyro_radps[0],
                y: s.gyro_radps[1],
                z: s.gyro_radps[2],
            },
            linear_acceleration: Vector3 {
                x: s.accel_mps2[0],
                y: s.accel_mps2[1],
                z: s.accel_mps2[2],
            },
            ..Imu::default()
        };
        loaded.messages.push((Port::Imu, s.stamp_ns, encode(&m)));
    }
    for p in seq.truth.iter().flatten() {
        // the total station measures the prism position only: orientation left at identity
        let m = PoseStamped {
            header: Header::new(p.stamp_ns, "world"),
            pose: Pose {
                position: Point {
                    x: p.position_m[0],
                    y: p.position_m[1],
                    z: p.position_m[2],
                },
                orientation: Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 1.0,
                },
            },
        };
        loaded.messages.push((Port::Truth, p.stamp_ns, encode(&m)));
    }
    loaded.summary = format!(
        "CMU-GPR: {} traces x {} samples, {} IMU, {} wheel, {} truth rows",
        seq.gpr.traces.len(),
        seq.gpr.samples_per_trace,
        seq.imu.as_ref().map_or(0, Vec::len),
        seq.wheel.len(),
        seq.truth.as_ref().map_or(0, Vec::len)
    );
    loaded
}

/// The MCAP topic behind each port (explicit, else found by type and name).
fn mcap_topics(rec: &Recording, map: &TopicMap) -> Vec<(Port, String)> {
    let topics = rec.topics();
    let by_type = |ty: &str, want: &dyn Fn(&str) -> bool| {
        topics
            .iter()
            .find(|(name, t)| t == ty && want(name))
            .map(|(name, _)| name.clone())
    };
    let any = |_: &str| true;
    let pick = |explicit: &Option<String>, port: Port| -> Option<String> {
        if let Some(t) = explicit {
            return Some(t.clone());
        }
        match port {
            Port::Sweep => by_type(Sweep::TYPE_NAME, &|n: &str| !n.contains("calibration")),
            Port::SweepCalibration => by_type(Sweep::TYPE_NAME, &|n: &str| n.contains("calibration")),
            Port::Truth => by_type(PoseStamped::TYPE_NAME, &|n: &str| n.contains("truth")),
            other => by_type(other.msg_type(), &any),
        }
    };
    let explicit = [
        (Port::Gpr, &map.gpr),
        (Port::Sweep, &map.sweep),
        (Port::SweepCalibration, &map.sweep_calibration),
        (Port::Imu, &map.imu),
        (Port::Wheel, &map.wheel),
        (Port::Truth, &map.truth),
    ];
    explicit
        .into_iter()
        .filter_map(|(port, e)| pick(e, port).map(|t| (port, t)))
        .collect()
}

fn load_mcap(path: &Path, map: &TopicMap) -> Result<Loaded, LoadError> {
    let rec = Recording::open(path).map_err(|e| LoadError::Mcap(e.to_string()))?;
    let wanted = mcap_topics(&rec, map);
    let mut loaded = Loaded::default();
    let (_, stopped) = rec.scan(|m| {
        if let Some((port, _)) = wanted.iter().find(|(_, t)| *t == m.topic) {
            let stamp = i64::try_from(m.log_time).unwrap_or(i64::MAX);
            loaded.messages.push((*port, stamp, m.data.to_vec()));
        }
    });
    if let Some(at) = stopped {
        loaded.dropped.push(format!(
            "{}: read stopped early ({at}); the messages before it are kept",
            path.display()
        ));
    }
    loaded.summary = format!(
        "MCAP: {}",
        wanted
            .iter()
            .map(|(p, t)| format!("{} <- {t}", p.name()))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(loaded)
}

/// The ingest stage.
#[derive(Debug)]
pub struct IngestStage {
    player: Player,
}

impl Stage for IngestStage {
    type Params = IngestParams;
    const NAME: &'static str = "ingest";
    const ABOUT: &'static str =
        "reads a recording (MCAP, CMU-GPR folder, GSSI DZT, S&S DT1/HD): raw traces, sweeps, IMU, wheel, truth";

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(Port::ALL
            .iter()
            .map(|p| PortSpec::new(p.name(), p.msg_type()))
            .collect())
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        if !(params.speed.is_finite() && params.speed > 0.0) {
            return Err(ParamError {
                path: vec!["speed".to_owned()],
                message: format!("must be finite and > 0, got {}", params.speed),
            }
            .into());
        }
        let loaded = load(&params).map_err(|e| match e {
            LoadError::Param { key, message } => StageError::Params(ParamError {
                path: vec![key],
                message,
            }),
            other => StageError::failed(other),
        })?;
        tracing::info!("ingest: {}: {}", params.source, loaded.summary);
        for d in loaded.dropped.iter().take(20) {
            tracing::warn!("ingest: skipped {d}");
        }
        if loaded.dropped.len() > 20 {
            tracing::warn!("ingest: ... {} records skipped in all", loaded.dropped.len());
        }
        // port order = output order
        debug_assert!(ports.outputs().iter().zip(Port::ALL).all(|(o, p)| o.name == p.name()));
        let messages = loaded
            .messages
            .into_iter()
            .map(|(port, stamp, data)| (port as usize, stamp, data))
            .collect();
        Ok(Self {
            player: Player::new(messages, params.pace, params.speed),
        })
    }

    fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        self.player.produce(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::radargram::RawTrace;

    fn params() -> IngestParams {
        IngestParams {
            source: "x.dt1".into(),
            format: SourceFormat::Auto,
            pace: Pace::Max,
            speed: 1.0,
            trace_interval_s: 0.01,
            center_frequency_hz: None,
            topics: TopicMap::default(),
            wheel_scale: 1.0,
        }
    }

    #[test]
    fn a_clock_going_back_keeps_every_trace_in_order_and_is_reported() {
        let trace = |stamp_ns: i64, v: i16| RawTrace {
            channel: 0,
            stamp_ns: Some(stamp_ns),
            distance_m: f64::from(v),
            samples: RawSamples::I16(vec![v; 3]),
        };
        let r = Radargram {
            source: "line.DT1".into(),
            format: Format::Dt1,
            channels: 1,
            samples_per_trace: 3,
            sample_interval_ns: 0.8,
            time_zero_ns: 0.0,
            center_frequency_hz: 50e6,
            traces: vec![trace(100, 1), trace(200, 2), trace(50, 3), trace(300, 4)],
            dropped: Vec::new(),
        };
        let mut l = load_radargram(&r, &params());
        l.messages.sort_by_key(|m| m.1);
        let traces: Vec<(i64, i16)> = l
            .messages
            .iter()
            .filter(|m| m.0 == Port::Gpr)
            .map(|m| {
                let t: Trace = gprflow_msg::decode(&m.2).expect("decodes");
                (m.1, t.samples_i16[0])
            })
            .collect();
        assert_eq!(traces, vec![(100, 1), (200, 2), (200, 3), (300, 4)]);
        assert_eq!(l.dropped.len(), 1);
        assert!(
            l.dropped[0].contains("line.DT1: trace 2: stamp goes back from 200 to 50 ns"),
            "{:?}",
            l.dropped
        );
    }

    #[test]
    fn a_ports_discriminant_is_its_output_index() {
        for (i, p) in Port::ALL.iter().enumerate() {
            assert_eq!(*p as usize, i, "{}", p.name());
        }
    }

    #[test]
    fn unknown_extensions_and_bad_intervals_are_refused_with_the_key() {
        let e = load(&IngestParams {
            source: "notes.txt".into(),
            ..params()
        })
        .expect_err("refused");
        assert!(e.to_string().contains("notes.txt: cannot tell the format"), "{e}");
        let e = load(&IngestParams {
            trace_interval_s: 0.0,
            ..params()
        })
        .expect_err("refused");
        assert!(e.to_string().starts_with("trace_interval_s:"), "{e}");
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = load(&IngestParams {
                wheel_scale: bad,
                ..params()
            })
            .expect_err("refused");
            assert!(e.to_string().starts_with("wheel_scale: must be finite and > 0"), "{e}");
        }
    }

    #[test]
    fn wheel_scale_multiplies_distances_and_speeds_and_leaves_out_what_does_not_decode() {
        let wheel = |d: f64, v: f64| {
            encode(&WheelOdometry {
                header: Header::new(0, "odom"),
                distance_m: d,
                ticks: 7,
                speed_mps: v,
            })
        };
        let imu = encode(&Imu::default());
        let mut l = Loaded {
            messages: vec![
                (Port::Wheel, 10, wheel(2.0, 0.5)),
                (Port::Imu, 15, imu.clone()),
                (Port::Wheel, 20, vec![1, 2, 3]),
                (Port::Wheel, 30, wheel(-1.0, -0.25)),
            ],
            ..Loaded::default()
        };
        scale_wheel(&mut l, Path::new("run.mcap"), 0.99);
        let stamps: Vec<i64> = l.messages.iter().map(|m| m.1).collect();
        assert_eq!(stamps, vec![10, 15, 30]);
        assert_eq!(l.messages[1].2, imu, "other ports untouched");
        let w: Vec<WheelOdometry> = [0, 2]
            .iter()
            .map(|&i| decode(&l.messages[i].2).expect("decodes"))
            .collect();
        assert!((w[0].distance_m - 1.98).abs() < 1e-12 && (w[0].speed_mps - 0.495).abs() < 1e-12);
        assert!((w[1].distance_m + 0.99).abs() < 1e-12 && (w[1].speed_mps + 0.2475).abs() < 1e-12);
        assert_eq!(w[0].ticks, 7, "ticks are counts: unscaled");
        assert_eq!(l.dropped.len(), 1);
        assert!(
            l.dropped[0].starts_with("run.mcap: wheel message at 20 ns: cannot be read"),
            "{:?}",
            l.dropped
        );
    }
}
