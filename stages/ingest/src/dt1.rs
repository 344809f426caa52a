//! Sensors & Software pulseEKKO `.DT1` data with its `.HD` header.
//!
//! The `.HD` is ASCII text: a few free lines (a `1234` tag, the system, the date), then
//! `KEY = value` lines ([`HdHeader`]). The `.DT1` holds, per trace, a 128-byte little-endian
//! header ([`Dt1TraceHeader`]) and the samples as int16 (int32 when the trace header says 4
//! bytes per sample).
//!
//! What the reader decides:
//! - **The HD governs the time axis**: `sample_interval_ns = TOTAL TIME WINDOW / NUMBER OF
//!   PTS/TRC`. The trace header's own "time window" is kept in [`Dt1TraceHeader::time_window`]
//!   but not used: in both real files it is not the window (800 and 400 against HD windows of
//!   1200 and 760 ns) but equals the HD's sample interval in picoseconds.
//! - **Time zero**: `TIMEZERO AT POINT` is a 1-based sample number, so sample 0 is at
//!   `-(point - 1) * sample_interval_ns`.
//! - **Distance**: the trace header's position, converted from `POSITION UNITS` to metres
//!   (`ft` x 0.3048, `in`, `cm`, `mm`, `km`, `m`; metres when the HD names no unit). Other
//!   units are an error.
//! - **Stamps**: the trace header's time of day (seconds since midnight of the survey day on
//!   the instrument's clock, time zone unknown), rounded to ns. `None` when every trace has 0
//!   there (a system that does not fill it).
//! - **Checks**: every trace header must give the HD's sample count and the first trace's bytes
//!   per sample ([`Error::Disagree`]). A file that ends inside a trace keeps the complete traces
//!   and reports the cut one in [`Radargram::dropped`], provided the HD promises at least that
//!   many traces; otherwise a trace count other than the HD's is an [`Error::Disagree`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{DropReason, Dropped, Error, Record, Result};
use crate::radargram::{Format, Radargram, RawTrace, ascii_text, le_bytes, signed_le_samples};

/// Size of a DT1 trace header (bytes).
pub const DT1_TRACE_HEADER_BYTES: usize = 128;

/// The `.HD` file: the documented keys parsed, everything else kept as text.
///
/// Lengths (`*_position`, `step_size`, `antenna_separation`) are in the HD's
/// [`position_units`](Self::position_units); [`metres_per_unit`](Self::metres_per_unit) converts.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct HdHeader {
    /// The lines that are not `KEY = value`, in order, trimmed, blank ones left out (in the
    /// real files: the `1234` tag, the system, the date).
    pub text_lines: Vec<String>,
    /// `NUMBER OF TRACES`.
    pub number_of_traces: usize,
    /// `NUMBER OF PTS/TRC`: samples per trace.
    pub points_per_trace: usize,
    /// `TIMEZERO AT POINT`: the 1-based sample number of time zero (fractional).
    pub timezero_at_point: Option<f64>,
    /// `TOTAL TIME WINDOW` (ns).
    pub total_time_window_ns: f64,
    /// `STARTING POSITION`, in position units.
    pub starting_position: Option<f64>,
    /// `FINAL POSITION`, in position units.
    pub final_position: Option<f64>,
    /// `STEP SIZE USED`, in position units.
    pub step_size: Option<f64>,
    /// `POSITION UNITS` as written (`m`, `ft`).
    pub position_units: Option<String>,
    /// `NOMINAL FREQUENCY` (MHz).
    pub nominal_frequency_mhz: Option<f64>,
    /// `ANTENNA SEPARATION`, in position units.
    pub antenna_separation: Option<f64>,
    /// `PULSER VOLTAGE (V)` (V).
    pub pulser_voltage_v: Option<f64>,
    /// `NUMBER OF STACKS`.
    pub number_of_stacks: Option<u32>,
    /// `SURVEY MODE` (`Reflection`, ...).
    pub survey_mode: Option<String>,
    /// Every other `KEY = value` line (serial numbers, batteries, `STACKING TYPE`,
    /// `ODOMETER CAL (t/m)`, ...), keys and values trimmed.
    pub other: BTreeMap<String, String>,
}

