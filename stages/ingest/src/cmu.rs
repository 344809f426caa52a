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
//! GPR traces: `stamp_ns` from `t`; `distance_m` NaN (the wheel is a separate file: matching
//! it to the traces is a later stage's job); sample interval [`CMU_SAMPLE_INTERVAL_NS`] (5 GHz
//! sampling); time zero 0 and centre frequency NaN (the files do not say).

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
}

/// Reads a sequence folder; see the module docs for what is refused and what is skipped.
pub fn read_cmu_sequence(dir: &Path) -> Result<CmuSequence> {
    let gpr_path = dir.join(GPR_FILE);
    let gpr = parse_gpr_csv(
        &read_required(&gpr_path, "a CMU-GPR sequence needs its radar traces")?,
        &gpr_path,
    )?;
    let wheel_path = dir.join(WHEEL_FILE);
    let wheel_text = read_required(&wheel_path, "a CMU-GPR sequence needs its wheel odometry")?;
    let (wheel, mut dropped) = parse_wheel_csv(&wheel_text, &wheel_path)?;
    let imu_path = dir.join(IMU_FILE);
    let imu = match read_optional(&imu_path)? {
        Some(text) => {
            let (rows, d) = parse_imu_csv(&text, &imu_path)?;
            dropped.extend(d);
            Some(rows)
        }
        None => None,
    };
    let truth_path = dir.join(TRUTH_FILE);
    let truth = match read_optional(&truth_path)? {
        Some(text) => {
            let (rows, d) = parse_truth_csv(&text, &truth_path)?;
            dropped.extend(d);
            Some(rows)
        }
        None => None,
    };
    Ok(CmuSequence {
        dir: dir.to_owned(),
        gpr,
        imu,
        wheel,
        truth,
        dropped,
    })
}

fn read_optional(path: &Path) -> Result<Option<String>> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(Some(String::from_utf8_lossy(&bytes).into_owned())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(Error::Io {
            path: path.to_owned(),
            source,
        }),
    }
}

fn read_required(path: &Path, why: &'static str) -> Result<String> {
    read_optional(path)?.ok_or_else(|| Error::Missing {
        path: path.to_owned(),
        why,
    })
}

/// Parses the text of a `gpr_meas.csv`; `path` names the file in errors and in the result.
/// The number of samples per trace is the header row's column count less one.
pub fn parse_gpr_csv(text: &str, path: &Path) -> Result<Radargram> {
    let table = parse_table(text, path, None, parse_count)?;
    let samples_per_trace = table.columns - 1;
    if samples_per_trace == 0 {
        return Err(Error::BadField {
            file: path.to_owned(),
            record: Record::Line(table.first_line),
            field: "columns".into(),
            value: "1".into(),
            why: "no amplitude columns after t".into(),
        });
    }
    let traces = table
        .rows
        .into_iter()
        .map(|(stamp_ns, samples)| RawTrace {
            channel: 0,
            stamp_ns: Some(stamp_ns),
            distance_m: f64::NAN,
            samples: RawSamples::I16(samples),
        })
        .collect();
    Ok(Radargram {
        source: path.to_owned(),
        format: Format::CmuGpr,
        channels: 1,
        samples_per_trace,
        sample_interval_ns: CMU_SAMPLE_INTERVAL_NS,
        time_zero_ns: 0.0,
        center_frequency_hz: f64::NAN,
        traces,
        dropped: table.dropped,
    })
}

/// Parses the text of an `imu_meas.csv` (11 columns).
pub fn parse_imu_csv(text: &str, path: &Path) -> Result<(Vec<ImuRow>, Vec<Dropped>)> {
    let table = parse_table(text, path, Some(11), parse_real)?;
    let rows = table
        .rows
        .into_iter()
        .map(|(stamp_ns, v)| ImuRow {
            stamp_ns,
            accel_mps2: [v[0], v[1], v[2]],
            gyro_radps: [v[3], v[4], v[5]],
            orientation_wxyz: [v[6], v[7], v[8], v[9]],
        })
        .collect();
    Ok((rows, table.dropped))
}

