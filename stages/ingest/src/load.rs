//! A recording as runtime messages: [`load`] reads a source (MCAP, CMU-GPR folder, DZT,
//! DT1/HD) into its raw traces, sweeps, IMU, wheel odometry and ground truth, encoded, in stamp
//! order. The `ingest` stage plays what it returns; `gprflow convert` writes it to MCAP.

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use gprflow_msg::{
    Header, Imu, Message, Odometry, Point, Pose, PoseStamped, Quaternion, Sweep, Trace, Vector3, WheelOdometry, decode,
    encode,
};
use gprflow_record::{Recording, seconds_window};

use crate::cmu::{CmuCounts, CmuRow, CmuSequence, CmuStream, ImuRow, TruthRow, WheelRow};
use crate::error::{Error, Result};
use crate::format::SourceFormat;
use crate::radargram::{Format, Radargram, RawSamples, RawTrace};

/// What a loaded message is: one of the `ingest` stage's outputs, whose declaration order is
/// the output index (`port as usize`).
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
    /// GPS/INS fixes (`nav_msgs/Odometry`: position, orientation, body velocity).
    Gps,
}

impl Port {
    /// Every port, in output order.
    pub const ALL: [Port; 7] = [
        Port::Gpr,
        Port::Sweep,
        Port::SweepCalibration,
        Port::Imu,
        Port::Wheel,
        Port::Truth,
        Port::Gps,
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
            Port::Gps => "gps",
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
            Port::Gps => Odometry::TYPE_NAME,
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
            Port::Gps => "/gps/odometry",
        }
    }
}

/// MCAP topics behind the outputs; unset ones are found by type.
#[derive(Debug, Clone, Default, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
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
    /// `gps` output (Odometry).
    pub gps: Option<String>,
}

/// How [`load`] turns a source into messages where the file does not say everything. The
/// defaults are the `ingest` stage's.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    /// Time between traces when the file has no clock (DZT in wheel mode), s; finite and > 0
    /// (default 0.01).
    pub trace_interval_s: f64,
    /// Antenna centre frequency, Hz, when the file does not say (default: 500 MHz for CMU-GPR
    /// folders, the thesis rig's Noggin 500; NaN otherwise).
    pub center_frequency_hz: Option<f64>,
    /// MCAP sources: the topic behind each port (default: found by type and name).
    pub topics: TopicMap,
    /// Every wheel distance and speed is multiplied by this; finite and > 0 (default 1: the
    /// source's own distances).
    pub wheel_scale: f64,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            trace_interval_s: 0.01,
            center_frequency_hz: None,
            topics: TopicMap::default(),
            wheel_scale: 1.0,
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

/// Reads `path`, in `format` ([`SourceFormat::Auto`]: told by [`crate::format::detect`]), into
/// messages sorted by stamp.
///
/// # Errors
/// The reader's error (naming the file, record and field), [`Error::UnknownFormat`], or
/// [`Error::Recording`] for an MCAP file that cannot be opened.
pub fn load(path: &Path, format: SourceFormat, options: &LoadOptions) -> Result<Loaded> {
    let mut loaded = match format.resolve(path)? {
        SourceFormat::Mcap | SourceFormat::Auto => load_mcap(path, &options.topics)?,
        SourceFormat::CmuGpr => {
            let seq = crate::cmu::read_cmu_sequence(path)?;
            load_cmu(&seq, options)
        }
        SourceFormat::Dzt => {
            let (h, r) = crate::dzt::read_dzt(path)?;
            let mut l = load_radargram(&r, options);
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
            let mut l = load_radargram(&r, options);
            l.summary = format!(
                "DT1: {} traces x {} samples, {:.1} ns window",
                r.traces.len(),
                r.samples_per_trace,
                r.sample_interval_ns * r.samples_per_trace as f64
            );
            l
        }
    };
    if options.wheel_scale != 1.0 {
        scale_wheel(&mut loaded, path, options.wheel_scale);
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
        match scaled_wheel(payload, scale, path, *stamp) {
            Ok(scaled) => {
                *payload = scaled;
                true
            }
            Err(why) => {
                dropped.push(why);
                false
            }
        }
    });
    loaded.dropped.extend(dropped);
}

/// A wheel payload with its distance and speed multiplied by `scale`; `Err` says (naming the
/// file and stamp) why it cannot be.
fn scaled_wheel(payload: &[u8], scale: f64, path: &Path, stamp: i64) -> std::result::Result<Vec<u8>, String> {
    let mut w = decode::<WheelOdometry>(payload).map_err(|e| {
        format!(
            "{}: wheel message at {stamp} ns: cannot be read to apply wheel_scale ({e}); left out",
            path.display()
        )
    })?;
    w.distance_m *= scale;
    w.speed_mps *= scale;
    Ok(encode(&w))
}