impl HdHeader {
    /// Metres per position unit: `m` 1, `ft` 0.3048, `in` 0.0254, `cm` 0.01, `mm` 0.001,
    /// `km` 1000 (case-insensitive); 1 when the HD gives no unit; `None` for anything else.
    pub fn metres_per_unit(&self) -> Option<f64> {
        let Some(unit) = &self.position_units else {
            return Some(1.0);
        };
        match unit.trim().to_ascii_lowercase().as_str() {
            "m" | "metres" | "meters" => Some(1.0),
            "ft" | "feet" => Some(0.3048),
            "in" | "inches" => Some(0.0254),
            "cm" => Some(0.01),
            "mm" => Some(0.001),
            "km" => Some(1000.0),
            _ => None,
        }
    }

    /// Time between samples (ns): the window over the points per trace.
    pub fn sample_interval_ns(&self) -> f64 {
        self.total_time_window_ns / self.points_per_trace as f64
    }
}

/// One 128-byte DT1 trace header, every field as stored (`f32` unless said; the byte offset
/// of each is in its doc). Lengths are in the HD's position units.
#[derive(Debug, Clone, PartialEq)]
pub struct Dt1TraceHeader {
    /// (0) Trace number, counted from 1.
    pub trace_number: f32,
    /// (4) Position along the line, in position units.
    pub position: f32,
    /// (8) Samples in the trace.
    pub samples: f32,
    /// (12) Topography (elevation), in position units.
    pub topography: f32,
    /// (16) Unused (in `SnS_WARR_XLINE00.DT1` it holds an integer, the position in mm, whose
    /// bits read as a denormal float).
    pub unused_16: f32,
    /// (20) Bytes per sample (2 or 4).
    pub bytes_per_sample: f32,
    /// (24) Time window as the trace header gives it; see the module docs for why it is not used.
    pub time_window: f32,
    /// (28) Number of stacks.
    pub stacks: f32,
    /// (32, 3 x `f64`) GPS x, y, z.
    pub gps_xyz: [f64; 3],
    /// (56) Receiver x, y, z, in position units.
    pub receiver_xyz: [f32; 3],
    /// (68) Transmitter x, y, z, in position units.
    pub transmitter_xyz: [f32; 3],
    /// (80) Time-zero adjustment (the format leaves the unit to the system; in the real
    /// files 0).
    pub time_zero_adjustment: f32,
    /// (84) Zero flag: 0 data ok, 1 zero data.
    pub zero_flag: f32,
    /// (88) Unused.
    pub unused_88: f32,
    /// (92) Time of day the trace was taken (s since midnight).
    pub time_of_day_s: f32,
    /// (96) Comment flag: 1 when the comment holds text.
    pub comment_flag: f32,
    /// (100, 28 bytes) Comment, up to the first NUL, non-ASCII bytes replaced.
    pub comment: String,
}

impl Dt1TraceHeader {
    /// Parses a 128-byte trace header; `None` when `bytes` is shorter.
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        if bytes.len() < DT1_TRACE_HEADER_BYTES {
            return None;
        }
        let f = |at| f32::from_le_bytes(le_bytes(bytes, at));
        let d = |at| f64::from_le_bytes(le_bytes(bytes, at));
        Some(Self {
            trace_number: f(0),
            position: f(4),
            samples: f(8),
            topography: f(12),
            unused_16: f(16),
            bytes_per_sample: f(20),
            time_window: f(24),
            stacks: f(28),
            gps_xyz: [d(32), d(40), d(48)],
            receiver_xyz: [f(56), f(60), f(64)],
            transmitter_xyz: [f(68), f(72), f(76)],
            time_zero_adjustment: f(80),
            zero_flag: f(84),
            unused_88: f(88),
            time_of_day_s: f(92),
            comment_flag: f(96),
            comment: ascii_text(bytes.get(100..128).unwrap_or_default()),
        })
    }
}

