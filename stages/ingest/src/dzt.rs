//! GSSI SIR `.DZT` files.
//!
//! Layout: one 1024-byte little-endian header per channel ([`DztHeader`]), then the data from
//! [`DztHeader::data_offset_bytes`] on: scans one after the other, each scan holding one trace of
//! `rh_nsamp` samples per channel (channel 0 first). Samples are unsigned for 8 and 16 bits (the
//! reader subtracts 2^(bits-1), whatever `rh_zero` says) and signed for 32 bits.
//!
//! What the reader decides:
//! - **All samples are kept.** Most SIR systems overwrite the first two samples of every trace:
//!   sample 0 holds a scan counter and sample 1 a user-mark flag (in `GSSI_FILE____032.DZT`
//!   raw sample 0 is the scan index and raw sample 1 is `0x6400` on the 11 marked scans, 0
//!   elsewhere). The format does not say how many words a system uses, so the reader does not
//!   guess: `samples_per_trace` is `rh_nsamp`, and processing should mute samples 0 and 1.
//! - **Distance**: scan `k` is at `k / rhf_spm` metres when `rhf_spm > 0` (survey-wheel mode);
//!   NaN otherwise.
//! - **Stamps**: only in time mode (`rhf_spm == 0`), where scans are taken at `rhf_sps` scans per
//!   second: scan `k` is at `k / rhf_sps` seconds after the first scan. In wheel mode the wheel
//!   triggers the scans and `rhf_sps` is only the maximum rate, so `stamp_ns` is `None`.
//! - **Time zero**: `rhf_position` is a display offset without a documented sign convention, so
//!   `time_zero_ns` is 0; the value is in [`DztHeader::position_ns`].
//! - **Centre frequency**: read from the antenna name when it reads like `400MHz` or `1.6GHz`;
//!   NaN for model numbers (`5103`).
//! - **Truncation**: a scan cut short at the end of the file is not returned; it is reported in
//!   [`Radargram::dropped`] with the bytes present. Everything before it is returned.
//! - `rh_tag` is not checked (`GSSI_FILE____032.DZT` has `0x0700`, not the documented `0x00ff`).

use std::path::{Path, PathBuf};

use crate::error::{DropReason, Dropped, Error, Record, Result};
use crate::radargram::{Format, Radargram, RawSamples, RawTrace, ascii_text, le_bytes, signed_le_samples};

/// Size of one channel header (bytes).
pub const DZT_HEADER_BYTES: usize = 1024;

/// A packed DZT date (`rfDateByte`): 5 bits seconds/2, 6 minutes, 5 hours, 5 day, 4 month,
/// 7 years since 1980, from the least significant bit up. Not checked for validity; an all-zero
/// field (no date) reads as 1980-00-00 00:00:00.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DztDate {
    /// The 32 bits as stored.
    pub bits: u32,
    /// Year (1980..=2107).
    pub year: u16,
    /// Month (1..=12 when valid).
    pub month: u8,
    /// Day of the month (1..=31 when valid).
    pub day: u8,
    /// Hour (0..=23 when valid).
    pub hour: u8,
    /// Minute (0..=59 when valid).
    pub minute: u8,
    /// Second (even, 0..=58 when valid).
    pub second: u8,
}

impl DztDate {
    /// Unpacks the 32 bits.
    pub fn from_bits(bits: u32) -> Self {
        let field = |shift: u32, width: u32| ((bits >> shift) & ((1 << width) - 1)) as u8;
        Self {
            bits,
            second: field(0, 5) * 2,
            minute: field(5, 6),
            hour: field(11, 5),
            day: field(16, 5),
            month: field(21, 4),
            year: 1980 + (bits >> 25) as u16,
        }
    }
}

