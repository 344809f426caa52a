//! The readers on input they must refuse or repair, built byte by byte here, and property
//! tests: garbage never panics, what a writer writes reads back the same.

use std::path::Path;

use gprflow_ingest::cmu::{
    self, CMU_SAMPLE_INTERVAL_NS, parse_gpr_csv, parse_imu_csv, parse_truth_csv, parse_wheel_csv, read_cmu_sequence,
};
use gprflow_ingest::dt1::{self, parse_dt1, parse_hd, read_dt1};
use gprflow_ingest::dzt::{DZT_HEADER_BYTES, parse_dzt};
use gprflow_ingest::error::{DropReason, Record};
use gprflow_ingest::{Error, RawSamples};
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------------
// Writers for the tests

/// The header fields a test varies; the rest of the 1024 bytes stay zero.
#[derive(Debug, Clone)]
struct DztSpec {
    data_field: u16,
    samples: u16,
    bits: u16,
    channels: u16,
    scans_per_second: f32,
    scans_per_metre: f32,
    range_ns: f32,
    antenna: &'static str,
}

impl Default for DztSpec {
    fn default() -> Self {
        Self {
            data_field: 1024,
            samples: 4,
            bits: 16,
            channels: 1,
            scans_per_second: 64.0,
            scans_per_metre: 0.0,
            range_ns: 8.0,
            antenna: "1.6GHz",
        }
    }
}

impl DztSpec {
    /// Channel headers (one per channel) followed by `data`.
    fn file(&self, data: &[u8]) -> Vec<u8> {
        let mut block = vec![0_u8; DZT_HEADER_BYTES];
        let mut put = |at: usize, bytes: &[u8]| block[at..at + bytes.len()].copy_from_slice(bytes);
        put(0, &0x00ff_u16.to_le_bytes());
        put(2, &self.data_field.to_le_bytes());
        put(4, &self.samples.to_le_bytes());
        put(6, &self.bits.to_le_bytes());
        put(10, &self.scans_per_second.to_le_bytes());
        put(14, &self.scans_per_metre.to_le_bytes());
        put(26, &self.range_ns.to_le_bytes());
        put(52, &self.channels.to_le_bytes());
        put(98, self.antenna.as_bytes());
        let mut out = block.repeat(usize::from(self.channels.max(1)));
        out.extend_from_slice(data);
        out
    }

    /// Samples as the format stores them: offset binary for 8/16 bits, signed for 32.
    fn encode(&self, samples: &[i32]) -> Vec<u8> {
        let mut out = Vec::new();
        for &s in samples {
            match self.bits {
                8 => out.push((s + 128) as u8),
                16 => out.extend_from_slice(&((s + 32768) as u16).to_le_bytes()),
                _ => out.extend_from_slice(&s.to_le_bytes()),
            }
        }
        out
    }
}

/// An HD file as pulseEKKO writes it (CR CR LF line ends, as in the real files).
fn hd_text(traces: usize, points: usize, units: &str) -> String {
    [
        "1234".to_owned(),
        "Data Collected with a test".to_owned(),
        "2024-01-02".to_owned(),
        format!("NUMBER OF TRACES   = {traces}"),
        format!("NUMBER OF PTS/TRC  = {points}"),
        "TIMEZERO AT POINT  = 11".to_owned(),
        "TOTAL TIME WINDOW  = 100".to_owned(),
        format!("POSITION UNITS     = {units}"),
        "NOMINAL FREQUENCY  = 250.00".to_owned(),
        "SOMETHING NEW      = kept".to_owned(),
    ]
    .map(|l| l + " \r\r\n")
    .concat()
}

/// One DT1 trace: 128-byte header and the samples (`wide`: int32).
fn dt1_trace(index: usize, position: f32, samples: &[i32], wide: bool) -> Vec<u8> {
    let mut out = vec![0_u8; 128];
    let width = if wide { 4.0_f32 } else { 2.0 };
    let fields = [(index + 1) as f32, position, samples.len() as f32, 0.0, 0.0, width];
    for (i, v) in fields.iter().enumerate() {
        out[4 * i..4 * i + 4].copy_from_slice(&v.to_le_bytes());
    }
    out[92..96].copy_from_slice(&(3600.0_f32 + index as f32).to_le_bytes());
    for &s in samples {
        if wide {
            out.extend_from_slice(&s.to_le_bytes());
        } else {
            out.extend_from_slice(&(s as i16).to_le_bytes());
        }
    }
    out
}

/// Seconds with nine decimals, as our simulator writes `t` (the sign in front, so that
/// negative stamps read back too).
fn seconds(stamp_ns: i64) -> String {
    let sign = if stamp_ns < 0 { "-" } else { "" };
    let abs = stamp_ns.unsigned_abs();
    format!("{sign}{}.{:09}", abs / 1_000_000_000, abs % 1_000_000_000)
}

fn gpr_csv(rows: &[(i64, Vec<i16>)], samples: usize) -> String {
    let names: Vec<String> = (1..=samples).map(|i| format!("amp_{i}")).collect();
    let mut out = format!("t,{}\n", names.join(","));
    for (stamp, amps) in rows {
        let amps: Vec<String> = amps.iter().map(i16::to_string).collect();
        out += &format!("{},{}\n", seconds(*stamp), amps.join(","));
    }
    out
}