fn center_frequency(r: &Radargram, options: &LoadOptions) -> f64 {
    match options.center_frequency_hz {
        Some(f) => f,
        None if r.center_frequency_hz.is_finite() => r.center_frequency_hz,
        None if r.format == Format::CmuGpr => 500e6,
        None => f64::NAN,
    }
}

/// Traces of a radargram; a wheel message per trace when the file gives distances.
fn load_radargram(r: &Radargram, options: &LoadOptions) -> Loaded {
    let mut messages = TraceMessages::new(r, options);
    let mut loaded = Loaded {
        dropped: r.dropped.iter().map(ToString::to_string).collect(),
        ..Loaded::default()
    };
    for (i, t) in r.traces.iter().enumerate() {
        messages.push(i, t, &mut loaded.messages);
    }
    loaded.dropped.append(&mut messages.corrected);
    loaded
}

/// Turns a radargram's traces, in file order, into trace and wheel messages (one trace at a
/// time: the same for a file read whole and one streamed).
#[derive(Debug)]
struct TraceMessages {
    source: PathBuf,
    channels: usize,
    sample_interval_ns: f64,
    time_zero_ns: f64,
    center_frequency_hz: f64,
    trace_interval_s: f64,
    last_distance: Option<f64>,
    last_stamp: i64,
    /// Traces published at a corrected stamp: one line each.
    corrected: Vec<String>,
}

impl TraceMessages {
    fn new(r: &Radargram, options: &LoadOptions) -> Self {
        Self {
            source: r.source.clone(),
            channels: usize::from(r.channels.max(1)),
            sample_interval_ns: r.sample_interval_ns,
            time_zero_ns: r.time_zero_ns,
            center_frequency_hz: center_frequency(r, options),
            trace_interval_s: options.trace_interval_s,
            last_distance: None,
            last_stamp: i64::MIN,
            corrected: Vec::new(),
        }
    }

    /// The messages of trace number `i` (in file order), appended to `out`.
    fn push(&mut self, i: usize, t: &RawTrace, out: &mut Vec<(Port, i64, Vec<u8>)>) {
        // scan index per channel: traces of one scan share a stamp
        let scan = i / self.channels;
        let period_ns = self.trace_interval_s * 1e9;
        let mut stamp = t.stamp_ns.unwrap_or((scan as f64 * period_ns).round() as i64);
        if stamp < self.last_stamp {
            // a clock going back (a DT1's time of day past midnight): the trace keeps its
            // place in the line, published at the previous stamp, and is reported
            self.corrected.push(format!(
                "{}: trace {i}: stamp goes back from {} to {stamp} ns: published at {} ns",
                self.source.display(),
                self.last_stamp,
                self.last_stamp
            ));
            stamp = self.last_stamp;
        }
        self.last_stamp = stamp;
        let (i16s, i32s): (Cow<'_, [i16]>, Cow<'_, [i32]>) = match &t.samples {
            RawSamples::I16(v) => (Cow::Borrowed(v), Cow::Borrowed(&[])),
            RawSamples::I32(v) => (Cow::Borrowed(&[]), Cow::Borrowed(v)),
        };
        let msg = Trace {
            header: Header::new(stamp, "gpr"),
            channel: t.channel,
            sample_interval_ns: self.sample_interval_ns,
            time_zero_ns: self.time_zero_ns,
            center_frequency_hz: self.center_frequency_hz,
            distance_m: t.distance_m,
            samples_i16: i16s,
            samples_i32: i32s,
            samples_f32: Cow::Borrowed(&[]),
        };
        out.push((Port::Gpr, stamp, encode(&msg)));
        if t.channel == 0 && t.distance_m.is_finite() {
            let speed = match self.last_distance {
                Some(d) => (t.distance_m - d) / self.trace_interval_s,
                None => 0.0,
            };
            self.last_distance = Some(t.distance_m);
            let w = WheelOdometry {
                header: Header::new(stamp, "odom"),
                distance_m: t.distance_m,
                ticks: 0,
                speed_mps: speed,
            };
            out.push((Port::Wheel, stamp, encode(&w)));
        }
    }
}

