//! CMU-GPR sequence folders: `gpr_meas.csv`, `we_odom_meas.csv`, and where present
//! `imu_meas.csv` and `ts_meas.csv` (the `camera/` images are not read).
//!
//! Each file is comma-separated text with one header row; the first column `t` is the stamp in
//! seconds. Our simulator writes `t` with exactly nine decimals (`1600000000.020000000`); the
//! reader takes decimal stamps to the nanosecond without going through `f64` (and accepts
//! exponent forms through `f64`). Cells may carry blanks around them, lines may end in CRLF,
//! blank lines are skipped. A first row whose first cell is a number is read as data: the file
//! then has no header row and columns are named `column N`.
//!
//! What the reader refuses ([`Error`]): a missing `gpr_meas.csv` or `we_odom_meas.csv`, a cell
//! that is not a number, an amplitude that is not a whole int16 count, a row with a different
//! number of cells than the header row. What it skips and counts ([`Dropped`], naming the file
//! and line): a row holding NaN or infinity, a row whose stamp is not after the previous kept
//! row's (repeated or going backwards), and a last line without a line end whose cell count is
//! wrong (the writer was stopped mid-line).
//!
//! Files are read line by line: [`read_cmu_sequence`] keeps every row, [`CmuStream`] one row
//! per file at a time (the rows of all files merged by stamp), after a first pass that checks
//! every line so that it refuses what [`read_cmu_sequence`] refuses before giving a row.
//!
//! GPR traces: `stamp_ns` from `t`; `distance_m` NaN (the wheel is a separate file: matching
//! it to the traces is a later stage's job); sample interval [`CMU_SAMPLE_INTERVAL_NS`] (5 GHz
//! sampling); time zero 0 and centre frequency NaN (the files do not say).

use std::fs::File;
use std::io::{BufRead, BufReader, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::error::{DropReason, Dropped, Error, Record, Result};
use crate::radargram::{Format, Radargram, RawSamples, RawTrace};

/// Sample interval of the CMU-GPR radar (ns): 5 GHz sampling.
pub const CMU_SAMPLE_INTERVAL_NS: f64 = 0.2;
/// The radar traces: `t, amp_1 .. amp_N` (raw int16 counts).
pub const GPR_FILE: &str = "gpr_meas.csv";
/// The IMU: `t, ax, ay, az, gx, gy, gz, qw, qx, qy, qz`.
pub const IMU_FILE: &str = "imu_meas.csv";
/// The wheel encoder: `t, signed distance (m)`.
pub const WHEEL_FILE: &str = "we_odom_meas.csv";
/// The total station: `t, px, py, pz`.
pub const TRUTH_FILE: &str = "ts_meas.csv";

/// One IMU sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuRow {
    /// Stamp (ns) on the sequence's clock.
    pub stamp_ns: i64,
    /// Specific force along body x, y, z (m/s^2).
    pub accel_mps2: [f64; 3],
    /// Angular rate about body x, y, z (rad/s).
    pub gyro_radps: [f64; 3],
    /// Orientation as a quaternion `[w, x, y, z]` (as written; not renormalised).
    pub orientation_wxyz: [f64; 4],
}

/// One wheel-encoder reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelRow {
    /// Stamp (ns) on the sequence's clock.
    pub stamp_ns: i64,
    /// Signed distance travelled since the start (m).
    pub distance_m: f64,
}

/// One total-station (ground truth) position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthRow {
    /// Stamp (ns) on the sequence's clock.
    pub stamp_ns: i64,
    /// Prism position x, y, z in the total station's frame (m).
    pub position_m: [f64; 3],
}