fn table_csv(header: &str, rows: &[(i64, Vec<f64>)]) -> String {
    let mut out = format!("{header}\n");
    for (stamp, values) in rows {
        let values: Vec<String> = values.iter().map(f64::to_string).collect();
        out += &format!("{},{}\n", seconds(*stamp), values.join(","));
    }
    out
}

const DZT: &str = "test.DZT";
const DT1: &str = "test.DT1";
const HD: &str = "test.HD";
const GPR: &str = "gpr_meas.csv";

fn message(e: &Error) -> String {
    e.to_string()
}

// ---------------------------------------------------------------------------------------------
// DZT

#[test]
fn dzt_samples_decode_for_every_width_and_interleave_by_channel() {
    for bits in [8, 16, 32] {
        let spec = DztSpec {
            bits,
            channels: 2,
            ..DztSpec::default()
        };
        let scan0 = [-128, -1, 0, 127, 5, 6, 7, 8];
        let scan1 = [1, 2, 3, 4, -5, -6, -7, -8];
        let data = [spec.encode(&scan0), spec.encode(&scan1)].concat();
        let (_, r) = parse_dzt(&spec.file(&data), Path::new(DZT)).expect("valid file");
        assert_eq!(r.traces.len(), 4, "2 scans x 2 channels");
        let channels: Vec<u16> = r.traces.iter().map(|t| t.channel).collect();
        assert_eq!(channels, [0, 1, 0, 1]);
        let got: Vec<i32> = r.traces[1].samples.to_f32().iter().map(|&s| s as i32).collect();
        assert_eq!(got, [5, 6, 7, 8]);
        assert_eq!(r.traces[2].samples.get(0), Some(1));
        assert_eq!(matches!(r.traces[0].samples, RawSamples::I32(_)), bits == 32);
        // Time mode: 64 scans/s.
        assert_eq!(r.traces[2].stamp_ns, Some(15_625_000));
        assert!(r.traces[2].distance_m.is_nan());
        assert_eq!(r.sample_interval_ns, 2.0);
        assert_eq!(r.center_frequency_hz, 1.6e9);
    }
}

#[test]
fn dzt_header_shorter_than_1024_bytes_is_truncated() {
    let bytes = DztSpec::default().file(&[]);
    let e = parse_dzt(&bytes[..812], Path::new(DZT)).expect_err("short header");
    assert!(matches!(
        e,
        Error::Truncated {
            record: Record::Header,
            got: 812,
            want: 1024,
            ..
        }
    ));
    assert_eq!(message(&e), "test.DZT: header: truncated: 812 of 1024 bytes");
}

#[test]
fn dzt_header_fields_out_of_range_are_refused_by_name() {
    let cases = [
        (
            DztSpec {
                bits: 12,
                ..DztSpec::default()
            },
            "test.DZT: header: rh_bits: 12: not 8, 16 or 32",
        ),
        (
            DztSpec {
                samples: 0,
                ..DztSpec::default()
            },
            "test.DZT: header: rh_nsamp: 0: no samples per trace",
        ),
        (
            DztSpec {
                channels: 0,
                ..DztSpec::default()
            },
            "test.DZT: header: rh_nchan: 0: no channels",
        ),
        (
            DztSpec {
                range_ns: f32::NAN,
                ..DztSpec::default()
            },
            "test.DZT: header: rhf_range: NaN: not a positive time range (ns)",
        ),
        (
            DztSpec {
                data_field: 0,
                ..DztSpec::default()
            },
            "test.DZT: header: rh_data: 0: data offset 0 B lies inside the 1 channel header(s)",
        ),
        (
            DztSpec {
                data_field: 5,
                ..DztSpec::default()
            },
            "test.DZT: header: rh_data: 5: data offset 5120 B is past the end of the file (1032 B)",
        ),
    ];
    for (spec, want) in cases {
        let bytes = spec.file(&[0; 8]);
        let e = parse_dzt(&bytes, Path::new(DZT)).expect_err(want);
        assert!(matches!(e, Error::BadField { .. }), "{e:?}");
        assert_eq!(message(&e), want);
    }
    // Two channels promise two headers; the file holds one and a bit.
    let spec = DztSpec {
        channels: 2,
        ..DztSpec::default()
    };
    let bytes = spec.file(&[]);
    let e = parse_dzt(&bytes[..1500], Path::new(DZT)).expect_err("second header cut");
    assert_eq!(message(&e), "test.DZT: header: truncated: 1500 of 2048 bytes");
}

#[test]
fn dzt_cut_short_keeps_the_complete_scans_and_reports_the_last() {
    let spec = DztSpec {
        samples: 512,
        scans_per_metre: 50.0,
        ..DztSpec::default()
    };
    let data = vec![0x80_u8; 3 * 1024 + 812];
    let (_, r) = parse_dzt(&spec.file(&data), Path::new(DZT)).expect("complete scans kept");
    assert_eq!(r.traces.len(), 3);
    assert_eq!(r.traces[2].distance_m, 0.04);
    assert_eq!(r.traces[2].stamp_ns, None, "wheel mode has no clock");
    assert_eq!(r.dropped.len(), 1);
    let d = &r.dropped[0];
    assert_eq!(d.record, Record::Trace(3));
    assert_eq!(d.reason, DropReason::Truncated { got: 812, want: 1024 });
    assert_eq!(d.to_string(), "test.DZT: trace 3: truncated: 812 of 1024 bytes");
}