/// One 1024-byte DZT channel header, every documented field of its first 128 bytes (the
/// byte offset of each is in its doc). Field names follow GSSI's `rh_*` names in plain words.
#[derive(Debug, Clone, PartialEq)]
pub struct DztHeader {
    /// `rh_tag` (0): `0x00ff` in the documentation, `0xfnff` for old files; not checked.
    pub tag: u16,
    /// `rh_data` (2): the data offset field; see [`Self::data_offset_bytes`].
    pub data_field: u16,
    /// `rh_nsamp` (4): samples per trace.
    pub samples_per_trace: u16,
    /// `rh_bits` (6): bits per sample (8, 16 or 32).
    pub bits_per_sample: u16,
    /// `rh_zero` (8): binary offset (0x80 / 0x8000) or, on SIR-30 and UtilityScan DF, repeats
    /// per sample. Not used: 8/16-bit samples are always offset by 2^(bits-1).
    pub zero: i16,
    /// `rhf_sps` (10): scans per second (in wheel mode: the maximum scan rate).
    pub scans_per_second: f32,
    /// `rhf_spm` (14): scans per metre; 0 in time mode.
    pub scans_per_metre: f32,
    /// `rhf_mpm` (18): metres per user mark.
    pub metres_per_mark: f32,
    /// `rhf_position` (22): position of the range window (ns).
    pub position_ns: f32,
    /// `rhf_range` (26): time range of a trace (ns).
    pub range_ns: f32,
    /// `rh_npass` (30): passes, for 2-D files.
    pub passes: u16,
    /// `rhb_cdt` (32): creation date and time.
    pub created: DztDate,
    /// `rhb_mdt` (36): last modification date and time.
    pub modified: DztDate,
    /// `rh_rgain` / `rh_mapOffset` (40): offset of the range gain function within the header (bytes).
    pub range_gain_offset: u16,
    /// `rh_nrgain` / `rh_mapSize` (42): size of the range gain function (bytes).
    pub range_gain_size: u16,
    /// `rh_text` (44): offset of the text block within the header (bytes).
    pub text_offset: u16,
    /// `rh_ntext` (46): size of the text block (bytes).
    pub text_size: u16,
    /// `rh_proc` (48): offset of the processing history within the header (bytes).
    pub processing_offset: u16,
    /// `rh_nproc` (50): size of the processing history (bytes).
    pub processing_size: u16,
    /// `rh_nchan` (52): channels in the file.
    pub channels: u16,
    /// `rhf_epsr` (54): average relative permittivity (dimensionless).
    pub relative_permittivity: f32,
    /// `rhf_top` (58): position of the top of the trace (m).
    pub top_m: f32,
    /// `rhf_depth` (62): depth range of a trace (m).
    pub depth_m: f32,
    /// `rh_coordX` (66): X coordinates (start, end) as stored.
    pub coord_x: [f32; 2],
    /// `rhf_servo_level` (74): gain servo level.
    pub servo_level: f32,
    /// `reserved` (78): 3 bytes as stored.
    pub reserved: [u8; 3],
    /// `rh_accomp` (81): antenna configuration component.
    pub antenna_config: u8,
    /// `rh_sconfig` (82): setup configuration number.
    pub setup_config: i16,
    /// `rh_spp` (84): scans per pass.
    pub scans_per_pass: i16,
    /// `rh_linenum` (86): line number.
    pub line_number: i16,
    /// `rh_coordY` (88): Y coordinates (start, end) as stored.
    pub coord_y: [f32; 2],
    /// `rh_lineorder` (96, low 4 bits).
    pub line_order: u8,
    /// `rh_slicetype` (96, high 4 bits).
    pub slice_type: u8,
    /// `rh_dtype` (97): data type byte.
    pub data_type: u8,
    /// `rh_antname` (98, 14 bytes ASCII, NUL-padded): antenna name.
    pub antenna_name: String,
    /// `rh_pass0TX` (112, low 4 bits): active transmit mask, pass 0.
    pub pass0_tx_mask: u8,
    /// `rh_pass1TX` (112, high 4 bits): active transmit mask, pass 1.
    pub pass1_tx_mask: u8,
    /// `rh_version` (113, low 3 bits): 1 no GPS, 2 GPS.
    pub version: u8,
    /// `rh_system` (113, high 5 bits): the control unit.
    pub system: u8,
    /// `rh_name` (114, 12 bytes ASCII, NUL-padded): the file's initial name.
    pub initial_name: String,
    /// `rh_chksum` (126): header checksum (not checked).
    pub checksum: u16,
}