/// A CMU-GPR sequence folder as read.
#[derive(Debug, Clone, PartialEq)]
pub struct CmuSequence {
    /// The folder.
    pub dir: PathBuf,
    /// The radar traces of `gpr_meas.csv`; its skipped rows are in `gpr.dropped`.
    pub gpr: Radargram,
    /// `imu_meas.csv`; `None` when the file is absent.
    pub imu: Option<Vec<ImuRow>>,
    /// `we_odom_meas.csv`.
    pub wheel: Vec<WheelRow>,
    /// `ts_meas.csv`; `None` when the file is absent.
    pub truth: Option<Vec<TruthRow>>,
    /// Rows skipped in the IMU, wheel and total-station files (those of `gpr_meas.csv` are in
    /// `gpr.dropped`).
    pub dropped: Vec<Dropped>,
}

impl CmuSequence {
    /// Every skipped row of every file.
    pub fn all_dropped(&self) -> impl Iterator<Item = &Dropped> {
        self.gpr.dropped.iter().chain(&self.dropped)
    }

    /// Rows kept in each file.
    pub fn counts(&self) -> CmuCounts {
        CmuCounts {
            gpr: self.gpr.traces.len(),
            wheel: self.wheel.len(),
            imu: self.imu.as_ref().map(Vec::len),
            truth: self.truth.as_ref().map(Vec::len),
        }
    }
}

/// Reads a sequence folder; see the module docs for what is refused and what is skipped. The
/// files are read line by line (the result holds every row, the reading no more than one line).
pub fn read_cmu_sequence(dir: &Path) -> Result<CmuSequence> {
    let gpr_path = dir.join(GPR_FILE);
    let gpr = read_gpr(open_required(&gpr_path, NEEDS_GPR)?, &gpr_path)?;
    let wheel_path = dir.join(WHEEL_FILE);
    let (wheel, mut dropped) = collect_rows(wheel_rows(open_required(&wheel_path, NEEDS_WHEEL)?, &wheel_path)?)?;
    let imu = read_optional(&dir.join(IMU_FILE), imu_rows, &mut dropped)?;
    let truth = read_optional(&dir.join(TRUTH_FILE), truth_rows, &mut dropped)?;
    Ok(CmuSequence {
        dir: dir.to_owned(),
        gpr,
        imu,
        wheel,
        truth,
        dropped,
    })
}

/// Every kept row of an optional file (`None` when it is absent); its skipped rows are added
/// to `dropped`.
fn read_optional<V, T>(path: &Path, open: OpenRows<V, T>, dropped: &mut Vec<Dropped>) -> Result<Option<Vec<T>>> {
    let Some(file) = open_optional(path)? else {
        return Ok(None);
    };
    let (rows, d) = collect_rows(open(file, path)?)?;
    dropped.extend(d);
    Ok(Some(rows))
}

const NEEDS_GPR: &str = "a CMU-GPR sequence needs its radar traces";
const NEEDS_WHEEL: &str = "a CMU-GPR sequence needs its wheel odometry";

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_owned(),
        source,
    }
}