#[test]
fn dzt_big_header_offset_counts_in_kilobytes() {
    let spec = DztSpec {
        data_field: 2,
        ..DztSpec::default()
    };
    let mut bytes = spec.file(&[0; 1024]);
    bytes.extend(spec.encode(&[1, 2, 3, 4]));
    let (h, r) = parse_dzt(&bytes, Path::new(DZT)).expect("valid file");
    assert_eq!(h.data_offset_bytes(), 2048);
    assert_eq!(r.traces.len(), 1);
    assert_eq!(r.traces[0].samples, RawSamples::I16(vec![1, 2, 3, 4]));
}

// ---------------------------------------------------------------------------------------------
// DT1 / HD

fn parse_test_dt1(hd: &str, dt1: &[u8]) -> gprflow_ingest::Result<dt1::Dt1Line> {
    let hd = parse_hd(hd, Path::new(HD))?;
    parse_dt1(hd, Path::new(HD), dt1, Path::new(DT1))
}

#[test]
fn dt1_reads_int16_and_int32_traces_and_converts_feet() {
    for wide in [false, true] {
        let dt1 = [
            dt1_trace(0, 0.0, &[1, -2, 3], wide),
            dt1_trace(1, 10.0, &[-32768, 5, 6], wide),
        ]
        .concat();
        let line = parse_test_dt1(&hd_text(2, 3, "ft"), &dt1).expect("valid line");
        let r = &line.radargram;
        assert_eq!(r.traces.len(), 2);
        assert_eq!(r.traces[1].distance_m, f64::from(10.0_f32) * 0.3048);
        assert_eq!(r.traces[1].stamp_ns, Some(3_601_000_000_000));
        assert_eq!(r.traces[0].samples.get(1), Some(-2));
        assert_eq!(matches!(r.traces[0].samples, RawSamples::I32(_)), wide);
        assert!((r.sample_interval_ns - 100.0 / 3.0).abs() < 1e-12);
        assert!((r.time_zero_ns + 10.0 * 100.0 / 3.0).abs() < 1e-9);
        assert_eq!(r.center_frequency_hz, 250e6);
        assert_eq!(line.hd.other.get("SOMETHING NEW").map(String::as_str), Some("kept"));
        assert_eq!(line.hd.text_lines.len(), 3);
    }
}

#[test]
fn dt1_trace_header_disagreeing_with_the_hd_is_refused() {
    let dt1 = [
        dt1_trace(0, 0.0, &[0; 1500], false),
        dt1_trace(1, 1.0, &[0; 1499], false),
    ]
    .concat();
    let e = parse_test_dt1(&hd_text(2, 1500, "m"), &dt1).expect_err("sample counts differ");
    assert!(matches!(
        e,
        Error::Disagree {
            record: Record::Trace(1),
            field: "samples",
            ..
        }
    ));
    assert_eq!(message(&e), "test.DT1: trace 1: header says 1499 samples, HD says 1500");

    let dt1 = [dt1_trace(0, 0.0, &[0; 4], false), dt1_trace(1, 1.0, &[0; 4], true)].concat();
    let e = parse_test_dt1(&hd_text(2, 4, "m"), &dt1).expect_err("width changes");
    assert_eq!(
        message(&e),
        "test.DT1: trace 1: header says 4 bytes/sample, trace 0 says 2"
    );

    let mut dt1 = dt1_trace(0, 0.0, &[0; 4], false);
    dt1[20..24].copy_from_slice(&3.0_f32.to_le_bytes());
    let e = parse_test_dt1(&hd_text(1, 4, "m"), &dt1).expect_err("3 bytes per sample");
    assert_eq!(message(&e), "test.DT1: trace 0: bytes/sample: 3: not 2 or 4");

    let dt1 = [dt1_trace(0, 0.0, &[0; 4], false), dt1_trace(1, 1.0, &[0; 4], false)].concat();
    let e = parse_test_dt1(&hd_text(3, 4, "m"), &dt1).expect_err("HD promises 3 traces");
    assert_eq!(message(&e), "test.DT1: file holds 2 complete traces, HD says 3");
    let e = parse_test_dt1(&hd_text(1, 4, "m"), &dt1).expect_err("HD promises 1 trace");
    assert_eq!(message(&e), "test.DT1: file holds 2 complete traces, HD says 1");
}

#[test]
fn dt1_cut_short_keeps_the_complete_traces() {
    let dt1 = [dt1_trace(0, 0.0, &[0; 4], false), dt1_trace(1, 1.0, &[0; 4], false)].concat();
    let line = parse_test_dt1(&hd_text(2, 4, "m"), &dt1[..dt1.len() - 3]).expect("one kept");
    assert_eq!(line.radargram.traces.len(), 1);
    assert_eq!(
        line.radargram.dropped[0].to_string(),
        "test.DT1: trace 1: truncated: 133 of 136 bytes"
    );
    let line = parse_test_dt1(&hd_text(2, 4, "m"), &dt1[..136 + 50]).expect("one kept");
    assert_eq!(
        line.radargram.dropped[0].to_string(),
        "test.DT1: trace 1: truncated: 50 of 136 bytes"
    );
}

