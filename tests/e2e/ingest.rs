//! Radar files in: the CMU-GPR folder, the real DZT and DT1 files in `recordings/real-gpr`
//! converted to MCAP, and the clear errors bad files get.

use std::path::PathBuf;

use crate::common::{gprflow, repo, stderr};
use crate::{decode_all, payloads, peer_check};

#[test]
fn a_cmu_gpr_folder_ingests_as_the_recording_it_was_written_with() {
    use gprflow::msg::{Imu, Trace, WheelOdometry};
    let dir = tempfile::tempdir().expect("tempdir");
    let sim = dir.path().join("basement.mcap");
    let o = gprflow(&[
        "sim",
        "tools/sim/scenarios/basement.yaml",
        "-o",
        sim.to_str().expect("utf8"),
        "--format",
        "cmu-gpr",
        "--duration",
        "4",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let folder = dir.path().join("basement");
    let conv = dir.path().join("converted.mcap");
    let o = gprflow(&[
        "convert",
        folder.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        conv.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, b) = (payloads(&sim), payloads(&conv));
    let (ta, tb): (Vec<Trace>, Vec<Trace>) = (decode_all(&a["/gpr/trace"]), decode_all(&b["/gpr/trace"]));
    assert_eq!(ta.len(), tb.len());
    assert!(ta.len() > 150);
    for (x, y) in ta.iter().zip(&tb) {
        assert_eq!(x.header.stamp, y.header.stamp);
        assert_eq!(x.samples_i16, y.samples_i16);
        assert_eq!(x.sample_interval_ns, y.sample_interval_ns);
    }
    let (wa, wb): (Vec<WheelOdometry>, Vec<WheelOdometry>) =
        (decode_all(&a["/wheel/odometry"]), decode_all(&b["/wheel/odometry"]));
    assert_eq!(wa.len(), wb.len());
    for (x, y) in wa.iter().zip(&wb) {
        assert_eq!(x.header.stamp, y.header.stamp);
        // the CSV holds 6 decimals
        assert!((x.distance_m - y.distance_m).abs() <= 5e-7 + 1e-12);
    }
    let (ia, ib): (Vec<Imu>, Vec<Imu>) = (decode_all(&a["/imu/data"]), decode_all(&b["/imu/data"]));
    assert_eq!(ia.len(), ib.len());
    for (x, y) in ia.iter().zip(&ib) {
        assert_eq!(x.header.stamp, y.header.stamp);
        // 7 decimals
        let close = |p: f64, q: f64| (p - q).abs() <= 5e-8 + 1e-12;
        assert!(close(x.angular_velocity.z, y.angular_velocity.z));
        assert!(close(x.linear_acceleration.x, y.linear_acceleration.x));
        assert!(close(x.linear_acceleration.z, y.linear_acceleration.z));
    }
}

/// The real radar files committed in `recordings/real-gpr`.
pub(crate) fn real_gpr(file: &str) -> PathBuf {
    let dir = repo().join("recordings/real-gpr");
    assert!(
        dir.is_dir(),
        "{} is missing: the tests read the real radar files there",
        dir.display()
    );
    dir.join(file)
}

#[test]
fn real_radar_files_convert_and_the_python_reader_agrees() {
    use gprflow::msg::{Trace, WheelOdometry};
    let dir = tempfile::tempdir().expect("tempdir");
    // file, traces, samples, sample interval ns, metres between traces
    let cases = [
        ("GSSI_FILE____032.DZT", 1040, 512, 48.0 / 512.0, 1.0 / 50.0),
        ("SnS_ComOffs_XLINE00.DT1", 531, 1500, 0.8, f64::NAN),
        ("SnS_WARR_XLINE00.DT1", 164, 1900, 0.4, f64::NAN),
    ];
    for (file, traces, samples, dt, spacing) in cases {
        let out = dir.path().join(format!("{file}.mcap"));
        let o = gprflow(&[
            "convert",
            real_gpr(file).to_str().expect("utf8"),
            "--to",
            "mcap",
            "-o",
            out.to_str().expect("utf8"),
        ]);
        assert!(o.status.success(), "{file}: {}", stderr(&o));
        let p = payloads(&out);
        let t: Vec<Trace> = decode_all(&p["/gpr/trace"]);
        assert_eq!(t.len(), traces, "{file}");
        assert!(t.iter().all(|t| t.len() == samples), "{file}");
        assert!(
            (t[0].sample_interval_ns - dt).abs() < 1e-9,
            "{file}: {}",
            t[0].sample_interval_ns
        );
        let w: Vec<WheelOdometry> = decode_all(&p["/wheel/odometry"]);
        assert_eq!(w.len(), traces, "{file}: a distance per trace");
        if spacing.is_finite() {
            let step = w[1].distance_m - w[0].distance_m;
            assert!((step - spacing).abs() < 1e-6, "{file}: {step}");
        }
        peer_check(&out, &format!("{} messages", 2 * traces));
    }
}

#[test]
fn bad_radar_files_get_clear_errors_and_lose_no_complete_trace() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bytes = std::fs::read(real_gpr("GSSI_FILE____032.DZT")).expect("dzt");
    // cut inside the last trace: every complete trace is kept, the cut one reported
    let cut = dir.path().join("cut.DZT");
    std::fs::write(&cut, &bytes[..bytes.len() - 300]).expect("write");
    let out = dir.path().join("cut.mcap");
    let o = gprflow(&[
        "convert",
        cut.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("1039 messages"), "{text}");
    assert!(text.contains("cut.DZT: trace 1039: truncated"), "{text}");
    // a header that says 12-bit samples: refused, naming the file and field
    let mut bad = bytes.clone();
    bad[6] = 12;
    bad[7] = 0;
    let badf = dir.path().join("bits.DZT");
    std::fs::write(&badf, &bad).expect("write");
    let o = gprflow(&[
        "convert",
        badf.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("bits.DZT: header: rh_bits: 12"), "{}", stderr(&o));
    // a DT1 without its HD
    let dt1 = dir.path().join("line.DT1");
    std::fs::copy(real_gpr("SnS_WARR_XLINE00.DT1"), &dt1).expect("copy");
    let o = gprflow(&[
        "convert",
        dt1.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("line.HD: not found"), "{}", stderr(&o));
    // the same errors stop a launched ingest stage with the file named
    let o = gprflow(&[
        "launch",
        "graphs/submaps.yaml",
        "--set",
        &format!("recording={}", badf.display()),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("bits.DZT: header: rh_bits: 12"), "{}", stderr(&o));
    // a CMU-GPR row with NaN is dropped and reported with file and line
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).expect("mkdir");
    let row = |t: &str, v: &str| format!("{t},{}\n", [v; 4].join(","));
    let gpr = format!(
        "t,amp_1,amp_2,amp_3,amp_4\n{}{}{}",
        row("1.00", "5"),
        row("1.02", "nan"),
        row("1.04", "7")
    );
    std::fs::write(seq.join("gpr_meas.csv"), gpr).expect("write");
    std::fs::write(seq.join("we_odom_meas.csv"), "t,dist\n1.0,0.0\n1.1,0.05\n").expect("write");
    let o = gprflow(&[
        "convert",
        seq.to_str().expect("utf8"),
        "--to",
        "mcap",
        "-o",
        out.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("/gpr/trace                   2 messages"), "{text}");
    assert!(text.contains("gpr_meas.csv:3"), "{text}");
}