fn open_optional(path: &Path) -> Result<Option<BufReader<File>>> {
    match File::open(path) {
        Ok(file) => Ok(Some(BufReader::with_capacity(1 << 16, file))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(io_error(path)(source)),
    }
}

fn open_required(path: &Path, why: &'static str) -> Result<BufReader<File>> {
    open_optional(path)?.ok_or_else(|| Error::Missing {
        path: path.to_owned(),
        why,
    })
}

/// Parses the text of a `gpr_meas.csv`; `path` names the file in errors and in the result.
/// The number of samples per trace is the header row's column count less one.
pub fn parse_gpr_csv(text: &str, path: &Path) -> Result<Radargram> {
    read_gpr(text.as_bytes(), path)
}

/// Parses the text of an `imu_meas.csv` (11 columns).
pub fn parse_imu_csv(text: &str, path: &Path) -> Result<(Vec<ImuRow>, Vec<Dropped>)> {
    collect_rows(imu_rows(text.as_bytes(), path)?)
}

/// Parses the text of a `we_odom_meas.csv` (2 columns).
pub fn parse_wheel_csv(text: &str, path: &Path) -> Result<(Vec<WheelRow>, Vec<Dropped>)> {
    collect_rows(wheel_rows(text.as_bytes(), path)?)
}

/// Parses the text of a `ts_meas.csv` (4 columns).
pub fn parse_truth_csv(text: &str, path: &Path) -> Result<(Vec<TruthRow>, Vec<Dropped>)> {
    collect_rows(truth_rows(text.as_bytes(), path)?)
}

fn read_gpr<R: BufRead>(reader: R, path: &Path) -> Result<Radargram> {
    let rows = gpr_rows(reader, path)?;
    let samples_per_trace = rows.columns() - 1;
    let (traces, dropped) = collect_rows(rows)?;
    Ok(gpr_radargram(path, samples_per_trace, traces, dropped))
}

/// The description of a `gpr_meas.csv`'s line, holding `traces`.
fn gpr_radargram(path: &Path, samples_per_trace: usize, traces: Vec<RawTrace>, dropped: Vec<Dropped>) -> Radargram {
    Radargram {
        source: path.to_owned(),
        format: Format::CmuGpr,
        channels: 1,
        samples_per_trace,
        sample_interval_ns: CMU_SAMPLE_INTERVAL_NS,
        time_zero_ns: 0.0,
        center_frequency_hz: f64::NAN,
        traces,
        dropped,
    }
}

/// The rows of a `gpr_meas.csv` (`t` and at least one amplitude column).
fn gpr_rows<R: BufRead>(reader: R, path: &Path) -> Result<CsvRows<R, i16, RawTrace>> {
    let rows = CsvRows::open(reader, path, None, parse_count, |stamp_ns, samples| RawTrace {
        channel: 0,
        stamp_ns: Some(stamp_ns),
        distance_m: f64::NAN,
        samples: RawSamples::I16(samples),
    })?;
    if rows.columns() == 1 {
        return Err(Error::BadField {
            file: path.to_owned(),
            record: Record::Line(rows.first_line),
            field: "columns".into(),
            value: "1".into(),
            why: "no amplitude columns after t".into(),
        });
    }
    Ok(rows)
}

/// The rows of an `imu_meas.csv`.
fn imu_rows<R: BufRead>(reader: R, path: &Path) -> Result<CsvRows<R, f64, ImuRow>> {
    CsvRows::open(reader, path, Some(11), parse_real, |stamp_ns, v| ImuRow {
        stamp_ns,
        accel_mps2: [v[0], v[1], v[2]],
        gyro_radps: [v[3], v[4], v[5]],
        orientation_wxyz: [v[6], v[7], v[8], v[9]],
    })
}

/// The rows of a `we_odom_meas.csv`.
fn wheel_rows<R: BufRead>(reader: R, path: &Path) -> Result<CsvRows<R, f64, WheelRow>> {
    CsvRows::open(reader, path, Some(2), parse_real, |stamp_ns, v| WheelRow {
        stamp_ns,
        distance_m: v[0],
    })
}

/// The rows of a `ts_meas.csv`.
fn truth_rows<R: BufRead>(reader: R, path: &Path) -> Result<CsvRows<R, f64, TruthRow>> {
    CsvRows::open(reader, path, Some(4), parse_real, |stamp_ns, v| TruthRow {
        stamp_ns,
        position_m: [v[0], v[1], v[2]],
    })
}

/// Every kept row of a file, and its skipped ones.
fn collect_rows<R: BufRead, V, T>(mut rows: CsvRows<R, V, T>) -> Result<(Vec<T>, Vec<Dropped>)> {
    let mut kept = Vec::new();
    while let Some((_, row)) = rows.next_row()? {
        kept.push(row);
    }
    Ok((kept, rows.dropped))
}

/// One row of a sequence folder, from whichever file.
#[derive(Debug, Clone, PartialEq)]
pub enum CmuRow {
    /// A trace of `gpr_meas.csv`.
    Gpr(RawTrace),
    /// A row of `we_odom_meas.csv`.
    Wheel(WheelRow),
    /// A row of `imu_meas.csv`.
    Imu(ImuRow),
    /// A row of `ts_meas.csv`.
    Truth(TruthRow),
}

impl From<RawTrace> for CmuRow {
    fn from(t: RawTrace) -> Self {
        Self::Gpr(t)
    }
}

impl From<WheelRow> for CmuRow {
    fn from(w: WheelRow) -> Self {
        Self::Wheel(w)
    }
}

impl From<ImuRow> for CmuRow {
    fn from(s: ImuRow) -> Self {
        Self::Imu(s)
    }
}

impl From<TruthRow> for CmuRow {
    fn from(p: TruthRow) -> Self {
        Self::Truth(p)
    }
}

/// Rows kept in each file of a sequence folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CmuCounts {
    /// Traces of `gpr_meas.csv`.
    pub gpr: usize,
    /// Rows of `we_odom_meas.csv`.
    pub wheel: usize,
    /// Rows of `imu_meas.csv`; `None` when the file is absent.
    pub imu: Option<usize>,
    /// Rows of `ts_meas.csv`; `None` when the file is absent.
    pub truth: Option<usize>,
}

