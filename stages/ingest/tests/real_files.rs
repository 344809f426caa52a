//! The readers on files written by real instruments (GPRPy's example data, committed in
//! `recordings/real-gpr`). Header values are those the data README lists; sample values were
//! read independently with Python's `struct`, the snippet beside each test.

use std::path::{Path, PathBuf};

use gprflow_ingest::RawSamples;
use gprflow_ingest::dt1::{read_dt1, read_dt1_line};
use gprflow_ingest::dzt::read_dzt;
use gprflow_ingest::radargram::Format;

/// Float header values compare to this (they are f32 in the files).
const TOLERANCE: f64 = 1e-6;

fn data_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/real-gpr");
    assert!(
        dir.is_dir(),
        "the real GPR files are missing: expected the folder {}",
        dir.display()
    );
    dir
}

fn i16_samples(samples: &RawSamples) -> &[i16] {
    match samples {
        RawSamples::I16(v) => v,
        RawSamples::I32(_) => panic!("expected 16-bit samples"),
    }
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= TOLERANCE * b.abs().max(1.0)
}

/// ```python
/// import struct
/// b = open('GSSI_FILE____032.DZT', 'rb').read()
/// print(struct.unpack_from('<4Hh5fH', b, 0))   # (1792, 1024, 512, 16, 0, 100.0, 50.0, 0.5, 0.0, 48.0, 0)
/// print(struct.unpack_from('<7H3f', b, 40))    # (0, 0, 512, 0, 128, 33, 1, 6.0, -0.2939..., 2.9393...)
/// print(b[98:112], b[113], b[114:126])          # b'400MHz\0...' 25 b'FILE____032\0'
/// trace = lambda i: [x - 32768 for x in struct.unpack_from('<512H', b, 1024 + i * 1024)]
/// print(trace(0)[:8])                           # [-32768, -7168, -1, -1, 0, -1, -1, -1]
/// t = trace(520); print(t[:2], max(t), t.index(max(t)))   # [-32248, -32768] 7503 59
/// print([i for i in range(1040) if trace(i)[1] != -32768])  # [0, 100, 200, ..., 1000]
/// ```
#[test]
fn gssi_dzt_reads_as_the_instrument_wrote_it() {
    let path = data_dir().join("GSSI_FILE____032.DZT");
    let (header, radargram) = read_dzt(&path).expect("the real DZT reads");

    assert_eq!(header.tag, 0x0700, "this file's tag is not the documented 0x00ff");
    assert_eq!(header.data_field, 1024);
    assert_eq!(header.data_offset_bytes(), 1024);
    assert_eq!(header.samples_per_trace, 512);
    assert_eq!(header.bits_per_sample, 16);
    assert_eq!(header.scans_per_second, 100.0);
    assert_eq!(header.scans_per_metre, 50.0);
    assert_eq!(header.metres_per_mark, 0.5);
    assert_eq!(header.range_ns, 48.0);
    assert_eq!(header.position_ns, 0.0);
    assert_eq!(header.channels, 1);
    assert_eq!(header.relative_permittivity, 6.0);
    assert!(close(f64::from(header.depth_m), 2.939_387_559_890_747));
    assert_eq!(header.antenna_name, "400MHz");
    assert_eq!(header.initial_name, "FILE____032");
    assert_eq!((header.version, header.system), (1, 3));
    assert_eq!((header.processing_offset, header.processing_size), (128, 33));
    assert_eq!((header.text_offset, header.text_size), (512, 0));
    let c = header.created;
    assert_eq!(
        (c.year, c.month, c.day, c.hour, c.minute, c.second),
        (2017, 3, 21, 0, 36, 46)
    );
    let m = header.modified;
    assert_eq!((m.year, m.month, m.day, m.minute, m.second), (2017, 3, 21, 38, 6));

    assert_eq!(radargram.format, Format::Dzt);
    assert_eq!(radargram.source, path);
    assert_eq!(radargram.channels, 1);
    assert_eq!(radargram.samples_per_trace, 512);
    assert_eq!(radargram.traces.len(), 1040);
    assert!(radargram.dropped.is_empty());
    assert!(close(radargram.sample_interval_ns, 48.0 / 512.0));
    assert_eq!(radargram.time_zero_ns, 0.0);
    assert_eq!(radargram.center_frequency_hz, 400e6);
    for trace in &radargram.traces {
        assert_eq!(trace.samples.len(), 512);
        assert_eq!(trace.channel, 0);
        assert_eq!(trace.stamp_ns, None, "wheel mode: no clock");
    }
    assert!(close(radargram.traces[520].distance_m, 10.4));
    assert!(close(radargram.traces[1039].distance_m, 1039.0 / 50.0));

    let first = i16_samples(&radargram.traces[0].samples);
    assert_eq!(first[..8], [-32768, -7168, -1, -1, 0, -1, -1, -1]);
    let mid = i16_samples(&radargram.traces[520].samples);
    assert_eq!(mid[..2], [-32248, -32768], "sample 0 counts scans");
    let (argmax, max) = mid.iter().enumerate().max_by_key(|(_, s)| **s).expect("512 samples");
    assert_eq!((argmax, *max), (59, 7503));
    let marked: Vec<usize> = radargram
        .traces
        .iter()
        .enumerate()
        .filter(|(_, t)| t.samples.get(1) != Some(-32768))
        .map(|(i, _)| i)
        .collect();
    assert_eq!(marked, (0..=1000).step_by(100).collect::<Vec<_>>());
}