#[test]
fn hd_files_missing_keys_or_holding_bad_values_are_refused_by_line() {
    let e = parse_hd("1234\r\nNUMBER OF TRACES = 3\r\n", Path::new(HD)).expect_err("no points");
    assert_eq!(message(&e), "test.HD: NUMBER OF PTS/TRC: missing");
    let text = hd_text(2, 4, "m").replace("NUMBER OF PTS/TRC  = 4", "NUMBER OF PTS/TRC  = four");
    let e = parse_hd(&text, Path::new(HD)).expect_err("not a number");
    assert_eq!(message(&e), "test.HD:5: NUMBER OF PTS/TRC: four: not a finite number");
    let text = hd_text(2, 4, "m").replace("= 2 ", "= 2.5 ");
    let e = parse_hd(&text, Path::new(HD)).expect_err("fractional count");
    assert_eq!(message(&e), "test.HD:4: NUMBER OF TRACES: 2.5: not a whole number >= 0");
    let e = parse_hd(&hd_text(2, 0, "m"), Path::new(HD)).expect_err("no points");
    assert_eq!(
        message(&e),
        "test.HD: header: NUMBER OF PTS/TRC: 0: no samples per trace"
    );
    let e = parse_hd(&hd_text(2, 4, "furlong"), Path::new(HD)).expect_err("unknown unit");
    assert_eq!(
        message(&e),
        "test.HD: header: POSITION UNITS: furlong: not a known length unit"
    );
}

#[test]
fn dt1_finds_its_hd_in_any_case_and_says_when_it_is_missing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let dt1 = dir.path().join("line.dt1");
    std::fs::write(&dt1, dt1_trace(0, 0.0, &[1, 2], false)).expect("write dt1");
    let e = read_dt1(&dt1).expect_err("no HD yet");
    assert!(matches!(e, Error::Missing { .. }), "{e:?}");
    assert!(message(&e).ends_with("line.HD: not found (a DT1 needs the HD header beside it)"));
    std::fs::write(dir.path().join("line.Hd"), hd_text(1, 2, "m")).expect("write hd");
    let (hd, r) = read_dt1(&dt1).expect("found line.Hd");
    assert_eq!((hd.number_of_traces, r.traces.len()), (1, 1));
}

// ---------------------------------------------------------------------------------------------
// CMU-GPR

