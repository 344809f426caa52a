use std::borrow::Cow;

use proptest::prelude::*;

use super::*;

fn header() -> impl Strategy<Value = Header> {
    (any::<i64>(), "[a-z_]{0,12}").prop_map(|(ns, frame)| Header::new(ns / 4, &frame))
}

fn pose() -> impl Strategy<Value = Pose> {
    prop::array::uniform7(-1e6f64..1e6).prop_map(|v| Pose {
        position: Point {
            x: v[0],
            y: v[1],
            z: v[2],
        },
        orientation: Quaternion {
            x: v[3],
            y: v[4],
            z: v[5],
            w: v[6],
        },
    })
}

fn trace() -> impl Strategy<Value = Trace<'static>> {
    (
        header(),
        any::<u16>(),
        any::<f64>(),
        prop::collection::vec(any::<i16>(), 0..300),
        prop::collection::vec(any::<f32>(), 0..300),
    )
        .prop_map(|(header, channel, dt, raw, f)| Trace {
            header,
            channel,
            sample_interval_ns: dt,
            time_zero_ns: 0.5,
            center_frequency_hz: 5e8,
            distance_m: f64::from(channel),
            samples_i16: Cow::Owned(raw),
            samples_i32: Cow::Borrowed(&[]),
            samples_f32: Cow::Owned(f),
        })
}

/// Bit-level equality, so that NaN payloads compare equal to themselves.
fn same_bits<T: CdrEncode>(a: &T, b: &T) -> bool {
    encode(a) == encode(b)
}

proptest! {
    #[test]
    fn trace_round_trips(t in trace()) {
        let bytes = encode(&t);
        prop_assert_eq!(bytes.len(), encoded_len(&t));
        let back: Trace<'_> = decode(&bytes)?;
        prop_assert!(same_bits(&t, &back));
        prop_assert_eq!(back.len(), t.len());
    }

    #[test]
    fn trajectory_round_trips(h in header(), poses in prop::collection::vec((header(), pose()), 0..20)) {
        let traj = Trajectory {
            header: h,
            state_indices: (0..poses.len() as u64).collect(),
            poses: poses.into_iter().map(|(header, pose)| PoseStamped { header, pose }).collect(),
        };
        let back: Trajectory = decode(&encode(&traj))?;
        prop_assert_eq!(back, traj);
    }

    #[test]
    fn submap_round_trips(h in header(), p in pose(), rows in 0u32..20, cols in 0u32..20, valid: bool) {
        let pixels: Vec<f32> = (0..rows * cols).map(|i| i as f32 * 0.5).collect();
        let s = Submap { header: h, id: 7, rows, cols, start_pose: p, end_pose: p, valid,
                         pixels: Cow::Owned(pixels), ..Submap::default() };
        let bytes = encode(&s);
        let back: Submap<'_> = decode(&bytes)?;
        prop_assert_eq!(back, s);
    }

    #[test]
    fn decoding_garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let mut payload = CDR_LE_HEADER.to_vec();
        payload.extend_from_slice(&bytes);
        for t in message_types() {
            let _ = t.decode_to_json(&bytes);
            let _ = t.decode_to_json(&payload);
        }
    }

    #[test]
    fn truncated_payload_is_an_error(t in trace(), cut in 1usize..64) {
        let bytes = encode(&t);
        let cut = cut.min(bytes.len());
        let res = decode::<Trace<'_>>(&bytes[..bytes.len() - cut]);
        // Cutting at most 3 bytes of final padding can still decode; anything else must fail.
        if let Ok(back) = res {
            prop_assert!(same_bits(&back, &t));
        }
    }
}

#[test]
fn imu_bytes_match_the_ros2_layout() {
    // Hand-computed: header (8 + 4 + "imu\0") then orientation at body offset 16.
    let imu = Imu {
        header: Header::new(1_500_000_000, "imu"),
        ..Imu::default()
    };
    let bytes = encode(&imu);
    assert_eq!(&bytes[..4], &CDR_LE_HEADER);
    assert_eq!(&bytes[4..8], &1i32.to_le_bytes()); // sec
    assert_eq!(&bytes[8..12], &500_000_000u32.to_le_bytes()); // nanosec
    assert_eq!(&bytes[12..16], &4u32.to_le_bytes()); // string length incl. NUL
    assert_eq!(&bytes[16..20], b"imu\0");
    // 9 f64 orientation/cov blocks: 4 + 9 + 3 + 9 + 3 + 9 doubles after 16 body bytes
    assert_eq!(bytes.len(), 4 + 16 + 8 * (4 + 9 + 3 + 9 + 3 + 9));
}

#[test]
fn schema_text_lists_dependencies_once() {
    let text = Imu::schema_text();
    assert!(text.starts_with(
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
    ));
    assert_eq!(text.matches("MSG: std_msgs/Header").count(), 1);
    assert_eq!(text.matches("MSG: builtin_interfaces/Time").count(), 1);
    assert_eq!(text.matches("MSG: geometry_msgs/Vector3").count(), 1);
    let traj = Trajectory::schema_text();
    assert!(traj.contains("geometry_msgs/PoseStamped[] poses"));
    assert!(traj.contains("uint64[] state_indices"));
}

#[test]
fn large_arrays_are_borrowed_in_place() {
    let t = Trace {
        samples_f32: Cow::Owned(vec![1.0; 1000]),
        ..Trace::default()
    };
    let bytes = encode(&t);
    // Vec<u8> from the global allocator is at least 8-byte aligned.
    let back: Trace<'_> = decode(&bytes).expect("decodes");
    assert!(
        matches!(back.samples_f32, Cow::Borrowed(_)),
        "expected a zero-copy view"
    );
    // Misaligned buffer: still decodes, by copying.
    let mut shifted = vec![0u8; bytes.len() + 1];
    shifted[1..].copy_from_slice(&bytes);
    let back: Trace<'_> = decode(&shifted[1..]).expect("decodes");
    assert_eq!(back.samples_f32.len(), 1000);
}

#[test]
fn corrupt_length_is_rejected_without_allocating() {
    let t = Trace {
        samples_i16: Cow::Owned(vec![3; 4]),
        ..Trace::default()
    };
    let mut bytes = encode(&t);
    // the samples_i16 length prefix sits right before the samples; make it huge
    let pos = bytes.len() - 4 - 4 - 8 - 4; // f32 len, i32 len, 4 samples (8 bytes), i16 len
    bytes[pos..pos + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    let err = decode::<Trace<'_>>(&bytes).expect_err("must fail");
    assert!(
        matches!(
            err,
            MsgError::Length {
                field: "gprflow_msgs/msg/Trace.samples_i16",
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn time_round_trips_negative_stamps() {
    for ns in [-1_500_000_001, -1, 0, 1, 1_700_000_000_123_456_789] {
        assert_eq!(Time::from_ns(ns).to_ns(), ns);
    }
}