impl CmuCounts {
    /// Rows in all.
    pub fn rows(&self) -> usize {
        self.gpr + self.wheel + self.imu.unwrap_or(0) + self.truth.unwrap_or(0)
    }
}

/// A sequence folder read row by row, the rows of its files merged in stamp order: what
/// [`read_cmu_sequence`] reads, one row at a time, so memory does not grow with the files.
/// Rows with equal stamps come in the order `gpr_meas.csv`, `we_odom_meas.csv`,
/// `imu_meas.csv`, `ts_meas.csv`. Each file is checked whole at [`CmuStream::open`], so what
/// [`read_cmu_sequence`] refuses is refused there, before the first row.
pub struct CmuStream {
    /// The files present, in the order above, each with its next row.
    files: Vec<MergedFile>,
    /// Rows skipped so far (taken by the caller as it goes).
    pub dropped: Vec<Dropped>,
}

impl std::fmt::Debug for CmuStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CmuStream")
            .field("files", &self.files.len())
            .field("dropped", &self.dropped)
            .finish_non_exhaustive()
    }
}

/// One file of a [`CmuStream`].
struct MergedFile {
    rows: Box<dyn RowSource>,
    next: Option<(i64, CmuRow)>,
    done: bool,
}

/// A file's rows as the merge takes them.
trait RowSource: Send {
    fn next_row(&mut self) -> Result<Option<(i64, CmuRow)>>;
    fn take_dropped(&mut self) -> Vec<Dropped>;
}

impl<R: BufRead + Send, V: Send, T: Into<CmuRow>> RowSource for CsvRows<R, V, T> {
    fn next_row(&mut self) -> Result<Option<(i64, CmuRow)>> {
        Ok(CsvRows::next_row(self)?.map(|(stamp_ns, row)| (stamp_ns, row.into())))
    }

    fn take_dropped(&mut self) -> Vec<Dropped> {
        std::mem::take(&mut self.dropped)
    }
}

type FileRows<V, T> = CsvRows<BufReader<File>, V, T>;

/// Reads a file's header row and gives its rows (`gpr_rows`, `imu_rows`, ...).
type OpenRows<V, T> = fn(BufReader<File>, &Path) -> Result<FileRows<V, T>>;

