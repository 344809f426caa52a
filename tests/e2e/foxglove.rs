//! What a recording shows in Foxglove: the `viz` node of the shipped graphs (`--set
//! foxglove=true`) publishes sensor_msgs/Image, nav_msgs/Path and PoseStamped, which the
//! Python MCAP ROS 2 reader decodes field for field as we do.

use std::borrow::Cow;

use gprflow::msg::{Image, Path as PathMsg, PoseStamped, StateEstimate, Trajectory};

use crate::common::BASEMENT;
use crate::{launch_recorded, payloads, peer_check};

#[test]
fn localisation_with_foxglove_topics_records_images_paths_and_poses() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (topics, _) = launch_recorded(
        dir.path(),
        "graphs/localize.yaml",
        &[format!("recording={BASEMENT}"), "foxglove=true".to_owned()],
    );
    let count = |t: &str| topics.get(t).map_or(0, Vec::len);
    // one pose per state, one path per trajectory snapshot, with the same poses
    assert_eq!(count("/viz/pose"), count("/estimate/state"));
    assert!(count("/viz/pose") > 1000, "{}", count("/viz/pose"));
    assert_eq!(count("/viz/path"), count("/estimate/trajectory"));
    let last_path: PathMsg = gprflow::msg::decode(&topics["/viz/path"][count("/viz/path") - 1]).expect("path");
    let last_traj: Trajectory =
        gprflow::msg::decode(&topics["/estimate/trajectory"][count("/estimate/trajectory") - 1]).expect("trajectory");
    assert_eq!(last_path.poses, last_traj.poses);
    let state: StateEstimate = gprflow::msg::decode(&topics["/estimate/state"][7]).expect("state");
    let pose: PoseStamped = gprflow::msg::decode(&topics["/viz/pose"][7]).expect("pose");
    assert_eq!(pose.pose, state.world_from_body.pose);
    // a radargram every 50 traces, 400 traces wide once the window is full, and submaps
    assert!(count("/viz/radargram") > 100, "{}", count("/viz/radargram"));
    assert!(count("/viz/submap") > 100, "{}", count("/viz/submap"));
    for topic in ["/viz/radargram", "/viz/submap"] {
        for bytes in &topics[topic] {
            let image: Image = gprflow::msg::decode(bytes).expect("image");
            assert_eq!(image.encoding, "mono8");
            assert_eq!(image.step, image.width);
            assert_eq!(image.data.len(), (image.width * image.height) as usize, "{topic}");
            assert!(image.height > 10, "{topic}: {}", image.height);
        }
    }
    let last: Image = gprflow::msg::decode(topics["/viz/radargram"].last().expect("one")).expect("image");
    assert_eq!(last.width, 400);
    // not a blank picture: the values spread over the grey scale
    let data: Cow<'_, [u8]> = last.data;
    let (lo, hi) = (data.iter().min().copied(), data.iter().max().copied());
    assert!(lo < Some(40) && hi > Some(215), "{lo:?}..{hi:?}");

    let rec = dir.path().join("run.mcap");
    let total: usize = payloads(&rec).values().map(Vec::len).sum();
    peer_check(&rec, &format!("{total} messages on {} topics", topics.len()));
}

#[test]
fn without_foxglove_the_graph_records_no_viz_topics() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (topics, _) = launch_recorded(dir.path(), "graphs/odometry.yaml", &[]);
    assert!(topics.contains_key("/estimate/state"));
    assert!(!topics.keys().any(|t| t.starts_with("/viz/")), "{:?}", topics.keys());
}
