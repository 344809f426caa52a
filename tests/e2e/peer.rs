//! The Python peer MCAP reader (tools/peer/check_mcap.py) decodes every message type and
//! every field as `gprflow inspect` does.

use crate::{peer_check, record_toy};

#[test]
fn python_mcap_reader_decodes_every_message_type() {
    use gprflow::msg::*;
    use std::borrow::Cow;
    let h = |ns: i64| Header::new(ns, "base_link");
    let pose = Pose {
        position: Point {
            x: 1.5,
            y: -2.25,
            z: 0.125,
        },
        orientation: Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.38268343236,
            w: 0.92387953251,
        },
    };
    let mut cov = Covariance6::default();
    for (i, c) in cov.0.iter_mut().enumerate() {
        *c = i as f64 * 0.01;
    }
    let mut msgs: Vec<(&str, &str, Vec<u8>)> = vec![
        (
            "/t/trace",
            Trace::TYPE_NAME,
            encode(&Trace {
                header: h(1),
                samples_i16: Cow::Owned(vec![-3, 7, i16::MIN]),
                sample_interval_ns: 0.2,
                ..Trace::default()
            }),
        ),
        (
            "/t/trace32",
            Trace::TYPE_NAME,
            encode(&Trace {
                header: h(2),
                samples_i32: Cow::Owned(vec![i32::MAX, -1]),
                ..Trace::default()
            }),
        ),
        (
            "/t/sweep",
            Sweep::TYPE_NAME,
            encode(&Sweep {
                header: h(3),
                channel_count: 1,
                bin_count: 2,
                values: Cow::Owned(vec![0.5, -0.5, 1.0, 2.0]),
                calibration: Cow::Owned(vec![1.0, 0.0, 1.0, 0.0]),
                start_frequency_hz: 1e8,
                frequency_step_hz: 6e6,
                ..Sweep::default()
            }),
        ),
        (
            "/t/wheel",
            WheelOdometry::TYPE_NAME,
            encode(&WheelOdometry {
                header: h(4),
                distance_m: 12.5,
                ticks: -4096,
                speed_mps: 0.75,
            }),
        ),
        (
            "/t/submap",
            Submap::TYPE_NAME,
            encode(&Submap {
                header: h(5),
                id: 9,
                rows: 2,
                cols: 3,
                pixels: Cow::Owned(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]),
                start_pose: pose,
                end_pose: pose,
                saliency: 0.25,
                valid: true,
                start_stamp: Time::from_ns(-1_500_000_000),
                ..Submap::default()
            }),
        ),
        (
            "/t/registration",
            Registration::TYPE_NAME,
            encode(&Registration {
                header: h(6),
                reference_submap: 1,
                query_submap: 2,
                reference_from_query: pose,
                covariance: cov,
                along_track_m: 0.4,
                along_track_variance_m2: 0.01,
                score: 0.9,
                method: "learned".to_owned(),
                ..Registration::default()
            }),
        ),
        (
            "/t/line",
            LineObservation::TYPE_NAME,
            encode(&LineObservation {
                header: h(7),
                line_id: u32::MAX,
                forward_distance_m: 0.3,
                sigma_m: 0.05,
                apex_time_ns: 12.0,
                depth_m: 0.6,
                score: 0.5,
                submap_id: 4,
                along_distance_m: 12.5,
                apex_stamp: Time::from_ns(6),
                velocity_m_per_ns: 0.12,
            }),
        ),
        (
            "/t/linemap",
            LineMap::TYPE_NAME,
            encode(&LineMap {
                header: h(8),
                lines: vec![
                    HoughLine {
                        id: 1,
                        rho_m: 2.0,
                        theta_rad: 0.5,
                        covariance: [1.0, 0.1, 0.1, 2.0],
                    },
                    HoughLine::default(),
                ],
            }),
        ),
        (
            "/t/state",
            StateEstimate::TYPE_NAME,
            encode(&StateEstimate {
                header: h(9),
                state_index: u64::MAX,
                world_from_body: PoseWithCovariance { pose, covariance: cov },
                velocity_in_world_mps: Vector3 { x: 1.0, y: 2.0, z: 3.0 },
                ..StateEstimate::default()
            }),
        ),
        (
            "/t/trajectory",
            Trajectory::TYPE_NAME,
            encode(&Trajectory {
                header: h(10),
                state_indices: vec![0, 1],
                poses: vec![PoseStamped { header: h(1), pose }, PoseStamped { header: h(2), pose }],
            }),
        ),
        (
            "/t/mapfix",
            MapFix::TYPE_NAME,
            encode(&MapFix {
                header: h(11),
                world_from_body: pose,
                covariance: cov,
                correlation: 0.93,
                overlapping_channels: 5,
                locked: true,
            }),
        ),
        (
            "/t/attempt",
            RegistrationAttempt::TYPE_NAME,
            encode(&RegistrationAttempt {
                header: h(16),
                reference_submap: 3,
                query_submap: 40,
                reference_stamp: Time::from_ns(2_000_000_001),
                query_stamp: Time::from_ns(9_000_000_002),
                method: "learned".to_owned(),
                outcome: "no_shared_features".to_owned(),
                shift_m: -0.125,
                score: 0.42,
                stretch: 1.015,
            }),
        ),
        (
            "/t/check",
            RegistrationCheck::TYPE_NAME,
            encode(&RegistrationCheck {
                header: h(17),
                reference_stamp: Time::from_ns(2_000_000_001),
                query_stamp: Time::from_ns(9_000_000_002),
                along_track_m: 3.25,
                residual_m: -0.5,
                gate_m: 0.3,
                sigma_m: 0.0,
                accepted: false,
            }),
        ),
        (
            "/t/imu",
            Imu::TYPE_NAME,
            encode(&Imu {
                header: h(12),
                orientation: pose.orientation,
                orientation_covariance: [0.5; 9],
                angular_velocity: Vector3 {
                    x: 0.1,
                    y: -0.2,
                    z: 0.3,
                },
                linear_acceleration: Vector3 {
                    x: 0.0,
                    y: 0.0,
                    z: 9.81,
                },
                ..Imu::default()
            }),
        ),
        (
            "/t/pose",
            PoseStamped::TYPE_NAME,
            encode(&PoseStamped { header: h(13), pose }),
        ),
        (
            "/t/odom",
            Odometry::TYPE_NAME,
            encode(&Odometry {
                header: h(14),
                child_frame_id: "gpr".to_owned(),
                pose: PoseWithCovariance { pose, covariance: cov },
                ..Odometry::default()
            }),
        ),
        (
            "/t/image",
            Image::TYPE_NAME,
            encode(&Image {
                header: h(15),
                height: 2,
                width: 2,
                encoding: "mono8".to_owned(),
                step: 2,
                data: Cow::Owned(vec![0, 127, 128, 255]),
                ..Image::default()
            }),
        ),
        (
            "/t/path",
            Path::TYPE_NAME,
            encode(&Path {
                header: h(16),
                poses: vec![
                    PoseStamped { header: h(16), pose },
                    PoseStamped {
                        header: h(17),
                        pose: Pose::default(),
                    },
                ],
            }),
        ),
    ];
    assert_eq!(
        msgs.len(),
        gprflow::msg::message_types().len() + 1,
        "one message of every type (Trace twice)"
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("all-types.mcap");
    {
        let mut w =
            gprflow::record::Recorder::create(&rec, &gprflow::record::RunMetadata::this_build()).expect("create");
        for (i, (topic, ty, bytes)) in msgs.drain(..).enumerate() {
            let ch = w.add_topic(topic, ty).expect("topic");
            w.write(ch, 0, i as i64 + 1, &bytes).expect("write");
        }
        w.finish().expect("finish");
    }
    peer_check(&rec, "18 messages on 18 topics");
}

#[test]
fn python_mcap_reader_decodes_every_field_alike() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rec = dir.path().join("peer.mcap");
    record_toy(300, &rec);
    peer_check(&rec, "600 messages on 2 topics");
}