#[test]
fn cmu_cells_that_are_not_numbers_name_line_column_and_header() {
    let rows: Vec<(i64, Vec<i16>)> = (0..20).map(|i| (i * 20_000_000, vec![0; 201])).collect();
    let mut text = gpr_csv(&rows, 201);
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let mut cells: Vec<&str> = lines[16].split(',').collect();
    cells[4] = "x1";
    lines[16] = cells.join(",");
    text = lines.join("\n") + "\n";
    let e = parse_gpr_csv(&text, Path::new(GPR)).expect_err("x1");
    assert_eq!(message(&e), r#"gpr_meas.csv:17: column 5 (amp_4): not a number: "x1""#);

    let text = "t,amp_1\n1.0,40000\n";
    let e = parse_gpr_csv(text, Path::new(GPR)).expect_err("out of int16");
    assert_eq!(
        message(&e),
        r#"gpr_meas.csv:2: column 2 (amp_1): "40000": not a whole count in -32768..=32767"#
    );
    let e = parse_wheel_csv("t,dist\n1.0,0.5\n2.0,--3\n", Path::new("w.csv")).expect_err("--3");
    assert_eq!(message(&e), r#"w.csv:3: column 2 (dist): not a number: "--3""#);
}

#[test]
fn cmu_rows_with_the_wrong_cell_count_are_refused_unless_cut_at_the_end() {
    let text = "t,amp_1,amp_2\n1.0,1,2\n2.0,1\n3.0,1,2\n";
    let e = parse_gpr_csv(text, Path::new(GPR)).expect_err("short row");
    assert_eq!(message(&e), "gpr_meas.csv:3: 2 columns, the header row has 3");

    let text = "t,amp_1,amp_2\n1.0,1,2\n2.0,1";
    let r = parse_gpr_csv(text, Path::new(GPR)).expect("the cut last line is dropped");
    assert_eq!(r.traces.len(), 1);
    assert_eq!(
        r.dropped[0].to_string(),
        "gpr_meas.csv:3: truncated last line: 2 of 3 columns"
    );

    let e = parse_imu_csv("t,ax\n1.0,2.0\n", Path::new("imu.csv")).expect_err("2 of 11");
    assert_eq!(message(&e), "imu.csv:1: 2 columns, the header row has 11");
    let e = parse_gpr_csv("t\n1.0\n", Path::new(GPR)).expect_err("no amplitudes");
    assert_eq!(message(&e), "gpr_meas.csv:1: columns: 1: no amplitude columns after t");
    let e = parse_gpr_csv(" \n\n", Path::new(GPR)).expect_err("empty");
    assert_eq!(message(&e), "gpr_meas.csv: empty");
}

#[test]
fn cmu_non_finite_and_out_of_order_rows_are_dropped_and_counted() {
    let text = "t,dist\n\
                1.0,0.0\n\
                2.0,NaN\n\
                3.0,0.2\n\
                3.0,0.3\n\
                2.5,0.4\n\
                inf,0.5\n\
                4.0,inf\n\
                5.0,0.6\n";
    let (rows, dropped) = parse_wheel_csv(text, Path::new("we_odom_meas.csv")).expect("parses");
    let stamps: Vec<i64> = rows.iter().map(|r| r.stamp_ns).collect();
    assert_eq!(stamps, [1_000_000_000, 3_000_000_000, 5_000_000_000]);
    let reports: Vec<String> = dropped.iter().map(ToString::to_string).collect();
    assert_eq!(
        reports,
        [
            "we_odom_meas.csv:3: column 2 (dist): not finite",
            "we_odom_meas.csv:5: stamp repeated: 3000000000 ns after 3000000000 ns",
            "we_odom_meas.csv:6: stamp goes backwards: 2500000000 ns after 3000000000 ns",
            "we_odom_meas.csv:7: column 1 (t): not finite",
            "we_odom_meas.csv:8: column 2 (dist): not finite",
        ]
    );
}

#[test]
fn cmu_accepts_crlf_blanks_and_a_missing_header_row() {
    let text = "t , amp_1 , amp_2\r\n\r\n 1.5 , 3 , -4 \r\n2.5,5.0,6\r\n";
    let r = parse_gpr_csv(text, Path::new(GPR)).expect("lenient layout");
    assert_eq!(r.traces.len(), 2);
    assert_eq!(r.traces[0].stamp_ns, Some(1_500_000_000));
    assert_eq!(r.traces[1].samples, RawSamples::I16(vec![5, 6]));
    let (rows, _) = parse_truth_csv("1.0,1,2,3\n2.0,4,5,6\n", Path::new("ts.csv")).expect("no header");
    assert_eq!(rows[1].position_m, [4.0, 5.0, 6.0]);
}

#[test]
fn cmu_folder_reads_with_and_without_its_optional_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let e = read_cmu_sequence(dir.path()).expect_err("empty folder");
    assert!(message(&e).ends_with("gpr_meas.csv: not found (a CMU-GPR sequence needs its radar traces)"));

    let rows: Vec<(i64, Vec<i16>)> = (0..3)
        .map(|i| (1_600_000_000_000_000_000 + i * 20_000_000, vec![i as i16; 201]))
        .collect();
    std::fs::write(dir.path().join(cmu::GPR_FILE), gpr_csv(&rows, 201)).expect("write gpr");
    let e = read_cmu_sequence(dir.path()).expect_err("no wheel");
    assert!(message(&e).ends_with("we_odom_meas.csv: not found (a CMU-GPR sequence needs its wheel odometry)"));

    let wheel = [
        (1_600_000_000_000_000_000, vec![0.0]),
        (1_600_000_000_000_000_000, vec![0.1]),
    ];
    std::fs::write(dir.path().join(cmu::WHEEL_FILE), table_csv("t,dist", &wheel)).expect("write wheel");
    let s = read_cmu_sequence(dir.path()).expect("gpr and wheel suffice");
    assert_eq!(s.gpr.traces.len(), 3);
    assert_eq!(s.gpr.samples_per_trace, 201);
    assert_eq!(s.gpr.sample_interval_ns, CMU_SAMPLE_INTERVAL_NS);
    assert_eq!(s.gpr.traces[2].stamp_ns, Some(1_600_000_000_040_000_000));
    assert!(s.imu.is_none() && s.truth.is_none());
    assert_eq!(s.wheel.len(), 1);
    assert_eq!(s.all_dropped().count(), 1, "the repeated wheel stamp");

    let imu = [(1, vec![0.0, 0.0, 9.81, 0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])];
    std::fs::write(
        dir.path().join(cmu::IMU_FILE),
        table_csv("t,ax,ay,az,gx,gy,gz,qw,qx,qy,qz", &imu),
    )
    .expect("write imu");
    std::fs::write(dir.path().join(cmu::TRUTH_FILE), "t,px,py,pz\n").expect("write ts");
    let s = read_cmu_sequence(dir.path()).expect("all four");
    let imu = s.imu.expect("imu present");
    assert_eq!(imu[0].accel_mps2, [0.0, 0.0, 9.81]);
    assert_eq!(imu[0].gyro_radps[2], 0.1);
    assert_eq!(imu[0].orientation_wxyz, [1.0, 0.0, 0.0, 0.0]);
    assert_eq!(s.truth, Some(vec![]), "present but empty");
}

// ---------------------------------------------------------------------------------------------
// Properties

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn dzt_garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..3000)) {
        let _ = parse_dzt(&bytes, Path::new(DZT));
    }

    #[test]
    fn dzt_headers_with_random_fields_never_panic(
        fields in prop::collection::vec((0_usize..128, any::<u8>()), 1..12),
        data_len in 0_usize..5000,
    ) {
        let mut bytes = DztSpec::default().file(&vec![0x55; data_len]);
        for (at, value) in fields {
            bytes[at] = value;
        }
        if let Ok((header, r)) = parse_dzt(&bytes, Path::new(DZT)) {
            for t in &r.traces {
                prop_assert_eq!(t.samples.len(), usize::from(header.samples_per_trace));
            }
            prop_assert!(r.dropped.len() <= 1);
        }
    }

    #[test]
    fn dt1_garbage_never_panics(
        hd in "[A-Z /=0-9.\r\n-]{0,300}",
        bytes in prop::collection::vec(any::<u8>(), 0..2000),
    ) {
        if let Ok(hd) = parse_hd(&hd, Path::new(HD)) {
            let _ = parse_dt1(hd, Path::new(HD), &bytes, Path::new(DT1));
        }
        let _ = parse_test_dt1(&hd_text(3, 8, "ft"), &bytes);
    }

    #[test]
    fn csv_garbage_never_panics(text in "[-t0-9.,eE naifNA\r\n]{0,400}") {
        let _ = parse_gpr_csv(&text, Path::new(GPR));
        let _ = parse_imu_csv(&text, Path::new("imu.csv"));
        let _ = parse_wheel_csv(&text, Path::new("wheel.csv"));
        let _ = parse_truth_csv(&text, Path::new("ts.csv"));
    }

    #[test]
    fn dzt_round_trips(
        bits in prop::sample::select(vec![8_u16, 16, 32]),
        channels in 1_u16..4,
        samples in 1_u16..16,
        scans in 0_usize..12,
        seed in any::<u64>(),
    ) {
        let spec = DztSpec { bits, channels, samples, ..DztSpec::default() };
        let (lo, hi) = match bits { 8 => (-128_i64, 127), 16 => (-32768, 32767), _ => (i64::from(i32::MIN), i64::from(i32::MAX)) };
        let count = scans * usize::from(channels) * usize::from(samples);
        let values: Vec<i32> = (0..count as u64)
            .map(|i| {
                let x = seed.wrapping_add(i).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 16;
                (lo + (x as i64).rem_euclid(hi - lo + 1)) as i32
            })
            .collect();
        let (_, r) = parse_dzt(&spec.file(&spec.encode(&values)), Path::new(DZT)).expect("valid");
        let read: Vec<i32> = r.traces.iter().flat_map(|t| (0..t.samples.len()).filter_map(|i| t.samples.get(i))).collect();
        prop_assert_eq!(read, values);
        prop_assert!(r.dropped.is_empty());
    }

    #[test]
    fn cmu_csv_round_trips(
        deltas in prop::collection::vec(1_i64..50_000_000_000, 0..20),
        start in -1_000_000_000_000_000_000_i64..2_000_000_000_000_000_000,
        samples in 1_usize..8,
        values in prop::collection::vec(any::<i16>(), 8),
        reals in prop::collection::vec(-1e6_f64..1e6, 10),
    ) {
        let stamps: Vec<i64> = deltas.iter().scan(start, |t, d| { *t += d; Some(*t) }).collect();
        let gpr: Vec<(i64, Vec<i16>)> = stamps.iter().map(|&s| (s, values[..samples].to_vec())).collect();
        let r = parse_gpr_csv(&gpr_csv(&gpr, samples), Path::new(GPR)).expect("written by us");
        prop_assert_eq!(r.samples_per_trace, samples);
        let read: Vec<(i64, Vec<i16>)> = r.traces.iter().map(|t| {
            let RawSamples::I16(v) = &t.samples else { unreachable!("int16 CSV") };
            (t.stamp_ns.unwrap_or(i64::MIN), v.clone())
        }).collect();
        prop_assert_eq!(read, gpr);

        let imu: Vec<(i64, Vec<f64>)> = stamps.iter().map(|&s| (s, reals.clone())).collect();
        let (rows, dropped) = parse_imu_csv(&table_csv("t,ax,ay,az,gx,gy,gz,qw,qx,qy,qz", &imu), Path::new("imu.csv")).expect("ours");
        prop_assert!(dropped.is_empty());
        prop_assert_eq!(rows.len(), stamps.len());
        for (row, &stamp) in rows.iter().zip(&stamps) {
            prop_assert_eq!(row.stamp_ns, stamp);
            prop_assert_eq!(row.accel_mps2.to_vec(), reals[0..3].to_vec());
            prop_assert_eq!(row.gyro_radps.to_vec(), reals[3..6].to_vec());
            prop_assert_eq!(row.orientation_wxyz.to_vec(), reals[6..10].to_vec());
        }
        let wheel: Vec<(i64, Vec<f64>)> = stamps.iter().map(|&s| (s, vec![reals[0]])).collect();
        let (rows, _) = parse_wheel_csv(&table_csv("t,dist", &wheel), Path::new("w.csv")).expect("ours");
        prop_assert!(rows.iter().all(|r| r.distance_m == reals[0]));
        let truth: Vec<(i64, Vec<f64>)> = stamps.iter().map(|&s| (s, reals[..3].to_vec())).collect();
        let (rows, _) = parse_truth_csv(&table_csv("t,px,py,pz", &truth), Path::new("ts.csv")).expect("ours");
        prop_assert_eq!(rows.len(), stamps.len());
    }
}