/// A DT1 line with everything the reader found: the HD, every trace header and the radargram.
#[derive(Debug, Clone, PartialEq)]
pub struct Dt1Line {
    /// Where the HD was found.
    pub hd_path: PathBuf,
    /// The HD.
    pub hd: HdHeader,
    /// One per trace of `radargram`, in the same order.
    pub trace_headers: Vec<Dt1TraceHeader>,
    /// The traces.
    pub radargram: Radargram,
}

/// Reads a DT1 file and the `.HD` beside it (same stem, extension `hd` in any case).
pub fn read_dt1(dt1: &Path) -> Result<(HdHeader, Radargram)> {
    let line = read_dt1_line(dt1)?;
    Ok((line.hd, line.radargram))
}

/// Like [`read_dt1`], keeping every trace header.
pub fn read_dt1_line(dt1: &Path) -> Result<Dt1Line> {
    let (hd_path, hd) = read_hd_beside(dt1)?;
    let bytes = std::fs::read(dt1).map_err(io_error(dt1))?;
    parse_dt1(hd, &hd_path, &bytes, dt1)
}

/// An I/O error on `path`.
fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.to_owned();
    move |source| Error::Io { path, source }
}

/// The `.HD` beside `dt1`, read: where it is and what it says.
fn read_hd_beside(dt1: &Path) -> Result<(PathBuf, HdHeader)> {
    let hd_path = find_hd(dt1)?;
    let hd_bytes = std::fs::read(&hd_path).map_err(io_error(&hd_path))?;
    let hd = parse_hd(&String::from_utf8_lossy(&hd_bytes), &hd_path)?;
    Ok((hd_path, hd))
}

/// The `.HD` next to `dt1`: same stem, extension `hd` in any case.
pub fn find_hd(dt1: &Path) -> Result<PathBuf> {
    let missing = || Error::Missing {
        path: dt1.with_extension("HD"),
        why: "a DT1 needs the HD header beside it",
    };
    let stem = dt1.file_stem().ok_or_else(missing)?;
    let dir = match dt1.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    for ext in ["HD", "hd"] {
        let candidate = dt1.with_extension(ext);
        if candidate.is_file() {
            return Ok(candidate);
        }
    }
    let entries = std::fs::read_dir(dir).map_err(|source| Error::Io {
        path: dir.to_owned(),
        source,
    })?;
    entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| {
            p.file_stem() == Some(stem) && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("hd")) && p.is_file()
        })
        .ok_or_else(missing)
}