/// ```python
/// import struct
/// b = open('SnS_ComOffs_XLINE00.DT1', 'rb').read(); rec = 128 + 2 * 1500
/// print(len(b) / rec)                                  # 531.0
/// print(struct.unpack_from('<8f', b, 0))               # (1.0, 0.0, 1500.0, 0.0, 0.0, 2.0, 800.0, 8.0)
/// print(struct.unpack_from('<f', b, 92))               # (38177.2265625,)
/// s = lambda i: struct.unpack_from('<1500h', b, i * rec + 128)
/// print(s(0)[:6])                                      # (-279, -286, -143, 557, 2158, 4301)
/// t = s(265); print(max(t), t.index(max(t)), min(t), t.index(min(t)))   # 12994 9 -24517 18
/// print(struct.unpack_from('<f', b, 530 * rec + 4))    # (1060.0,)
/// ```
#[test]
fn pulse_ekko_common_offset_line_reads_in_metres() {
    let path = data_dir().join("SnS_ComOffs_XLINE00.DT1");
    let line = read_dt1_line(&path).expect("the real DT1 reads");
    let hd = &line.hd;
    assert_eq!(line.hd_path, data_dir().join("SnS_ComOffs_XLINE00.HD"));
    assert_eq!(
        hd.text_lines,
        ["1234", "Data Collected with pE PRO (2011-00114-00)", "2017-04-10"]
    );
    assert_eq!(hd.number_of_traces, 531);
    assert_eq!(hd.points_per_trace, 1500);
    assert_eq!(hd.timezero_at_point, Some(3.18));
    assert_eq!(hd.total_time_window_ns, 1200.0);
    assert_eq!(hd.starting_position, Some(0.0));
    assert_eq!(hd.final_position, Some(1060.0));
    assert_eq!(hd.step_size, Some(2.0));
    assert_eq!(hd.position_units.as_deref(), Some("ft"));
    assert_eq!(hd.nominal_frequency_mhz, Some(50.0));
    assert_eq!(hd.antenna_separation, Some(3.0));
    assert_eq!(hd.pulser_voltage_v, Some(12.0));
    assert_eq!(hd.number_of_stacks, Some(8));
    assert_eq!(hd.survey_mode.as_deref(), Some("Reflection"));
    assert_eq!(
        hd.other.get("STACKING TYPE").map(String::as_str),
        Some("F1, P8, DynaQ OFF")
    );
    assert_eq!(
        hd.other.get("Start Tx Battery").map(String::as_str),
        Some("12.54V 12.50V")
    );

    let th = &line.trace_headers[0];
    assert_eq!(line.trace_headers.len(), 531);
    assert_eq!((th.trace_number, th.samples, th.bytes_per_sample), (1.0, 1500.0, 2.0));
    assert_eq!(th.time_window, 800.0, "the trace header's window is not the HD's");
    assert_eq!(th.stacks, 8.0);
    assert_eq!(th.time_of_day_s, 38177.227);

    let r = &line.radargram;
    assert_eq!(r.format, Format::Dt1);
    assert_eq!((r.traces.len(), r.samples_per_trace), (531, 1500));
    assert!(r.dropped.is_empty());
    assert!(close(r.sample_interval_ns, 0.8));
    assert!(close(r.time_zero_ns, -2.18 * 0.8));
    assert_eq!(r.center_frequency_hz, 50e6);
    assert!(close(r.traces[1].distance_m, 2.0 * 0.3048));
    assert!(close(r.traces[530].distance_m, 1060.0 * 0.3048));
    assert_eq!(r.traces[0].stamp_ns, Some(38_177_226_562_500));
    assert!(r.traces.iter().all(|t| t.samples.len() == 1500));
    let first = i16_samples(&r.traces[0].samples);
    assert_eq!(first[..6], [-279, -286, -143, 557, 2158, 4301]);
    let mid = i16_samples(&r.traces[265].samples);
    let max = mid.iter().copied().max();
    let min = mid.iter().copied().min();
    assert_eq!((max, min), (Some(12994), Some(-24517)));
    assert_eq!(mid.iter().position(|&s| s == 12994), Some(9));
    assert_eq!(mid.iter().position(|&s| s == -24517), Some(18));
}