/// A radar file read trace by trace ([`crate::dzt::DztStream`], [`crate::dt1::Dt1Stream`]).
pub trait TraceStream: Iterator<Item = RawTrace> + Send {
    /// Records skipped so far (taken: each is returned once).
    fn take_dropped(&mut self) -> Vec<crate::error::Dropped>;
}

impl TraceStream for crate::dzt::DztStream {
    fn take_dropped(&mut self) -> Vec<crate::error::Dropped> {
        std::mem::take(&mut self.dropped)
    }
}

impl TraceStream for crate::dt1::Dt1Stream {
    fn take_dropped(&mut self) -> Vec<crate::error::Dropped> {
        std::mem::take(&mut self.dropped)
    }
}

/// A DZT or DT1 file or a CMU-GPR folder streamed from disk as the `ingest` stage's messages
/// (what [`load`] gives for it, in the same order), trace by trace or row by row: memory does
/// not grow with the file. Wheel messages are scaled as they pass; skipped and corrected
/// records are logged as warnings naming the file.
pub struct RadarMessages {
    rows: Rows,
    convert: TraceMessages,
    index: usize,
    queue: std::collections::VecDeque<(Port, i64, Vec<u8>)>,
    wheel_scale: f64,
    /// A CMU-GPR folder's previous wheel row: stamp and distance (for the speed).
    last_wheel: Option<(i64, f64)>,
    warned: usize,
    /// Messages in all (traces, and wheel messages where the file gives distances; a CMU-GPR
    /// folder's rows), when known.
    pub total: Option<usize>,
    /// What was read, for logs.
    pub summary: String,
}

/// Where a [`RadarMessages`] takes its records.
enum Rows {
    /// A radar file's traces.
    Traces(Box<dyn TraceStream>),
    /// A CMU-GPR folder's rows, in stamp order.
    Cmu(CmuStream),
}

impl std::fmt::Debug for RadarMessages {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RadarMessages")
            .field("summary", &self.summary)
            .finish_non_exhaustive()
    }
}

/// Warnings a streamed source logs one by one before it only counts them.
const WARN_AT_MOST: usize = 20;

impl RadarMessages {
    /// Opens `path` in `format` (DZT, DT1 or CMU-GPR) and checks its header (a DT1: every
    /// trace header; a CMU-GPR folder: every line of every file, refused as
    /// [`crate::cmu::read_cmu_sequence`] refuses it). With `start_s`, a DZT starts at its first
    /// scan stamped that late or later (its stamps count from 0) without reading the scans
    /// before it, giving the messages [`load`] gives from there; a DT1 and a CMU-GPR folder
    /// (stamped by their clocks) start at their beginning.
    ///
    /// # Errors
    /// As [`crate::dzt::read_dzt`], [`crate::dt1::read_dt1`] and
    /// [`crate::cmu::read_cmu_sequence`]; [`Error::UnknownFormat`] for another format; a DZT
    /// that cannot seek.
    pub fn open(path: &Path, format: SourceFormat, options: &LoadOptions, start_s: Option<f64>) -> Result<Self> {
        let mut first_index = 0;
        let mut distance_before = None;
        let (r, rows, total, summary): (Radargram, Rows, Option<usize>, String) = match format {
            SourceFormat::Dzt => {
                let (h, r, mut traces) = crate::dzt::DztStream::open(path)?;
                let scans = traces.scans();
                let wheel = usize::from(h.scans_per_metre.is_finite() && h.scans_per_metre > 0.0);
                let summary = format!(
                    "DZT (streamed): {} traces x {} samples, {} channel(s), {} ns range, antenna {:?}",
                    scans * usize::from(r.channels),
                    r.samples_per_trace,
                    r.channels,
                    h.range_ns,
                    h.antenna_name
                );
                let mut total = Some(scans * (usize::from(r.channels) + wheel));
                if let Some(start_s) = start_s {
                    let (scan, before) = traces.seek_stamp((start_s * 1e9).round() as i64, options.trace_interval_s)?;
                    first_index = scan * traces.channels().max(1);
                    distance_before = before;
                    total = None;
                }
                (r, Rows::Traces(Box::new(traces)), total, summary)
            }
            SourceFormat::Dt1 => {
                let (_, r, traces) = crate::dt1::Dt1Stream::open(path)?;
                let n = traces.traces();
                let summary = format!(
                    "DT1 (streamed): {n} traces x {} samples, {:.1} ns window",
                    r.samples_per_trace,
                    r.sample_interval_ns * r.samples_per_trace as f64
                );
                // a wheel message per trace: DT1 traces carry their position
                (r, Rows::Traces(Box::new(traces)), Some(2 * n), summary)
            }
            SourceFormat::CmuGpr => {
                let (counts, r, rows) = CmuStream::open(path)?;
                let summary = cmu_summary("CMU-GPR (streamed)", &counts, r.samples_per_trace);
                // a message per row: the traces carry no distance
                (r, Rows::Cmu(rows), Some(counts.rows()), summary)
            }
            _ => return Err(Error::UnknownFormat { path: path.into() }),
        };
        let mut convert = TraceMessages::new(&r, options);
        convert.last_distance = distance_before;
        Ok(Self {
            convert,
            summary,
            total,
            rows,
            index: first_index,
            queue: std::collections::VecDeque::new(),
            wheel_scale: options.wheel_scale,
            last_wheel: None,
            warned: 0,
        })
    }