/// Parses the text of an HD file; `path` only names it in errors. Keys match in any case.
/// `NUMBER OF TRACES`, `NUMBER OF PTS/TRC` and `TOTAL TIME WINDOW` are required; a documented
/// key whose value is not a number is an error naming the line.
pub fn parse_hd(text: &str, path: &Path) -> Result<HdHeader> {
    let mut hd = HdHeader::default();
    let mut traces = None;
    let mut points = None;
    let mut window = None;
    for (index, raw) in text.lines().enumerate() {
        let line = index + 1;
        let trimmed = raw.trim_matches(|c: char| c.is_whitespace() || c == '\0');
        let Some((key, value)) = trimmed.split_once('=') else {
            if !trimmed.is_empty() {
                hd.text_lines.push(trimmed.to_owned());
            }
            continue;
        };
        let key = key.trim();
        let value = value.trim();
        let bad = |why: &str| Error::BadField {
            file: path.to_owned(),
            record: Record::Line(line),
            field: key.to_owned(),
            value: value.to_owned(),
            why: why.to_owned(),
        };
        let real = || {
            value
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| bad("not a finite number"))
        };
        let count = || {
            let v = real()?;
            if v >= 0.0 && v.fract() == 0.0 && v <= u32::MAX as f64 {
                Ok(v as usize)
            } else {
                Err(bad("not a whole number >= 0"))
            }
        };
        match key.to_ascii_uppercase().as_str() {
            "NUMBER OF TRACES" => traces = Some(count()?),
            "NUMBER OF PTS/TRC" => points = Some(count()?),
            "TIMEZERO AT POINT" => hd.timezero_at_point = Some(real()?),
            "TOTAL TIME WINDOW" => window = Some(real()?),
            "STARTING POSITION" => hd.starting_position = Some(real()?),
            "FINAL POSITION" => hd.final_position = Some(real()?),
            "STEP SIZE USED" => hd.step_size = Some(real()?),
            "POSITION UNITS" => hd.position_units = Some(value.to_owned()),
            "NOMINAL FREQUENCY" => hd.nominal_frequency_mhz = Some(real()?),
            "ANTENNA SEPARATION" => hd.antenna_separation = Some(real()?),
            "PULSER VOLTAGE (V)" => hd.pulser_voltage_v = Some(real()?),
            "NUMBER OF STACKS" => hd.number_of_stacks = Some(count()? as u32),
            "SURVEY MODE" => hd.survey_mode = Some(value.to_owned()),
            _ => {
                hd.other.insert(key.to_owned(), value.to_owned());
            }
        }
    }
    let missing = |field: &str| Error::MissingField {
        file: path.to_owned(),
        field: field.to_owned(),
    };
    hd.number_of_traces = traces.ok_or_else(|| missing("NUMBER OF TRACES"))?;
    hd.points_per_trace = points.ok_or_else(|| missing("NUMBER OF PTS/TRC"))?;
    hd.total_time_window_ns = window.ok_or_else(|| missing("TOTAL TIME WINDOW"))?;
    let header_field = |field: &str, value: String, why: &str| Error::BadField {
        file: path.to_owned(),
        record: Record::Header,
        field: field.to_owned(),
        value,
        why: why.to_owned(),
    };
    if hd.points_per_trace == 0 {
        return Err(header_field("NUMBER OF PTS/TRC", "0".into(), "no samples per trace"));
    }
    if hd.total_time_window_ns <= 0.0 {
        let window = hd.total_time_window_ns.to_string();
        return Err(header_field("TOTAL TIME WINDOW", window, "not a positive time (ns)"));
    }
    if hd.metres_per_unit().is_none() {
        let unit = hd.position_units.clone().unwrap_or_default();
        return Err(header_field("POSITION UNITS", unit, "not a known length unit"));
    }
    Ok(hd)
}

/// Parses the bytes of a DT1 file against its HD; the paths only name the files in errors and
/// in the result.
pub fn parse_dt1(hd: HdHeader, hd_path: &Path, bytes: &[u8], dt1_path: &Path) -> Result<Dt1Line> {
    let checked = check_records(&hd, dt1_path, bytes.len(), |at| {
        bytes.get(at..).and_then(Dt1TraceHeader::parse)
    })?;
    let mut trace_headers = Vec::with_capacity(checked.complete);
    let mut traces = Vec::with_capacity(checked.complete);
    for i in 0..checked.complete {
        let record = bytes
            .get(i * checked.record_bytes..(i + 1) * checked.record_bytes)
            .unwrap_or_default();
        let Some(header) = Dt1TraceHeader::parse(record) else {
            break;
        };
        traces.push(checked.trace(&header, &record[DT1_TRACE_HEADER_BYTES..]));
        trace_headers.push(header);
    }
    let mut radargram = checked.radargram(&hd, dt1_path);
    radargram.traces = traces;
    Ok(Dt1Line {
        hd_path: hd_path.to_owned(),
        hd,
        trace_headers,
        radargram,
    })
}

