//! What the readers and the loader report: [`Error`] for input they refuse, [`Dropped`] for
//! single records they skip and count. Every message names the file, the record and the field.

use std::fmt;
use std::path::PathBuf;

/// Where in a file something is: the file header, a binary trace, or a text line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Record {
    /// The file as a whole (its size, its trace count).
    File,
    /// The file header (DZT channel headers; the first bytes of a DT1).
    Header,
    /// A binary trace, counted from 0 (in a DZT: a scan, which holds one trace per channel).
    Trace(usize),
    /// A text line, counted from 1 (the header row of a CSV is line 1).
    Line(usize),
}

/// Formats `file: trace 3` / `file:17` / `file: header` / `file`, the start of every message.
#[derive(Debug, Clone, Copy)]
struct At<'a> {
    file: &'a std::path::Path,
    record: Record,
}

impl fmt::Display for At<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let file = self.file.display();
        match self.record {
            Record::File => write!(f, "{file}"),
            Record::Header => write!(f, "{file}: header"),
            Record::Trace(i) => write!(f, "{file}: trace {i}"),
            Record::Line(n) => write!(f, "{file}:{n}"),
        }
    }
}

fn at(file: &std::path::Path, record: Record) -> At<'_> {
    At { file, record }
}

/// Why a reader refused its input. Each variant names the file and, where there is one, the
/// record and the field.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The file could not be opened or read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// A file the reader needs is not there (a DT1's `.HD`, a CMU folder's `gpr_meas.csv`).
    #[error("{}: not found ({why})", path.display())]
    Missing {
        /// Where the reader looked.
        path: PathBuf,
        /// Why the reader needs it.
        why: &'static str,
    },
    /// A record ends before the bytes its header promises.
    #[error("{}: truncated: {got} of {want} bytes", at(file, *record))]
    Truncated {
        /// The file.
        file: PathBuf,
        /// The record that is cut short.
        record: Record,
        /// Bytes present.
        got: usize,
        /// Bytes the record needs.
        want: usize,
    },
    /// A header field holds a value the format does not allow (or that makes the file unreadable).
    #[error("{}: {field}: {value}: {why}", at(file, *record))]
    BadField {
        /// The file.
        file: PathBuf,
        /// The record holding the field.
        record: Record,
        /// The field's name as the format documents it (`rh_bits`, `NUMBER OF TRACES`).
        field: String,
        /// The value found, as text.
        value: String,
        /// What is wrong with it.
        why: String,
    },
    /// A required key or field is absent.
    #[error("{}: {field}: missing", file.display())]
    MissingField {
        /// The file.
        file: PathBuf,
        /// The key or field (`TOTAL TIME WINDOW`).
        field: String,
    },
    /// A CSV cell is not a number of the kind its column holds.
    #[error("{}: column {column} ({name}): not a number: {text:?}", at(file, Record::Line(*line)))]
    NotANumber {
        /// The file.
        file: PathBuf,
        /// The line, counted from 1.
        line: usize,
        /// The column, counted from 1 (the stamp `t` is column 1).
        column: usize,
        /// The column's name from the header row.
        name: String,
        /// The cell as written.
        text: String,
    },
    /// A CSV cell is a number but out of the column's range (an amplitude outside int16).
    #[error("{}: column {column} ({name}): {text:?}: {why}", at(file, Record::Line(*line)))]
    OutOfRange {
        /// The file.
        file: PathBuf,
        /// The line, counted from 1.
        line: usize,
        /// The column, counted from 1.
        column: usize,
        /// The column's name from the header row.
        name: String,
        /// The cell as written.
        text: String,
        /// The allowed range.
        why: &'static str,
    },
    /// A CSV row has a different number of cells than the header row.
    #[error("{}: {got} columns, the header row has {want}", at(file, Record::Line(*line)))]
    ColumnCount {
        /// The file.
        file: PathBuf,
        /// The line, counted from 1.
        line: usize,
        /// Cells in this row.
        got: usize,
        /// Cells in the header row (or the first row when there is no header row).
        want: usize,
    },
    /// Two places that must agree do not (a DT1 trace header and its HD file).
    #[error("{}: {found}, {other}", at(file, *record))]
    Disagree {
        /// The file holding the record.
        file: PathBuf,
        /// The record.
        record: Record,
        /// What disagrees (`samples`, `bytes/sample`, `traces`).
        field: &'static str,
        /// What this record says, as a phrase (`header says 1499 samples`, `file holds 530 traces`).
        found: String,
        /// What the other place says, as a phrase (`HD says 1500`, `trace 0 says 2`).
        other: String,
    },
    /// A file holds no data at all (not even a header row).
    #[error("{}: empty", file.display())]
    Empty {
        /// The file.
        file: PathBuf,
    },
    /// The format cannot be told from the path ([`crate::format::detect`]).
    #[error(
        "{}: cannot tell the format (a folder is a CMU-GPR sequence; files: .mcap, .dzt, .dt1); set `format`",
        path.display()
    )]
    UnknownFormat {
        /// The source.
        path: PathBuf,
    },
    /// An MCAP recording cannot be opened.
    #[error("{message}")]
    Recording {
        /// The recording.
        path: PathBuf,
        /// What the recording reader said (it names the file).
        message: String,
    },
}

/// The result of the readers.
pub type Result<T> = std::result::Result<T, Error>;

/// A record a reader skipped and counted instead of refusing the whole file.
#[derive(Debug, Clone, PartialEq)]
pub struct Dropped {
    /// The file.
    pub file: PathBuf,
    /// The record skipped (a trace for binary files, a line for CSV).
    pub record: Record,
    /// Why.
    pub reason: DropReason,
}

impl fmt::Display for Dropped {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", at(&self.file, self.record), self.reason)
    }
}

/// Why a record was skipped.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum DropReason {
    /// The file ends inside this record (the last trace of a cut-short recording).
    Truncated {
        /// Bytes present.
        got: usize,
        /// Bytes the record needs.
        want: usize,
    },
    /// The last line of a CSV has no line end and fewer or more cells than the header: the
    /// writer was stopped while writing it.
    TruncatedLine {
        /// Cells present.
        got: usize,
        /// Cells the header row has.
        want: usize,
    },
    /// A cell is NaN or infinite.
    NotFinite {
        /// The column, counted from 1.
        column: usize,
        /// The column's name.
        name: String,
    },
    /// The stamp is not after the previous kept row's stamp (repeated or going backwards).
    StampNotIncreasing {
        /// This row's stamp (ns).
        stamp_ns: i64,
        /// The previous kept row's stamp (ns).
        previous_ns: i64,
    },
}

impl fmt::Display for DropReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Truncated { got, want } => write!(f, "truncated: {got} of {want} bytes"),
            Self::TruncatedLine { got, want } => {
                write!(f, "truncated last line: {got} of {want} columns")
            }
            Self::NotFinite { column, name } => write!(f, "column {column} ({name}): not finite"),
            Self::StampNotIncreasing { stamp_ns, previous_ns } => {
                let how = if stamp_ns == previous_ns {
                    "repeated"
                } else {
                    "goes backwards"
                };
                write!(f, "stamp {how}: {stamp_ns} ns after {previous_ns} ns")
            }
        }
    }
}