#[test]
fn a_streamed_dzt_gives_what_the_whole_file_gives_cut_off_or_not() {
    use gprflow_ingest::SourceFormat;
    use gprflow_ingest::load::{LoadOptions, RadarMessages};
    let dir = tempfile::tempdir().expect("tempdir");
    // two channels in survey-wheel mode (a wheel message per scan), 16 bits, 50 scans
    let spec = DztSpec {
        channels: 2,
        scans_per_metre: 20.0,
        ..DztSpec::default()
    };
    let data: Vec<u8> = (0..50)
        .flat_map(|scan| spec.encode(&(0..8).map(|i| scan * 10 + i - 40).collect::<Vec<_>>()))
        .collect();
    let file = spec.file(&data);
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/real-gpr/GSSI_FILE____032.DZT");
    let real_bytes = std::fs::read(&real).expect("the real DZT");
    let options = LoadOptions {
        wheel_scale: 1.01,
        ..LoadOptions::default()
    };
    for (name, bytes) in [
        ("whole.DZT", file.clone()),
        // cut inside scan 37: 37 complete scans, the cut one reported
        ("cut.DZT", file[..file.len() - 13 * 16 - 5].to_vec()),
        ("real.DZT", real_bytes.clone()),
        ("real-cut.DZT", real_bytes[..real_bytes.len() / 2 + 3].to_vec()),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, &bytes).expect("write");
        let whole = streams_like_the_whole_file(&path, SourceFormat::Dzt, &options, name.contains("cut"));
        // a start found by seeking: the stream begins there, with what the whole file has from there
        for start_s in [0.0, 0.013, 0.2, 0.5] {
            let start_ns = (start_s * 1e9_f64).round() as i64;
            let from: Vec<_> = whole.messages.iter().filter(|m| m.1 >= start_ns).cloned().collect();
            let sought: Vec<_> = RadarMessages::open(&path, SourceFormat::Dzt, &options, Some(start_s))
                .expect("seeks")
                .collect();
            assert!(
                sought == from,
                "{name}: from {start_s} s, {} vs {} messages",
                sought.len(),
                from.len()
            );
        }
    }
}