/// What the check of every trace header found: the layout of the complete traces.
#[derive(Debug, Clone)]
struct Checked {
    complete: usize,
    record_bytes: usize,
    width: usize,
    clock_filled: bool,
    metres_per_unit: f64,
    dropped: Vec<Dropped>,
}

impl Checked {
    fn trace(&self, h: &Dt1TraceHeader, data: &[u8]) -> RawTrace {
        RawTrace {
            channel: 0,
            stamp_ns: (self.clock_filled && h.time_of_day_s.is_finite())
                .then(|| (f64::from(h.time_of_day_s) * 1e9).round() as i64),
            distance_m: f64::from(h.position) * self.metres_per_unit,
            samples: signed_le_samples(data, self.width),
        }
    }

    /// The line's description, without its traces.
    fn radargram(&self, hd: &HdHeader, dt1_path: &Path) -> Radargram {
        let interval_ns = hd.sample_interval_ns();
        Radargram {
            source: dt1_path.to_owned(),
            format: Format::Dt1,
            channels: 1,
            samples_per_trace: hd.points_per_trace,
            sample_interval_ns: interval_ns,
            time_zero_ns: hd.timezero_at_point.map_or(0.0, |point| -(point - 1.0) * interval_ns),
            center_frequency_hz: hd.nominal_frequency_mhz.map_or(f64::NAN, |mhz| mhz * 1e6),
            traces: Vec::new(),
            dropped: self.dropped.clone(),
        }
    }
}

/// Checks every trace header of a `len`-byte DT1 file (`header_at(offset)`: the header at
/// that offset, `None` when fewer than 128 bytes are left) against the HD and each other.
fn check_records(
    hd: &HdHeader,
    dt1_path: &Path,
    len: usize,
    mut header_at: impl FnMut(usize) -> Option<Dt1TraceHeader>,
) -> Result<Checked> {
    let file = || dt1_path.to_owned();
    let disagree = |record, field, found: String, other: String| Error::Disagree {
        file: file(),
        record,
        field,
        found,
        other,
    };
    let points = hd.points_per_trace;
    let mut checked = Checked {
        complete: 0,
        record_bytes: 0,
        width: 2,
        clock_filled: false,
        metres_per_unit: hd.metres_per_unit().unwrap_or(1.0),
        dropped: Vec::new(),
    };
    let mut record_bytes = None;
    let mut at = 0;
    while at < len {
        let index = checked.complete;
        let rest = len - at;
        let Some(header) = header_at(at) else {
            let want = record_bytes.unwrap_or(DT1_TRACE_HEADER_BYTES);
            checked.dropped.push(truncated(dt1_path, index, rest, want));
            break;
        };
        let width = match header.bytes_per_sample {
            2.0 => 2,
            4.0 => 4,
            other => {
                return Err(Error::BadField {
                    file: file(),
                    record: Record::Trace(index),
                    field: "bytes/sample".into(),
                    value: other.to_string(),
                    why: "not 2 or 4".into(),
                });
            }
        };
        if header.samples != points as f32 {
            let found = format!("header says {} samples", header.samples);
            let hd_says = format!("HD says {points}");
            return Err(disagree(Record::Trace(index), "samples", found, hd_says));
        }
        let this_record = points.saturating_mul(width).saturating_add(DT1_TRACE_HEADER_BYTES);
        match record_bytes {
            None => {
                record_bytes = Some(this_record);
                checked.width = width;
            }
            Some(first) if first != this_record => {
                let found = format!("header says {width} bytes/sample");
                let first = format!("trace 0 says {}", (first - DT1_TRACE_HEADER_BYTES) / points);
                return Err(disagree(Record::Trace(index), "bytes/sample", found, first));
            }
            Some(_) => {}
        }
        if rest < this_record {
            checked.dropped.push(truncated(dt1_path, index, rest, this_record));
            break;
        }
        checked.clock_filled |= header.time_of_day_s != 0.0;
        checked.complete += 1;
        at += this_record;
    }
    checked.record_bytes = record_bytes.unwrap_or(DT1_TRACE_HEADER_BYTES);
    let complete = checked.complete;
    let cut_short = !checked.dropped.is_empty() && complete < hd.number_of_traces;
    if complete != hd.number_of_traces && !cut_short {
        let found = format!("file holds {complete} complete traces");
        let hd_says = format!("HD says {}", hd.number_of_traces);
        return Err(disagree(Record::File, "traces", found, hd_says));
    }
    Ok(checked)
}