/// ```python
/// import struct
/// b = open('SnS_WARR_XLINE00.DT1', 'rb').read(); rec = 128 + 2 * 1900
/// print(len(b) / rec)                                          # 164.0
/// print(struct.unpack_from('<8f', b, 0)[5:7])                  # (2.0, 400.0)
/// print([struct.unpack_from('<i', b, i * rec + 16)[0] for i in (1, 163)])   # [100, 16300]
/// s = lambda i: struct.unpack_from('<1900h', b, i * rec + 128)
/// print(s(0)[:4])                                              # (-13703, -15897, -20736, -25264)
/// t = s(82); print(max(t), t.index(max(t)), min(t), t.index(min(t)))   # 299 243 -450 352
/// ```
#[test]
fn pulse_ekko_warr_gather_reads() {
    let path = data_dir().join("SnS_WARR_XLINE00.DT1");
    let line = read_dt1_line(&path).expect("the real WARR DT1 reads");
    let hd = &line.hd;
    assert_eq!((hd.number_of_traces, hd.points_per_trace), (164, 1900));
    assert_eq!(hd.total_time_window_ns, 760.0);
    assert_eq!(hd.timezero_at_point, Some(34.07));
    assert_eq!(hd.position_units.as_deref(), Some("m"));
    assert_eq!(hd.nominal_frequency_mhz, Some(100.0));
    assert_eq!(hd.antenna_separation, Some(0.75));
    assert_eq!(hd.starting_position, Some(0.6));
    assert_eq!(
        hd.other.get("ODOMETER CAL (t/m)").map(String::as_str),
        Some("1000.000000")
    );
    assert_eq!(line.trace_headers[0].time_window, 400.0);
    assert_eq!(line.trace_headers[163].unused_16.to_bits(), 16300);

    let r = &line.radargram;
    assert_eq!((r.traces.len(), r.samples_per_trace), (164, 1900));
    assert!(close(r.sample_interval_ns, 0.4));
    assert!(close(r.time_zero_ns, -33.07 * 0.4));
    assert_eq!(r.center_frequency_hz, 100e6);
    assert_eq!(r.traces[0].distance_m, 0.0, "trace positions start at 0, not at 0.6");
    assert!(close(r.traces[163].distance_m, 16.3));
    let first = i16_samples(&r.traces[0].samples);
    assert_eq!(first[..4], [-13703, -15897, -20736, -25264]);
    let mid = i16_samples(&r.traces[82].samples);
    assert_eq!(mid.iter().copied().max(), Some(299));
    assert_eq!(mid.iter().position(|&s| s == 299), Some(243));
    assert_eq!(mid.iter().copied().min(), Some(-450));
    assert_eq!(mid.iter().position(|&s| s == -450), Some(352));

    let (hd_only, radargram) = read_dt1(&path).expect("the short form reads too");
    assert_eq!(&hd_only, hd);
    assert_eq!(&radargram, r);
}