impl CmuStream {
    /// Opens the folder and checks every file whole, line by line, keeping nothing; returns
    /// the rows each file keeps, the description of `gpr_meas.csv`'s line (its `traces`
    /// empty: they come from the stream) and the stream.
    ///
    /// # Errors
    /// As [`read_cmu_sequence`].
    pub fn open(dir: &Path) -> Result<(CmuCounts, Radargram, Self)> {
        let gpr_path = dir.join(GPR_FILE);
        let (gpr, gpr_rows) = checked(open_required(&gpr_path, NEEDS_GPR)?, &gpr_path, gpr_rows)?;
        let samples_per_trace = gpr_rows.columns() - 1;
        let wheel_path = dir.join(WHEEL_FILE);
        let (wheel, wheel_rows) = checked(open_required(&wheel_path, NEEDS_WHEEL)?, &wheel_path, wheel_rows)?;
        let mut files = vec![MergedFile::new(gpr_rows), MergedFile::new(wheel_rows)];
        let imu = merge_optional(&dir.join(IMU_FILE), imu_rows, &mut files)?;
        let truth = merge_optional(&dir.join(TRUTH_FILE), truth_rows, &mut files)?;
        let counts = CmuCounts { gpr, wheel, imu, truth };
        let description = gpr_radargram(&gpr_path, samples_per_trace, Vec::new(), Vec::new());
        Ok((
            counts,
            description,
            Self {
                files,
                dropped: Vec::new(),
            },
        ))
    }
}

/// Checks an optional file whole ([`checked`]) and adds its rows to the merge; the rows it
/// keeps, `None` when it is absent.
fn merge_optional<V: Send + 'static, T: Into<CmuRow> + 'static>(
    path: &Path,
    open: OpenRows<V, T>,
    files: &mut Vec<MergedFile>,
) -> Result<Option<usize>> {
    let Some(file) = open_optional(path)? else {
        return Ok(None);
    };
    let (count, rows) = checked(file, path, open)?;
    files.push(MergedFile::new(rows));
    Ok(Some(count))
}

/// Reads the file at `reader` to its end through `open`'s rows, keeping nothing but the count
/// of kept rows, then opens it again from its start.
fn checked<V, T>(reader: BufReader<File>, path: &Path, open: OpenRows<V, T>) -> Result<(usize, FileRows<V, T>)> {
    let mut rows = open(reader, path)?;
    let mut kept = 0;
    while rows.next_row()?.is_some() {
        kept += 1;
    }
    let mut file = rows.lines.reader.into_inner();
    file.seek(SeekFrom::Start(0)).map_err(io_error(path))?;
    Ok((kept, open(BufReader::with_capacity(1 << 16, file), path)?))
}

impl MergedFile {
    fn new<V: Send + 'static, T: Into<CmuRow> + 'static>(rows: FileRows<V, T>) -> Self {
        Self {
            rows: Box::new(rows),
            next: None,
            done: false,
        }
    }
}

impl Iterator for CmuStream {
    type Item = CmuRow;

    fn next(&mut self) -> Option<CmuRow> {
        for f in &mut self.files {
            if f.next.is_none() && !f.done {
                match f.rows.next_row() {
                    Ok(Some(row)) => f.next = Some(row),
                    Ok(None) => f.done = true,
                    Err(e) => {
                        // checked at open: the file changed since
                        tracing::warn!("{e}; the rows before it are kept");
                        f.done = true;
                    }
                }
                self.dropped.append(&mut f.rows.take_dropped());
            }
        }
        // the smallest stamp; on equal stamps the first file (min_by_key keeps the first)
        let first = self
            .files
            .iter_mut()
            .filter(|f| f.next.is_some())
            .min_by_key(|f| f.next.as_ref().map(|(stamp_ns, _)| *stamp_ns))?;
        first.next.take().map(|(_, row)| row)
    }
}