impl DztHeader {
    /// Parses one 1024-byte header block; `None` when `block` is shorter. Checks nothing else.
    pub fn parse(block: &[u8]) -> Option<Self> {
        if block.len() < DZT_HEADER_BYTES {
            return None;
        }
        let u16_at = |at| u16::from_le_bytes(le_bytes(block, at));
        let i16_at = |at| i16::from_le_bytes(le_bytes(block, at));
        let u32_at = |at| u32::from_le_bytes(le_bytes(block, at));
        let f32_at = |at| f32::from_le_bytes(le_bytes(block, at));
        let byte = |at: usize| block.get(at).copied().unwrap_or(0);
        Some(Self {
            tag: u16_at(0),
            data_field: u16_at(2),
            samples_per_trace: u16_at(4),
            bits_per_sample: u16_at(6),
            zero: i16_at(8),
            scans_per_second: f32_at(10),
            scans_per_metre: f32_at(14),
            metres_per_mark: f32_at(18),
            position_ns: f32_at(22),
            range_ns: f32_at(26),
            passes: u16_at(30),
            created: DztDate::from_bits(u32_at(32)),
            modified: DztDate::from_bits(u32_at(36)),
            range_gain_offset: u16_at(40),
            range_gain_size: u16_at(42),
            text_offset: u16_at(44),
            text_size: u16_at(46),
            processing_offset: u16_at(48),
            processing_size: u16_at(50),
            channels: u16_at(52),
            relative_permittivity: f32_at(54),
            top_m: f32_at(58),
            depth_m: f32_at(62),
            coord_x: [f32_at(66), f32_at(70)],
            servo_level: f32_at(74),
            reserved: le_bytes(block, 78),
            antenna_config: byte(81),
            setup_config: i16_at(82),
            scans_per_pass: i16_at(84),
            line_number: i16_at(86),
            coord_y: [f32_at(88), f32_at(92)],
            line_order: byte(96) & 0x0f,
            slice_type: byte(96) >> 4,
            data_type: byte(97),
            antenna_name: ascii_text(block.get(98..112).unwrap_or_default()),
            pass0_tx_mask: byte(112) & 0x0f,
            pass1_tx_mask: byte(112) >> 4,
            version: byte(113) & 0x07,
            system: byte(113) >> 3,
            initial_name: ascii_text(block.get(114..126).unwrap_or_default()),
            checksum: u16_at(126),
        })
    }

    /// Where the data starts (bytes from the start of the file): `1024 * rh_data` when
    /// `rh_data < 1024` (big headers), else `1024 * rh_nchan`.
    pub fn data_offset_bytes(&self) -> usize {
        let blocks = if usize::from(self.data_field) < DZT_HEADER_BYTES {
            self.data_field
        } else {
            self.channels
        };
        usize::from(blocks) * DZT_HEADER_BYTES
    }

    /// Bytes per sample (1, 2 or 4 for a valid header).
    pub fn bytes_per_sample(&self) -> usize {
        usize::from(self.bits_per_sample / 8)
    }

    /// Centre frequency (Hz) read from the antenna name (`400MHz`, `1.6GHz`); NaN otherwise.
    pub fn center_frequency_hz(&self) -> f64 {
        frequency_in_name_hz(&self.antenna_name)
    }
}

/// `400MHz` -> 4e8, `1.6 GHz` -> 1.6e9; NaN when the name has no such number.
fn frequency_in_name_hz(name: &str) -> f64 {
    let lower = name.to_ascii_lowercase();
    for (unit, scale) in [("mhz", 1e6), ("ghz", 1e9)] {
        if let Some(at) = lower.find(unit) {
            let number: String = lower[..at]
                .trim_end()
                .chars()
                .rev()
                .take_while(|c| c.is_ascii_digit() || *c == '.')
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            if let Ok(value) = number.parse::<f64>() {
                return value * scale;
            }
        }
    }
    f64::NAN
}

/// Reads a DZT file; see the module docs for what is kept and what is decided.
pub fn read_dzt(path: &Path) -> Result<(DztHeader, Radargram)> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.to_owned(),
        source,
    })?;
    parse_dzt(&bytes, path)
}