/// Checks that `path` streamed gives the messages the whole-file reader gives, in the same
/// order, and that a cut file reports its cut record; returns the whole-file reading.
fn streams_like_the_whole_file(
    path: &Path,
    format: gprflow_ingest::SourceFormat,
    options: &gprflow_ingest::load::LoadOptions,
    cut: bool,
) -> gprflow_ingest::load::Loaded {
    use gprflow_ingest::load::{RadarMessages, load};
    let name = path.display();
    let whole = load(path, format, options).expect("loads");
    let streamed: Vec<_> = RadarMessages::open(path, format, options, None)
        .expect("opens")
        .collect();
    assert!(!whole.messages.is_empty(), "{name}");
    assert!(
        whole.messages == streamed,
        "{name}: the stream gives the same messages in the same order"
    );
    assert_eq!(
        whole.dropped.iter().any(|d| d.contains("truncated")),
        cut,
        "{name}: {:?}",
        whole.dropped
    );
    whole
}

#[test]
fn a_streamed_dt1_gives_what_the_whole_file_gives_cut_off_or_not() {
    use gprflow_ingest::SourceFormat;
    use gprflow_ingest::load::LoadOptions;
    let dir = tempfile::tempdir().expect("tempdir");
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/real-gpr");
    let options = LoadOptions::default();
    for stem in ["SnS_ComOffs_XLINE00", "SnS_WARR_XLINE00"] {
        let bytes = std::fs::read(real.join(format!("{stem}.DT1"))).expect("the real DT1");
        let hd = std::fs::read(real.join(format!("{stem}.HD"))).expect("its HD");
        for (name, cut) in [
            (stem.to_owned(), bytes.len()),
            (format!("{stem}-cut"), bytes.len() * 2 / 3 + 7),
        ] {
            std::fs::write(dir.path().join(format!("{name}.DT1")), &bytes[..cut]).expect("write");
            std::fs::write(dir.path().join(format!("{name}.HD")), &hd).expect("write");
            let path = dir.path().join(format!("{name}.DT1"));
            streams_like_the_whole_file(&path, SourceFormat::Dt1, &options, cut < bytes.len());
        }
    }
}

/// Stamp of a written CMU-GPR folder's first row (ns).
const CMU_T0_NS: i64 = 1_600_000_000_000_000_000;

/// Writes a CMU-GPR folder as the simulator writes one (headers, stamps with nine decimals),
/// 4 s at the rig's rates: radar 50 Hz x 64 samples, wheel 100 Hz, IMU 200 Hz, total station
/// 10 Hz, so that every radar stamp is also a wheel and an IMU stamp and every total-station
/// stamp is all four. With what the reader skips: a NaN wheel row, a repeated IMU stamp, and
/// CRLF line ends and a blank line in the total-station file. Returns the text of
/// `gpr_meas.csv`.
fn write_cmu_folder(dir: &Path) -> String {
    std::fs::create_dir_all(dir).expect("folder");
    let at = |period_ms: i64, i: i64| CMU_T0_NS + i * period_ms * 1_000_000;
    let gpr: Vec<(i64, Vec<i16>)> = (0..200)
        .map(|i| {
            let amps = (0..64).map(|s| ((i * 37 + s * 101) % 2000 - 1000) as i16).collect();
            (at(20, i), amps)
        })
        .collect();
    let mut wheel: Vec<(i64, Vec<f64>)> = (0..400).map(|i| (at(10, i), vec![0.005 * i as f64])).collect();
    wheel[150].1[0] = f64::NAN;
    let mut imu: Vec<(i64, Vec<f64>)> = (0..800)
        .map(|i| {
            let x = i as f64 * 1e-3;
            (at(5, i), vec![x, -x, 9.81, 0.01, 0.02, x, 1.0, 0.0, 0.0, 0.0])
        })
        .collect();
    imu.insert(300, imu[299].clone());
    let truth: Vec<(i64, Vec<f64>)> = (0..40).map(|i| (at(100, i), vec![0.05 * i as f64, 1.0, 0.0])).collect();
    let gpr_text = gpr_csv(&gpr, 64);
    let truth_text = table_csv("t,px,py,pz", &truth).replace('\n', "\r\n") + "\r\n";
    for (name, text) in [
        (cmu::GPR_FILE, gpr_text.clone()),
        (cmu::WHEEL_FILE, table_csv("t,dist", &wheel)),
        (cmu::IMU_FILE, table_csv("t,ax,ay,az,gx,gy,gz,qw,qx,qy,qz", &imu)),
        (cmu::TRUTH_FILE, truth_text),
    ] {
        std::fs::write(dir.join(name), text).expect("write");
    }
    gpr_text
}