/// A DT1 line read trace by trace from disk: memory does not grow with its length. Opening
/// reads every trace header once (the checks of [`read_dt1`], and whether the clock is
/// filled); the stream then yields the traces [`read_dt1`] would return, in the same order.
#[derive(Debug)]
pub struct Dt1Stream {
    checked: Checked,
    reader: std::io::BufReader<std::fs::File>,
    buffer: Vec<u8>,
    next: usize,
    path: PathBuf,
    /// Records skipped (a cut-short last trace; a read error).
    pub dropped: Vec<Dropped>,
}

impl Dt1Stream {
    /// Opens `dt1` and the `.HD` beside it and checks every trace header; returns the HD,
    /// the line's description (its `traces` empty: they come from the stream) and the stream.
    ///
    /// # Errors
    /// As [`read_dt1`].
    pub fn open(dt1: &Path) -> Result<(HdHeader, Radargram, Self)> {
        use std::io::{Read, Seek, SeekFrom};
        let (_, hd) = read_hd_beside(dt1)?;
        let io = io_error;
        let file = std::fs::File::open(dt1).map_err(io(dt1))?;
        let len = usize::try_from(file.metadata().map_err(io(dt1))?.len()).unwrap_or(usize::MAX);
        let mut reader = std::io::BufReader::with_capacity(1 << 16, file);
        let mut head = [0_u8; DT1_TRACE_HEADER_BYTES];
        let mut failed = None;
        let checked = check_records(&hd, dt1, len, |at| {
            if len - at < DT1_TRACE_HEADER_BYTES || failed.is_some() {
                return None;
            }
            let read = reader
                .seek(SeekFrom::Start(at as u64))
                .and_then(|_| reader.read_exact(&mut head));
            match read {
                Ok(()) => Dt1TraceHeader::parse(&head),
                Err(e) => {
                    failed = Some(e);
                    None
                }
            }
        })?;
        if let Some(e) = failed {
            return Err(io(dt1)(e));
        }
        reader.seek(SeekFrom::Start(0)).map_err(io(dt1))?;
        let radargram = checked.radargram(&hd, dt1);
        Ok((
            hd,
            radargram,
            Self {
                dropped: checked.dropped.clone(),
                buffer: vec![0; checked.record_bytes],
                checked,
                reader,
                next: 0,
                path: dt1.to_owned(),
            },
        ))
    }

    /// Complete traces in the line.
    pub fn traces(&self) -> usize {
        self.checked.complete
    }
}

impl Iterator for Dt1Stream {
    type Item = RawTrace;

    fn next(&mut self) -> Option<RawTrace> {
        use std::io::Read;
        if self.next >= self.checked.complete {
            return None;
        }
        if let Err(e) = self.reader.read_exact(&mut self.buffer) {
            tracing::warn!(
                "{}: read error at trace {}: {e}; the traces before it are kept",
                self.path.display(),
                self.next
            );
            self.dropped
                .push(truncated(&self.path, self.next, 0, self.checked.record_bytes));
            self.next = self.checked.complete;
            return None;
        }
        self.next += 1;
        let header = Dt1TraceHeader::parse(&self.buffer)?;
        Some(self.checked.trace(&header, &self.buffer[DT1_TRACE_HEADER_BYTES..]))
    }
}

fn truncated(file: &Path, index: usize, got: usize, want: usize) -> Dropped {
    Dropped {
        file: file.to_owned(),
        record: Record::Trace(index),
        reason: DropReason::Truncated { got, want },
    }
}