/// Every channel header of a DZT file (the first governs the layout; the others are
/// returned as stored, unchecked).
pub fn channel_headers(bytes: &[u8], path: &Path) -> Result<Vec<DztHeader>> {
    let first = first_header(bytes, path)?;
    let channels = usize::from(first.channels).max(1);
    Ok((0..channels)
        .filter_map(|c| bytes.get(c * DZT_HEADER_BYTES..).and_then(DztHeader::parse))
        .collect())
}

fn first_header(bytes: &[u8], path: &Path) -> Result<DztHeader> {
    DztHeader::parse(bytes).ok_or_else(|| Error::Truncated {
        file: path.to_owned(),
        record: Record::Header,
        got: bytes.len(),
        want: DZT_HEADER_BYTES,
    })
}

/// Where a checked DZT file's scans are, and how they read.
#[derive(Debug, Clone)]
struct Layout {
    header: DztHeader,
    offset: usize,
    trace_bytes: usize,
    scan_bytes: usize,
    /// Scans per metre in survey-wheel mode.
    spm: Option<f64>,
    /// Scans per second in time mode.
    sps: Option<f64>,
}

impl Layout {
    /// Checks the header of a `file_len`-byte file from its first bytes `head` (at least the
    /// channel headers, when the file has them).
    fn check(head: &[u8], file_len: usize, path: &Path) -> Result<Self> {
        let header = first_header(head, path)?;
        let bad = |field: &str, value: String, why: String| Error::BadField {
            file: path.to_owned(),
            record: Record::Header,
            field: field.to_owned(),
            value,
            why,
        };
        if !matches!(header.bits_per_sample, 8 | 16 | 32) {
            let bits = header.bits_per_sample.to_string();
            return Err(bad("rh_bits", bits, "not 8, 16 or 32".into()));
        }
        if header.samples_per_trace == 0 {
            return Err(bad("rh_nsamp", "0".into(), "no samples per trace".into()));
        }
        if header.channels == 0 {
            return Err(bad("rh_nchan", "0".into(), "no channels".into()));
        }
        if !(header.range_ns.is_finite() && header.range_ns > 0.0) {
            let range = header.range_ns.to_string();
            return Err(bad("rhf_range", range, "not a positive time range (ns)".into()));
        }
        let channels = usize::from(header.channels);
        let headers_bytes = channels * DZT_HEADER_BYTES;
        if file_len < headers_bytes {
            return Err(Error::Truncated {
                file: path.to_owned(),
                record: Record::Header,
                got: file_len,
                want: headers_bytes,
            });
        }
        let offset = header.data_offset_bytes();
        if offset < headers_bytes {
            let why = format!("data offset {offset} B lies inside the {channels} channel header(s)");
            return Err(bad("rh_data", header.data_field.to_string(), why));
        }
        if offset > file_len {
            let why = format!("data offset {offset} B is past the end of the file ({file_len} B)");
            return Err(bad("rh_data", header.data_field.to_string(), why));
        }
        let trace_bytes = usize::from(header.samples_per_trace) * header.bytes_per_sample();
        let spm = f64::from(header.scans_per_metre);
        let sps = f64::from(header.scans_per_second);
        let wheel_mode = spm.is_finite() && spm > 0.0;
        let timed = !wheel_mode && sps.is_finite() && sps > 0.0;
        Ok(Self {
            offset,
            trace_bytes,
            scan_bytes: trace_bytes.saturating_mul(channels),
            spm: wheel_mode.then_some(spm),
            sps: timed.then_some(sps),
            header,
        })
    }

    /// The traces of scan number `scan`, from its bytes.
    fn traces<'a>(&self, scan: usize, bytes: &'a [u8]) -> impl Iterator<Item = RawTrace> + 'a {
        let distance_m = self.spm.map_or(f64::NAN, |spm| scan as f64 / spm);
        let stamp_ns = self.sps.map(|sps| (scan as f64 * 1e9 / sps).round() as i64);
        let bits = self.header.bits_per_sample;
        (0..self.header.channels)
            .zip(bytes.chunks_exact(self.trace_bytes))
            .map(move |(channel, trace)| RawTrace {
                channel,
                stamp_ns,
                distance_m,
                samples: decode_samples(trace, bits),
            })
    }

    /// The file's description, without its traces.
    fn radargram(&self, path: &Path) -> Radargram {
        let samples = usize::from(self.header.samples_per_trace);
        Radargram {
            source: path.to_owned(),
            format: Format::Dzt,
            channels: self.header.channels,
            samples_per_trace: samples,
            sample_interval_ns: f64::from(self.header.range_ns) / samples as f64,
            time_zero_ns: 0.0,
            center_frequency_hz: self.header.center_frequency_hz(),
            traces: Vec::new(),
            dropped: Vec::new(),
        }
    }

    fn truncated(&self, path: &Path, scan: usize, got: usize) -> Dropped {
        Dropped {
            file: path.to_owned(),
            record: Record::Trace(scan),
            reason: DropReason::Truncated {
                got,
                want: self.scan_bytes,
            },
        }
    }
}