    fn warn(&mut self, what: &str) {
        if self.warned < WARN_AT_MOST {
            tracing::warn!("ingest: skipped {what}");
        }
        self.warned += 1;
    }

    /// The messages of the next trace or row, appended to `out`; false at the end. Skipped
    /// records found on the way are warned of.
    fn read_next(&mut self, out: &mut Vec<(Port, i64, Vec<u8>)>) -> bool {
        let (record, dropped) = match &mut self.rows {
            // a radar file's trace is what a CMU-GPR folder's radar row reads as
            Rows::Traces(traces) => (traces.next().map(CmuRow::Gpr), traces.take_dropped()),
            Rows::Cmu(rows) => (rows.next(), std::mem::take(&mut rows.dropped)),
        };
        for d in dropped {
            self.warn(&d.to_string());
        }
        match record {
            None => return false,
            Some(CmuRow::Gpr(trace)) => {
                self.convert.push(self.index, &trace, out);
                self.index += 1;
                for line in std::mem::take(&mut self.convert.corrected) {
                    self.warn(&line);
                }
            }
            Some(CmuRow::Wheel(w)) => out.push(wheel_message(&w, &mut self.last_wheel)),
            Some(CmuRow::Imu(s)) => out.push(imu_message(&s)),
            Some(CmuRow::Truth(p)) => out.push(truth_message(&p)),
        }
        true
    }
}

impl Iterator for RadarMessages {
    type Item = (Port, i64, Vec<u8>);

    fn next(&mut self) -> Option<Self::Item> {
        while self.queue.is_empty() {
            let mut out = Vec::with_capacity(2);
            if !self.read_next(&mut out) {
                if self.warned > WARN_AT_MOST {
                    tracing::warn!("ingest: ... {} records skipped or corrected in all", self.warned);
                }
                return None;
            }
            for (port, stamp, payload) in out {
                if port == Port::Wheel && self.wheel_scale != 1.0 {
                    match scaled_wheel(&payload, self.wheel_scale, &self.convert.source, stamp) {
                        Ok(scaled) => self.queue.push_back((port, stamp, scaled)),
                        Err(why) => self.warn(&why),
                    }
                } else {
                    self.queue.push_back((port, stamp, payload));
                }
            }
        }
        self.queue.pop_front()
    }
}

fn load_cmu(seq: &CmuSequence, options: &LoadOptions) -> Loaded {
    let mut loaded = load_radargram(&seq.gpr, options);
    loaded.dropped.extend(seq.dropped.iter().map(ToString::to_string));
    let mut last_wheel = None;
    for w in &seq.wheel {
        loaded.messages.push(wheel_message(w, &mut last_wheel));
    }
    loaded.messages.extend(seq.imu.iter().flatten().map(imu_message));
    loaded.messages.extend(seq.truth.iter().flatten().map(truth_message));
    loaded.summary = cmu_summary("CMU-GPR", &seq.counts(), seq.gpr.samples_per_trace);
    loaded
}

fn cmu_summary(what: &str, counts: &CmuCounts, samples_per_trace: usize) -> String {
    format!(
        "{what}: {} traces x {samples_per_trace} samples, {} IMU, {} wheel, {} truth rows",
        counts.gpr,
        counts.imu.unwrap_or(0),
        counts.wheel,
        counts.truth.unwrap_or(0)
    )
}

/// A wheel row as a message, its speed from `last` (the previous row's stamp and distance),
/// which it then holds.
fn wheel_message(w: &WheelRow, last: &mut Option<(i64, f64)>) -> (Port, i64, Vec<u8>) {
    let speed = match *last {
        Some((t0, d0)) if w.stamp_ns > t0 => (w.distance_m - d0) / ((w.stamp_ns - t0) as f64 * 1e-9),
        _ => 0.0,
    };
    *last = Some((w.stamp_ns, w.distance_m));
    let m = WheelOdometry {
        header: Header::new(w.stamp_ns, "odom"),
        distance_m: w.distance_m,
        ticks: 0,
        speed_mps: speed,
    };
    (Port::Wheel, w.stamp_ns, encode(&m))
}