mod never_panic {
    use super::*;
    use gprflow_ingest::dt1::{parse_dt1, parse_hd};
    use gprflow_ingest::dzt::parse_dzt;
    use proptest::prelude::*;

    fn real(name: &str) -> Vec<u8> {
        std::fs::read(data_dir().join(name)).expect("the real file reads")
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        /// A DZT cut anywhere: refused in the header, else the complete traces and at most one
        /// reported partial one.
        #[test]
        fn truncated_dzt_keeps_complete_traces(cut in 0_usize..1_065_984) {
            let bytes = real("GSSI_FILE____032.DZT");
            match parse_dzt(&bytes[..cut], Path::new("cut.DZT")) {
                Ok((_, r)) => {
                    prop_assert!(cut >= 1024);
                    prop_assert_eq!(r.traces.len(), (cut - 1024) / 1024);
                    prop_assert_eq!(r.dropped.len(), usize::from((cut - 1024) % 1024 != 0));
                    prop_assert!(r.traces.iter().all(|t| t.samples.len() == 512));
                }
                Err(e) => prop_assert!(cut < 1024, "{e}"),
            }
        }

        /// Random bytes written over the real DZT header never panic the reader.
        #[test]
        fn mangled_dzt_header_never_panics(
            edits in prop::collection::vec((0_usize..1024, any::<u8>()), 1..16),
        ) {
            let mut bytes = real("GSSI_FILE____032.DZT");
            for (at, value) in edits {
                bytes[at] = value;
            }
            let _ = parse_dzt(&bytes, Path::new("mangled.DZT"));
        }

        /// A DT1 cut anywhere against its real HD: never a panic; when it reads, every trace is
        /// complete and a cut trace is reported.
        #[test]
        fn truncated_dt1_never_panics(cut in 0_usize..1_660_968, which in any::<bool>()) {
            let (name, points) = if which {
                ("SnS_ComOffs_XLINE00", 1500)
            } else {
                ("SnS_WARR_XLINE00", 1900)
            };
            let hd_bytes = real(&format!("{name}.HD"));
            let hd = parse_hd(&String::from_utf8_lossy(&hd_bytes), Path::new("x.HD")).expect("real HD");
            let bytes = real(&format!("{name}.DT1"));
            let cut = cut.min(bytes.len());
            let record = 128 + 2 * points;
            match parse_dt1(hd, Path::new("x.HD"), &bytes[..cut], Path::new("cut.DT1")) {
                Ok(line) => {
                    prop_assert_eq!(line.radargram.traces.len(), cut / record);
                    prop_assert_eq!(line.radargram.dropped.len(), usize::from(cut % record != 0));
                }
                Err(e) => prop_assert!(cut % record == 0 && cut < bytes.len(), "{e}"),
            }
        }

        /// Random bytes written over the real DT1 trace headers and HD never panic the reader.
        #[test]
        fn mangled_dt1_never_panics(
            edits in prop::collection::vec((0_usize..644_192, any::<u8>()), 1..32),
            hd_edits in prop::collection::vec((0_usize..783, 0x20_u8..0x7f), 0..8),
        ) {
            let mut bytes = real("SnS_WARR_XLINE00.DT1");
            let mut hd = real("SnS_WARR_XLINE00.HD");
            for (at, value) in edits {
                // Mostly the trace headers, where the structure lives.
                let at = (at / 3928) * 3928 + at % 128;
                bytes[at] = value;
            }
            for (at, value) in hd_edits {
                hd[at] = value;
            }
            if let Ok(hd) = parse_hd(&String::from_utf8_lossy(&hd), Path::new("x.HD")) {
                let _ = parse_dt1(hd, Path::new("x.HD"), &bytes, Path::new("mangled.DT1"));
            }
        }
    }
}