/// Parses the bytes of a DZT file; `path` only names the file in errors and in the result.
pub fn parse_dzt(bytes: &[u8], path: &Path) -> Result<(DztHeader, Radargram)> {
    let layout = Layout::check(bytes, bytes.len(), path)?;
    let data = bytes.get(layout.offset..).unwrap_or_default();
    let scans = data.chunks_exact(layout.scan_bytes);
    let mut radargram = layout.radargram(path);
    if !scans.remainder().is_empty() {
        radargram
            .dropped
            .push(layout.truncated(path, data.len() / layout.scan_bytes, scans.remainder().len()));
    }
    radargram.traces = scans
        .enumerate()
        .flat_map(|(scan, scan_data)| layout.traces(scan, scan_data))
        .collect();
    Ok((layout.header, radargram))
}

/// A DZT file read scan by scan from disk: memory does not grow with its length. Yields the
/// traces [`read_dzt`] would return, in the same order; a scan cut short at the end is
/// reported in [`DztStream::dropped`] once the stream has ended.
#[derive(Debug)]
pub struct DztStream {
    layout: Layout,
    path: PathBuf,
    reader: std::io::BufReader<std::fs::File>,
    scan: usize,
    buffer: Vec<u8>,
    pending: std::collections::VecDeque<RawTrace>,
    /// Records skipped so far (a cut-short last scan, a read error).
    pub dropped: Vec<Dropped>,
    done: bool,
}

impl DztStream {
    /// Opens `path` and checks its header; returns the header and the file's description (its
    /// `traces` empty: they come from the stream).
    ///
    /// # Errors
    /// As [`read_dzt`] for the header.
    pub fn open(path: &Path) -> Result<(DztHeader, Radargram, Self)> {
        use std::io::{Read, Seek};
        let io = |source| Error::Io {
            path: path.to_owned(),
            source,
        };
        let mut file = std::fs::File::open(path).map_err(io)?;
        let len = usize::try_from(file.metadata().map_err(io)?.len()).unwrap_or(usize::MAX);
        // the first header says how many there are
        let mut head = Vec::new();
        (&mut file)
            .take(DZT_HEADER_BYTES as u64)
            .read_to_end(&mut head)
            .map_err(io)?;
        let channels = first_header(&head, path).map_or(1, |h| usize::from(h.channels).max(1));
        (&mut file)
            .take(((channels - 1) * DZT_HEADER_BYTES) as u64)
            .read_to_end(&mut head)
            .map_err(io)?;
        let layout = Layout::check(&head, len, path)?;
        file.seek(std::io::SeekFrom::Start(layout.offset as u64)).map_err(io)?;
        let radargram = layout.radargram(path);
        Ok((
            layout.header.clone(),
            radargram,
            Self {
                buffer: vec![0; layout.scan_bytes],
                layout,
                path: path.to_owned(),
                reader: std::io::BufReader::with_capacity(1 << 16, file),
                scan: 0,
                pending: std::collections::VecDeque::new(),
                dropped: Vec::new(),
                done: false,
            },
        ))
    }