/// How one cell reads.
enum Cell<V> {
    Value(V),
    NotFinite,
    NotANumber,
    OutOfRange(&'static str),
}

/// A stamp in seconds as ns: plain decimals exactly (rounded at the 10th decimal), other
/// forms (`1.6e9`) through `f64`.
fn parse_stamp_ns(text: &str) -> Cell<i64> {
    if let Some(ns) = decimal_seconds_ns(text) {
        return Cell::Value(ns);
    }
    match text.parse::<f64>() {
        Ok(s) if !s.is_finite() => Cell::NotFinite,
        // i64 ns span about +-292 years around 0.
        Ok(s) if (s * 1e9).abs() < 9.2e18 => Cell::Value((s * 1e9).round() as i64),
        Ok(_) => Cell::OutOfRange("a stamp beyond +-292 years (i64 ns)"),
        Err(_) => Cell::NotANumber,
    }
}

fn decimal_seconds_ns(text: &str) -> Option<i64> {
    let (negative, digits) = match text.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, text.strip_prefix('+').unwrap_or(text)),
    };
    let (whole, fraction) = digits.split_once('.').unwrap_or((digits, ""));
    let all_digits = |s: &str| s.bytes().all(|b| b.is_ascii_digit());
    if (whole.is_empty() && fraction.is_empty()) || !all_digits(whole) || !all_digits(fraction) {
        return None;
    }
    let whole_s: i64 = if whole.is_empty() { 0 } else { whole.parse().ok()? };
    let mut fraction_ns = 0_i64;
    let mut scale = 100_000_000_i64;
    for b in fraction.bytes().take(9) {
        fraction_ns += i64::from(b - b'0') * scale;
        scale /= 10;
    }
    if fraction.as_bytes().get(9).is_some_and(|&b| b >= b'5') {
        fraction_ns += 1;
    }
    let ns = whole_s.checked_mul(1_000_000_000)?.checked_add(fraction_ns)?;
    Some(if negative { -ns } else { ns })
}

const COUNT_RANGE: &str = "not a whole count in -32768..=32767";

/// An int16 count; `163.0` is accepted as 163.
fn parse_count(text: &str) -> Cell<i16> {
    if let Ok(v) = text.parse::<i16>() {
        return Cell::Value(v);
    }
    if text.parse::<i64>().is_ok() {
        return Cell::OutOfRange(COUNT_RANGE);
    }
    match text.parse::<f64>() {
        Ok(v) if !v.is_finite() => Cell::NotFinite,
        Ok(v) if v.fract() == 0.0 && (-32768.0..=32767.0).contains(&v) => Cell::Value(v as i16),
        Ok(_) => Cell::OutOfRange(COUNT_RANGE),
        Err(_) => Cell::NotANumber,
    }
}

fn parse_real(text: &str) -> Cell<f64> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Cell::Value(v),
        Ok(_) => Cell::NotFinite,
        Err(_) => Cell::NotANumber,
    }
}

/// The non-blank lines of a CSV file, read one at a time with the next one read ahead: a
/// wrong cell count is forgiven only on the last line of a file that does not end in a line end.
struct Lines<R> {
    reader: R,
    file: PathBuf,
    /// Lines read so far, blank ones included.
    read: usize,
    buffer: Vec<u8>,
    /// The next non-blank line: (line number, text without its line end).
    ahead: Option<(usize, String)>,
    /// Whether the last line read ended in `\n` (at the end: whether the file does).
    ends_with_newline: bool,
}

impl<R: BufRead> Lines<R> {
    fn new(reader: R, file: &Path) -> Result<Self> {
        let mut lines = Self {
            reader,
            file: file.to_owned(),
            read: 0,
            buffer: Vec::new(),
            ahead: None,
            ends_with_newline: false,
        };
        lines.ahead = lines.read_non_blank()?;
        Ok(lines)
    }

