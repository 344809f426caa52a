//! [`Radargram`]: one radar line as a file holds it, the common result of every reader.

use std::path::PathBuf;

use crate::error::Dropped;

/// The file format a [`Radargram`] was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// GSSI SIR `.DZT`.
    Dzt,
    /// Sensors & Software pulseEKKO `.DT1` with its `.HD`.
    Dt1,
    /// A CMU-GPR sequence folder's `gpr_meas.csv`.
    CmuGpr,
}

/// One radar line as a file holds it: raw counts, the time axis and where each trace was taken.
#[derive(Debug, Clone, PartialEq)]
pub struct Radargram {
    /// The file the traces came from.
    pub source: PathBuf,
    /// Its format.
    pub format: Format,
    /// Channels (antenna pairs) in the file; every trace names its own.
    pub channels: u16,
    /// Samples in every trace.
    pub samples_per_trace: usize,
    /// Time between two samples (ns).
    pub sample_interval_ns: f64,
    /// Two-way travel time of sample 0 relative to time zero (ns); negative when time zero lies
    /// inside the trace. 0 when the file says nothing.
    pub time_zero_ns: f64,
    /// Centre frequency of the antenna (Hz); NaN when the file does not say.
    pub center_frequency_hz: f64,
    /// The traces in file order (for several channels: scan 0 channel 0, scan 0 channel 1, ...).
    pub traces: Vec<RawTrace>,
    /// Records the reader skipped and counted (a cut-short last trace, a bad CSV row).
    pub dropped: Vec<Dropped>,
}

impl Radargram {
    /// The traces of one channel, in file order.
    pub fn channel(&self, channel: u16) -> impl Iterator<Item = &RawTrace> {
        self.traces.iter().filter(move |t| t.channel == channel)
    }

    /// Two-way travel time of sample `index` relative to time zero (ns).
    pub fn sample_time_ns(&self, index: usize) -> f64 {
        self.time_zero_ns + index as f64 * self.sample_interval_ns
    }
}

/// One trace (A-scan) as recorded.
#[derive(Debug, Clone, PartialEq)]
pub struct RawTrace {
    /// The channel, counted from 0.
    pub channel: u16,
    /// When the trace was taken (ns) on the recording's own clock; `None` when the file does not
    /// say. Each reader documents its clock.
    pub stamp_ns: Option<i64>,
    /// Distance along the line (m); NaN when the file does not say.
    pub distance_m: f64,
    /// The samples, raw counts as stored (after removing an unsigned format's offset).
    pub samples: RawSamples,
}

/// Raw sample counts, in the width the file stores them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RawSamples {
    /// 8- and 16-bit files (8-bit values span -128..=127).
    I16(Vec<i16>),
    /// 32-bit files.
    I32(Vec<i32>),
}

impl RawSamples {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            Self::I16(v) => v.len(),
            Self::I32(v) => v.len(),
        }
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sample `index` widened to `i32`; `None` past the end.
    pub fn get(&self, index: usize) -> Option<i32> {
        match self {
            Self::I16(v) => v.get(index).map(|&s| i32::from(s)),
            Self::I32(v) => v.get(index).copied(),
        }
    }

    /// The samples as `f32` counts (exact for 16-bit, rounded to 24 bits for 32-bit).
    pub fn to_f32(&self) -> Vec<f32> {
        match self {
            Self::I16(v) => v.iter().map(|&s| f32::from(s)).collect(),
            Self::I32(v) => v.iter().map(|&s| s as f32).collect(),
        }
    }
}

/// `N` bytes of `bytes` from `at`, zeros past the end. For fixed header layouts whose length the
/// caller has already checked; never panics.
pub(crate) fn le_bytes<const N: usize>(bytes: &[u8], at: usize) -> [u8; N] {
    let mut out = [0; N];
    if let Some(src) = at.checked_add(N).and_then(|end| bytes.get(at..end)) {
        out.copy_from_slice(src);
    }
    out
}

/// Text up to the first NUL, non-ASCII bytes replaced by `?`, surrounding blanks removed.
pub(crate) fn ascii_text(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    bytes[..end]
        .iter()
        .map(|&b| if b.is_ascii() { char::from(b) } else { '?' })
        .collect::<String>()
        .trim()
        .to_owned()
}

/// Little-endian signed samples of `width` bytes (2 or 4; anything else reads as 4).
pub(crate) fn signed_le_samples(bytes: &[u8], width: usize) -> RawSamples {
    if width == 2 {
        RawSamples::I16(
            bytes
                .chunks_exact(2)
                .map(|c| i16::from_le_bytes([c[0], c[1]]))
                .collect(),
        )
    } else {
        RawSamples::I32(
            bytes
                .chunks_exact(4)
                .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        )
    }
}