    /// Moves to the first scan stamped at or after `start_ns` (stamps count from 0 at scan 0:
    /// `scan / rhf_sps` in time mode, `scan x trace_interval_s` in survey-wheel mode) without
    /// reading the scans before it. Returns the scan number and, in survey-wheel mode, the
    /// distance of the scan before it (for the wheel speed of the first one).
    ///
    /// # Errors
    /// When the file cannot seek.
    pub fn seek_stamp(&mut self, start_ns: i64, trace_interval_s: f64) -> Result<(usize, Option<f64>)> {
        use std::io::Seek;
        let period_ns = match self.layout.sps {
            Some(sps) => 1e9 / sps,
            None => trace_interval_s * 1e9,
        };
        let scan = if start_ns <= 0 || period_ns <= 0.0 {
            0
        } else {
            // the smallest scan whose rounded stamp is at or after the start
            let mut k = (start_ns as f64 / period_ns).floor().max(0.0) as usize;
            while ((k as f64 * period_ns).round() as i64) < start_ns {
                k += 1;
            }
            k
        };
        let at = self.layout.offset as u64 + (scan as u64) * self.layout.scan_bytes as u64;
        self.reader
            .seek(std::io::SeekFrom::Start(at))
            .map_err(|source| Error::Io {
                path: self.path.clone(),
                source,
            })?;
        self.scan = scan;
        self.pending.clear();
        let before = self.layout.spm.filter(|_| scan > 0).map(|spm| (scan - 1) as f64 / spm);
        Ok((scan, before))
    }

    /// Channels per scan.
    pub fn channels(&self) -> usize {
        usize::from(self.layout.header.channels)
    }

    /// Scans in the file (complete ones), from its length.
    pub fn scans(&self) -> usize {
        let len = self.reader.get_ref().metadata().map_or(0, |m| m.len());
        usize::try_from(len).unwrap_or(0).saturating_sub(self.layout.offset) / self.layout.scan_bytes.max(1)
    }

    /// Reads the next scan into `pending`; false at the end.
    fn read_scan(&mut self) -> bool {
        use std::io::Read;
        let mut got = 0;
        while got < self.buffer.len() {
            match self.reader.read(&mut self.buffer[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    tracing::warn!(
                        "{}: read error at scan {}: {e}; the scans before it are kept",
                        self.path.display(),
                        self.scan
                    );
                    self.dropped.push(self.layout.truncated(&self.path, self.scan, got));
                    return false;
                }
            }
        }
        if got < self.buffer.len() {
            if got > 0 {
                self.dropped.push(self.layout.truncated(&self.path, self.scan, got));
            }
            return false;
        }
        self.pending.extend(self.layout.traces(self.scan, &self.buffer));
        self.scan += 1;
        true
    }
}

impl Iterator for DztStream {
    type Item = RawTrace;

    fn next(&mut self) -> Option<RawTrace> {
        if self.pending.is_empty() && !self.done && !self.read_scan() {
            self.done = true;
        }
        self.pending.pop_front()
    }
}

/// Little-endian samples; 8 and 16 bits unsigned with the mid-scale offset removed.
fn decode_samples(bytes: &[u8], bits: u16) -> RawSamples {
    match bits {
        8 => RawSamples::I16(bytes.iter().map(|&b| i16::from(b) - 128).collect()),
        16 => RawSamples::I16(
            bytes
                .chunks_exact(2)
                .map(|c| (u16::from_le_bytes([c[0], c[1]]) ^ 0x8000) as i16)
                .collect(),
        ),
        _ => signed_le_samples(bytes, 4),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_unpack_from_the_least_significant_bit() {
        // GSSI_FILE____032.DZT's creation date.
        let d = DztDate::from_bits(0x4a75_0497);
        assert_eq!(
            (d.year, d.month, d.day, d.hour, d.minute, d.second),
            (2017, 3, 21, 0, 36, 46)
        );
    }

    #[test]
    fn antenna_names_give_frequencies_when_they_say_one() {
        assert_eq!(frequency_in_name_hz("400MHz"), 400e6);
        assert_eq!(frequency_in_name_hz("1.6 GHz"), 1.6e9);
        assert!(frequency_in_name_hz("5103").is_nan());
        assert!(frequency_in_name_hz("MHz").is_nan());
    }

    #[test]
    fn sixteen_bit_samples_lose_their_offset() {
        let bytes = [0x00, 0x00, 0x00, 0x80, 0xff, 0xff];
        assert_eq!(decode_samples(&bytes, 16), RawSamples::I16(vec![-32768, 0, 32767]));
        assert_eq!(decode_samples(&[0, 128, 255], 8), RawSamples::I16(vec![-128, 0, 127]));
    }
}