#[test]
fn a_streamed_cmu_sequence_gives_what_the_whole_folder_gives_cut_off_or_not() {
    use gprflow_ingest::SourceFormat;
    use gprflow_ingest::load::{LoadOptions, Port, RadarMessages};
    let dir = tempfile::tempdir().expect("tempdir");
    let whole = dir.path().join("sequence");
    let gpr_text = write_cmu_folder(&whole);
    // a copy whose gpr_meas.csv stops in the middle of line 121
    let cut = dir.path().join("sequence-cut");
    write_cmu_folder(&cut);
    let line_start: usize = gpr_text.lines().take(120).map(|l| l.len() + 1).sum();
    let line_len = gpr_text[line_start..].find('\n').expect("line 121 ends");
    std::fs::write(cut.join(cmu::GPR_FILE), &gpr_text[..line_start + line_len / 2]).expect("cut");
    for wheel_scale in [1.0, 0.98] {
        let options = LoadOptions {
            wheel_scale,
            ..LoadOptions::default()
        };
        for (path, traces) in [(&whole, 200), (&cut, 119)] {
            let is_cut = path == &cut;
            let loaded = streams_like_the_whole_file(path, SourceFormat::CmuGpr, &options, is_cut);
            let name = path.display();
            // a NaN wheel row and a repeated IMU stamp skipped
            let count = |port| loaded.messages.iter().filter(|m| m.0 == port).count();
            let counts = [Port::Gpr, Port::Wheel, Port::Imu, Port::Truth].map(count);
            assert_eq!(counts, [traces, 399, 800, 40], "{name}");
            assert_eq!(
                loaded.dropped.len(),
                2 + usize::from(is_cut),
                "{name}: {:?}",
                loaded.dropped
            );
            // on an equal stamp: radar, wheel, IMU, total station, as the files are listed
            let first: Vec<Port> = loaded
                .messages
                .iter()
                .take_while(|m| m.1 == CMU_T0_NS)
                .map(|m| m.0)
                .collect();
            assert_eq!(first, [Port::Gpr, Port::Wheel, Port::Imu, Port::Truth], "{name}");
            let stream = RadarMessages::open(path, SourceFormat::CmuGpr, &options, None).expect("opens");
            assert_eq!(stream.total, Some(loaded.messages.len()), "{name}: counted at open");
        }
    }
}

#[test]
fn a_cmu_folder_with_a_bad_cell_is_refused_at_open_naming_file_line_and_field() {
    use gprflow_ingest::SourceFormat;
    use gprflow_ingest::load::{LoadOptions, RadarMessages};
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = dir.path().join("sequence");
    write_cmu_folder(&folder);
    let replace_cell = |file: &str, line: usize, column: usize, cell: &str| {
        let path = folder.join(file);
        let text = std::fs::read_to_string(&path).expect("read");
        let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
        let mut cells: Vec<&str> = lines[line - 1].split(',').collect();
        if cell.is_empty() {
            cells.remove(column - 1);
        } else {
            cells[column - 1] = cell;
        }
        lines[line - 1] = cells.join(",");
        std::fs::write(&path, lines.join("\n") + "\n").expect("write");
        text
    };
    let refused = |want: String| {
        let e = RadarMessages::open(&folder, SourceFormat::CmuGpr, &LoadOptions::default(), None)
            .expect_err("refused at open, before the first message");
        assert_eq!(message(&e), want);
        let whole = read_cmu_sequence(&folder).expect_err("refused read whole");
        assert_eq!(message(&whole), want, "as the whole-folder reader refuses it");
    };
    // a bad cell in the middle of imu_meas.csv (tens of kilobytes in), an amplitude out of
    // int16, a short row: each names the file, line and field
    for (file, line, column, cell, want) in [
        (
            cmu::IMU_FILE,
            401,
            4,
            "9.81x",
            r#":401: column 4 (az): not a number: "9.81x""#,
        ),
        (
            cmu::GPR_FILE,
            101,
            3,
            "40000",
            r#":101: column 3 (amp_2): "40000": not a whole count in -32768..=32767"#,
        ),
        (cmu::WHEEL_FILE, 200, 2, "", ":200: 1 columns, the header row has 2"),
    ] {
        let original = replace_cell(file, line, column, cell);
        refused(format!("{}{want}", folder.join(file).display()));
        std::fs::write(folder.join(file), original).expect("restore");
    }
    let wheel = folder.join(cmu::WHEEL_FILE);
    std::fs::remove_file(&wheel).expect("remove");
    refused(format!(
        "{}: not found (a CMU-GPR sequence needs its wheel odometry)",
        wheel.display()
    ));
}