/// Parses the text of a `we_odom_meas.csv` (2 columns).
pub fn parse_wheel_csv(text: &str, path: &Path) -> Result<(Vec<WheelRow>, Vec<Dropped>)> {
    let table = parse_table(text, path, Some(2), parse_real)?;
    let rows = table
        .rows
        .into_iter()
        .map(|(stamp_ns, v)| WheelRow {
            stamp_ns,
            distance_m: v[0],
        })
        .collect();
    Ok((rows, table.dropped))
}

/// Parses the text of a `ts_meas.csv` (4 columns).
pub fn parse_truth_csv(text: &str, path: &Path) -> Result<(Vec<TruthRow>, Vec<Dropped>)> {
    let table = parse_table(text, path, Some(4), parse_real)?;
    let rows = table
        .rows
        .into_iter()
        .map(|(stamp_ns, v)| TruthRow {
            stamp_ns,
            position_m: [v[0], v[1], v[2]],
        })
        .collect();
    Ok((rows, table.dropped))
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

/// The kept rows of a CSV file: `(stamp_ns, values after t)`.
struct Table<V> {
    /// Cells per row, `t` included.
    columns: usize,
    /// The line of the header row (or of the first data row when there is none).
    first_line: usize,
    rows: Vec<(i64, Vec<V>)>,
    dropped: Vec<Dropped>,
}

/// Parses a CSV with `t` first and `columns` cells per row (from the header row when `None`).
fn parse_table<V>(
    text: &str,
    file: &Path,
    columns: Option<usize>,
    parse_value: fn(&str) -> Cell<V>,
) -> Result<Table<V>> {
    let ends_with_newline = text.ends_with('\n');
    let mut lines = text
        .split('\n')
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim_end_matches('\r')))
        .filter(|(_, line)| !line.trim().is_empty())
        .peekable();
    let Some(&(first_line, first)) = lines.peek() else {
        return Err(Error::Empty { file: file.to_owned() });
    };
    let first_cells: Vec<&str> = first.split(',').map(str::trim).collect();
    let first_cell = first_cells.first().copied().unwrap_or_default();
    let has_header = matches!(parse_stamp_ns(first_cell), Cell::NotANumber);
    let want = columns.unwrap_or(first_cells.len());
    let names: Vec<String> = if has_header {
        lines.next();
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

    let mut table = Table {
        columns: want,
        first_line,
        rows: Vec::new(),
        dropped: Vec::new(),
    };
    let mut previous_ns: Option<i64> = None;
    let mut cells = Vec::with_capacity(want);
    while let Some((line, text)) = lines.next() {
        let drop = |reason| Dropped {
            file: file.to_owned(),
            record: Record::Line(line),
            reason,
        };
        let got = text.split(',').count();
        if got != want {
            if lines.peek().is_none() && !ends_with_newline {
                table.dropped.push(drop(DropReason::TruncatedLine { got, want }));
                continue;
            }
            return Err(Error::ColumnCount {
                file: file.to_owned(),
                line,
                got,
                want,
            });
        }
        let mut not_finite = None;
        cells.clear();
        let mut stamp_ns = 0;
        for (index, cell) in text.split(',').map(str::trim).enumerate() {
            let column = index + 1;
            let name = || names.get(index).cloned().unwrap_or_default();
            let refuse_not_a_number = || Error::NotANumber {
                file: file.to_owned(),
                line,
                column,
                name: name(),
                text: cell.to_owned(),
            };
            let refuse_range = |why| Error::OutOfRange {
                file: file.to_owned(),
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
            match parse_value(cell) {
                Cell::Value(v) => cells.push(v),
                Cell::NotFinite => not_finite = not_finite.or(Some((column, name()))),
                Cell::NotANumber => return Err(refuse_not_a_number()),
                Cell::OutOfRange(why) => return Err(refuse_range(why)),
            }
        }
        if let Some((column, name)) = not_finite {
            table.dropped.push(drop(DropReason::NotFinite { column, name }));
            continue;
        }
        if let Some(previous_ns) = previous_ns.filter(|&p| stamp_ns <= p) {
            table
                .dropped
                .push(drop(DropReason::StampNotIncreasing { stamp_ns, previous_ns }));
            continue;
        }
        previous_ns = Some(stamp_ns);
        table.rows.push((stamp_ns, std::mem::take(&mut cells)));
        cells.reserve(want);
    }
    Ok(table)
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