    fn read_non_blank(&mut self) -> Result<Option<(usize, String)>> {
        loop {
            self.buffer.clear();
            let n = self
                .reader
                .read_until(b'\n', &mut self.buffer)
                .map_err(io_error(&self.file))?;
            if n == 0 {
                return Ok(None);
            }
            self.read += 1;
            let bytes = match self.buffer.strip_suffix(b"\n") {
                Some(line) => {
                    self.ends_with_newline = true;
                    line
                }
                None => {
                    self.ends_with_newline = false;
                    &self.buffer[..]
                }
            };
            let text = String::from_utf8_lossy(bytes);
            let text = text.trim_end_matches('\r');
            if !text.trim().is_empty() {
                return Ok(Some((self.read, text.to_owned())));
            }
        }
    }

    /// The next non-blank line (number, text), and whether it is the cut-off last line of a
    /// file that does not end in a line end.
    fn next(&mut self) -> Result<Option<(usize, String, bool)>> {
        let Some((line, text)) = self.ahead.take() else {
            return Ok(None);
        };
        self.ahead = self.read_non_blank()?;
        let cut_off = self.ahead.is_none() && !self.ends_with_newline;
        Ok(Some((line, text, cut_off)))
    }
}

/// A CSV file with `t` first, read one row at a time: each kept row as `row(stamp_ns, values
/// after t)`; skipped rows counted in `dropped`.
struct CsvRows<R, V, T> {
    lines: Lines<R>,
    /// Column names (from the header row, else `column N`); their count is the row's.
    names: Vec<String>,
    /// The line of the header row (or of the first data row when there is none).
    first_line: usize,
    parse_value: fn(&str) -> Cell<V>,
    row: fn(i64, Vec<V>) -> T,
    previous_ns: Option<i64>,
    dropped: Vec<Dropped>,
}

/// How a row of cells reads, when it is not refused.
enum Parsed<V> {
    Kept(i64, Vec<V>),
    Skipped(DropReason),
}

impl<R: BufRead, V, T> CsvRows<R, V, T> {
    /// Reads the header row; `columns` cells per row (from the header row when `None`).
    fn open(
        reader: R,
        file: &Path,
        columns: Option<usize>,
        parse_value: fn(&str) -> Cell<V>,
        row: fn(i64, Vec<V>) -> T,
    ) -> Result<Self> {
        let mut lines = Lines::new(reader, file)?;
        let Some((first_line, first)) = lines.ahead.clone() else {
            return Err(Error::Empty { file: file.to_owned() });
        };
        let first_cells: Vec<&str> = first.split(',').map(str::trim).collect();
        let first_cell = first_cells.first().copied().unwrap_or_default();
        let has_header = matches!(parse_stamp_ns(first_cell), Cell::NotANumber);
        let want = columns.unwrap_or(first_cells.len());
        let names: Vec<String> = if has_header {
            lines.next()?;
            first_cells.iter().map(|s| (*s).to_owned()).collect()
        } else {
            (1..=want).map(|c| format!("column {c}")).collect()
        };
        if names.len() != want {
            return Err(Error::ColumnCount {
                file: file.to_owned(),
                line: first_line,
                got: names.len(),
                want,
            });
        }
        Ok(Self {
            lines,
            names,
            first_line,
            parse_value,
            row,
            previous_ns: None,
            dropped: Vec::new(),
        })
    }

    /// Cells per row, `t` included.
    fn columns(&self) -> usize {
        self.names.len()
    }

    /// The next kept row and its stamp; `None` at the end of the file.
    fn next_row(&mut self) -> Result<Option<(i64, T)>> {
        while let Some((line, text, cut_off)) = self.lines.next()? {
            let drop = |reason| Dropped {
                file: self.lines.file.clone(),
                record: Record::Line(line),
                reason,
            };
            let (got, want) = (text.split(',').count(), self.columns());
            if got != want {
                if cut_off {
                    self.dropped.push(drop(DropReason::TruncatedLine { got, want }));
                    continue;
                }
                return Err(Error::ColumnCount {
                    file: self.lines.file.clone(),
                    line,
                    got,
                    want,
                });
            }
            let (stamp_ns, values) = match self.parse_cells(line, &text)? {
                Parsed::Kept(stamp_ns, values) => (stamp_ns, values),
                Parsed::Skipped(reason) => {
                    self.dropped.push(drop(reason));
                    continue;
                }
            };
            if let Some(previous_ns) = self.previous_ns.filter(|&p| stamp_ns <= p) {
                self.dropped
                    .push(drop(DropReason::StampNotIncreasing { stamp_ns, previous_ns }));
                continue;
            }
            self.previous_ns = Some(stamp_ns);
            return Ok(Some((stamp_ns, (self.row)(stamp_ns, values))));
        }
        Ok(None)
    }