fn imu_message(s: &ImuRow) -> (Port, i64, Vec<u8>) {
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
    (Port::Imu, s.stamp_ns, encode(&m))
}

fn truth_message(p: &TruthRow) -> (Port, i64, Vec<u8>) {
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
    (Port::Truth, p.stamp_ns, encode(&m))
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
        (Port::Gps, &map.gps),
    ];
    explicit
        .into_iter()
        .filter_map(|(port, e)| pick(e, port).map(|t| (port, t)))
        .collect()
}

fn load_mcap(path: &Path, map: &TopicMap) -> Result<Loaded> {
    let rec = open_mcap(path)?;
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
    loaded.summary = mcap_summary(&wanted);
    Ok(loaded)
}

fn open_mcap(path: &Path) -> Result<Recording> {
    Recording::open(path).map_err(|e| Error::Recording {
        path: path.into(),
        message: e.to_string(),
    })
}

fn mcap_summary(wanted: &[(Port, String)]) -> String {
    format!(
        "MCAP: {}",
        wanted
            .iter()
            .map(|(p, t)| format!("{} <- {t}", p.name()))
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// An MCAP source streamed from disk: what [`load`] gives for it, one message at a time, so
/// memory does not grow with the recording. Messages come in stamp order within the window
/// (see [`gprflow_record::Recording::messages`]); wheel messages are scaled as they pass, and
/// one that does not decode is left out with a warning naming the file and stamp.
pub struct McapStream {
    messages: gprflow_record::Messages,
    ports: HashMap<Arc<str>, Port>,
    wheel_scale: f64,
    path: PathBuf,
    /// What was read, for logs.
    pub summary: String,
}

impl std::fmt::Debug for McapStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapStream")
            .field("path", &self.path)
            .field("summary", &self.summary)
            .finish_non_exhaustive()
    }
}

impl McapStream {
    /// Opens `path`, picks the topic behind each port and reads those topics from `start_s`
    /// to `end_s` seconds after the recording's first message (checked by
    /// [`gprflow_record::check_window`]; `None`: from its start, to its end).
    ///
    /// # Errors
    /// [`Error::Recording`] for a file that cannot be opened.
    pub fn open(path: &Path, options: &LoadOptions, start_s: Option<f64>, end_s: Option<f64>) -> Result<Self> {
        let rec = open_mcap(path)?;
        let mut window = seconds_window(&rec, start_s, end_s);
        let wanted = mcap_topics(&rec, &options.topics);
        window.topics = Some(wanted.iter().map(|(_, t)| t.clone()).collect());
        let messages = rec.messages(&window).map_err(|e| Error::Recording {
            path: path.into(),
            message: e.to_string(),
        })?;
        Ok(Self {
            messages,
            ports: wanted.iter().map(|(p, t)| (Arc::from(t.as_str()), *p)).collect(),
            wheel_scale: options.wheel_scale,
            path: path.into(),
            summary: mcap_summary(&wanted),
        })
    }

    /// Messages on the chosen topics in all (whole-time windows of indexed files only).
    pub fn total(&self) -> Option<usize> {
        self.messages.total().and_then(|t| usize::try_from(t).ok())
    }
}

impl Iterator for McapStream {
    type Item = (Port, i64, Vec<u8>);

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let m = self.messages.next()?;
            let Some(&port) = self.ports.get(&m.topic) else {
                continue;
            };
            let stamp = i64::try_from(m.log_time).unwrap_or(i64::MAX);
            if port == Port::Wheel && self.wheel_scale != 1.0 {
                match scaled_wheel(&m.data, self.wheel_scale, &self.path, stamp) {
                    Ok(scaled) => return Some((port, stamp, scaled)),
                    Err(why) => {
                        tracing::warn!("{why}");
                        continue;
                    }
                }
            }
            return Some((port, stamp, m.data));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::radargram::RawTrace;

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
        let mut l = load_radargram(&r, &LoadOptions::default());
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
    fn an_unknown_extension_is_refused_naming_the_file() {
        let e = load(Path::new("notes.txt"), SourceFormat::Auto, &LoadOptions::default()).expect_err("refused");
        assert!(e.to_string().contains("notes.txt: cannot tell the format"), "{e}");
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