    /// The cells of data line `line`: refused when one is not a number of its column's kind,
    /// skipped when one is not finite.
    fn parse_cells(&self, line: usize, text: &str) -> Result<Parsed<V>> {
        let file = &self.lines.file;
        let mut not_finite = None;
        let mut values = Vec::with_capacity(self.columns().saturating_sub(1));
        let mut stamp_ns = 0;
        for (index, cell) in text.split(',').map(str::trim).enumerate() {
            let column = index + 1;
            let name = || self.names.get(index).cloned().unwrap_or_default();
            let refuse_not_a_number = || Error::NotANumber {
                file: file.clone(),
                line,
                column,
                name: name(),
                text: cell.to_owned(),
            };
            let refuse_range = |why| Error::OutOfRange {
                file: file.clone(),
                line,
                column,
                name: name(),
                text: cell.to_owned(),
                why,
            };
            if index == 0 {
                match parse_stamp_ns(cell) {
                    Cell::Value(ns) => stamp_ns = ns,
                    Cell::NotFinite => not_finite = not_finite.or(Some((column, name()))),
                    Cell::NotANumber => return Err(refuse_not_a_number()),
                    Cell::OutOfRange(why) => return Err(refuse_range(why)),
                }
                continue;
            }
            match (self.parse_value)(cell) {
                Cell::Value(v) => values.push(v),
                Cell::NotFinite => not_finite = not_finite.or(Some((column, name()))),
                Cell::NotANumber => return Err(refuse_not_a_number()),
                Cell::OutOfRange(why) => return Err(refuse_range(why)),
            }
        }
        Ok(match not_finite {
            Some((column, name)) => Parsed::Skipped(DropReason::NotFinite { column, name }),
            None => Parsed::Kept(stamp_ns, values),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stamp(text: &str) -> Option<i64> {
        match parse_stamp_ns(text) {
            Cell::Value(ns) => Some(ns),
            _ => None,
        }
    }

    #[test]
    fn decimal_stamps_are_exact_to_the_nanosecond() {
        assert_eq!(stamp("1600000000.020000001"), Some(1_600_000_000_020_000_001));
        assert_eq!(stamp("1600000000.0200000015"), Some(1_600_000_000_020_000_002));
        assert_eq!(stamp("-1.5"), Some(-1_500_000_000));
        assert_eq!(stamp(".25"), Some(250_000_000));
        assert_eq!(stamp("3"), Some(3_000_000_000));
        assert_eq!(stamp("1.6e9"), Some(1_600_000_000_000_000_000));
        assert_eq!(stamp("."), None);
        assert_eq!(stamp("t"), None);
        assert_eq!(stamp("1e300"), None);
        assert!(matches!(parse_stamp_ns("nan"), Cell::NotFinite));
    }

    #[test]
    fn counts_are_whole_int16_values() {
        assert!(matches!(parse_count("-32768"), Cell::Value(-32768)));
        assert!(matches!(parse_count("163.0"), Cell::Value(163)));
        assert!(matches!(parse_count("32768"), Cell::OutOfRange(_)));
        assert!(matches!(parse_count("1.5"), Cell::OutOfRange(_)));
        assert!(matches!(parse_count("inf"), Cell::NotFinite));
        assert!(matches!(parse_count("x1"), Cell::NotANumber));
    }
}
