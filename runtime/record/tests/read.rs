//! Reading recordings streamed from disk: stamp order across chunks that overlap in time,
//! windows of topics and times, and files cut off mid-write.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use gprflow_record::{Recording, Window};
use proptest::prelude::*;

/// One message to write: topic index, log time ns, payload.
type Msg = (usize, u64, Vec<u8>);

const TOPICS: [&str; 3] = ["/a/trace", "/b/imu", "/c/wheel"];

/// Writes `messages` in the given (file) order, closing a chunk every `chunk_bytes`.
fn write(path: &Path, messages: &[Msg], chunk_bytes: u64) {
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .chunk_size(Some(chunk_bytes))
        .create(BufWriter::new(File::create(path).expect("create")))
        .expect("writer");
    let schema = w.add_schema("raw", "", &[]).expect("schema");
    let ids: Vec<u16> = TOPICS
        .iter()
        .map(|t| w.add_channel(schema, t, "cdr", &BTreeMap::new()).expect("channel"))
        .collect();
    for (seq, (topic, stamp, data)) in messages.iter().enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: ids[*topic],
            sequence: u32::try_from(seq).expect("small"),
            log_time: *stamp,
            publish_time: *stamp,
        };
        w.write_to_known_channel(&header, data).expect("write");
    }
    w.finish().expect("finish");
}

/// (topic, stamp, payload) of what `Recording::messages` yields.
fn read(rec: &Recording, window: &Window) -> Vec<(String, u64, Vec<u8>)> {
    let mut it = rec.messages(window).expect("messages");
    let out: Vec<_> = it.by_ref().map(|m| (m.topic.to_string(), m.log_time, m.data)).collect();
    assert_eq!(it.stopped(), None, "{}", rec.path().display());
    out
}

/// What a window should hold, from the written messages: filtered and sorted by stamp.
fn expected(messages: &[Msg], window: &Window) -> Vec<(String, u64, Vec<u8>)> {
    let mut want: Vec<_> = messages
        .iter()
        .filter(|(t, s, _)| {
            window.topics.as_ref().is_none_or(|w| w.contains(TOPICS[*t]))
                && window.start_ns.is_none_or(|a| *s >= a)
                && window.end_ns.is_none_or(|b| *s < b)
        })
        .map(|(t, s, d)| (TOPICS[*t].to_owned(), *s, d.clone()))
        .collect();
    want.sort_by_key(|m| m.1);
    want
}

/// Two sensors written in bursts, each burst its own chunk, so chunks overlap in time (as
/// when a recorder flushes one busy topic while a slow one lags).
fn bursts() -> Vec<Msg> {
    let mut out = Vec::new();
    for burst in 0..20u64 {
        for i in 0..50u64 {
            let t = burst * 1_000_000 + i * 20_000;
            out.push((0, t * 2 + 1, vec![0xA0; 64]));
        }
        for i in 0..50u64 {
            let t = burst * 1_000_000 + i * 20_000;
            out.push((1, t * 2, t.to_le_bytes().to_vec()));
        }
    }
    out
}

#[test]
fn messages_come_in_stamp_order_across_chunks_that_overlap_in_time() {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("bursts.mcap");
    let messages = bursts();
    write(&path, &messages, 1024);
    let rec = Recording::open(&path).expect("open");
    let summary = rec.summary().expect("a finished file has a summary");
    assert!(
        summary.chunk_indexes.len() > 10,
        "{} chunks",
        summary.chunk_indexes.len()
    );
    let it = rec.messages(&Window::default()).expect("messages");
    assert!(it.is_indexed());
    assert_eq!(it.total(), Some(messages.len() as u64));
    let got = read(&rec, &Window::default());
    assert_eq!(got, expected(&messages, &Window::default()));
    // scan keeps file order, every message once
    let mut scanned = Vec::new();
    let (_, stopped) = rec.scan(|m| scanned.push(m.log_time));
    assert_eq!(stopped, None);
    assert_eq!(scanned, messages.iter().map(|m| m.1).collect::<Vec<_>>());
}

#[test]
fn a_window_of_topics_and_times_reads_exactly_what_it_holds() {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("bursts.mcap");
    let messages = bursts();
    write(&path, &messages, 2048);
    let rec = Recording::open(&path).expect("open");
    assert_eq!(rec.start_ns(), Some(0));
    for window in [
        Window {
            topics: Some(BTreeSet::from([TOPICS[1].to_owned()])),
            ..Window::default()
        },
        Window {
            start_ns: Some(13_000_001),
            ..Window::default()
        },
        Window {
            start_ns: Some(5_000_000),
            end_ns: Some(9_000_000),
            topics: Some(BTreeSet::from([TOPICS[0].to_owned()])),
        },
        Window {
            end_ns: Some(1),
            ..Window::default()
        },
    ] {
        let got = read(&rec, &window);
        let want = expected(&messages, &window);
        assert!(!want.is_empty() || window.end_ns == Some(1));
        assert_eq!(got, want, "{window:?}");
    }
}

#[test]
fn a_file_cut_off_mid_write_yields_every_complete_chunk_and_says_where_it_stopped() {
    let dir = tempfile::tempdir().expect("tmp");
    let whole = dir.path().join("whole.mcap");
    // one topic in stamp order, as our recorder writes
    let messages: Vec<Msg> = (0..2000u64)
        .map(|i| (2, i * 10_000, i.to_le_bytes().repeat(8)))
        .collect();
    write(&whole, &messages, 4096);
    let bytes = std::fs::read(&whole).expect("read");
    for keep in [bytes.len() * 3 / 5, bytes.len() - 100] {
        let cut = dir.path().join(format!("cut{keep}.mcap"));
        std::fs::write(&cut, &bytes[..keep]).expect("write");
        let rec = Recording::open(&cut).expect("the start is intact");
        assert!(rec.summary().is_none(), "a cut-off file has no summary");
        let mut it = rec.messages(&Window::default()).expect("messages");
        assert!(!it.is_indexed());
        let got: Vec<(u64, Vec<u8>)> = it.by_ref().map(|m| (m.log_time, m.data)).collect();
        let stopped = it.stopped().expect("says it stopped early").to_owned();
        assert!(stopped.contains(&format!("after {} messages", got.len())), "{stopped}");
        // a prefix of what was written: all of it when only the summary is cut off
        let all = keep == bytes.len() - 100;
        assert!(
            got.len() > 1000 && (got.len() < messages.len() || all),
            "{} of {}",
            got.len(),
            messages.len()
        );
        let want: Vec<(u64, Vec<u8>)> = messages[..got.len()].iter().map(|m| (m.1, m.2.clone())).collect();
        assert_eq!(got, want);
        // scan agrees
        let mut scanned = 0;
        let (_, scan_stopped) = rec.scan(|_| scanned += 1);
        assert!(scan_stopped.is_some());
        assert_eq!(scanned, got.len());
    }
}

#[test]
fn a_file_that_is_not_mcap_is_refused_by_name() {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("notes.mcap");
    std::fs::write(&path, b"hello, this is text").expect("write");
    let e = Recording::open(&path).expect_err("refused").to_string();
    assert!(e.contains("notes.mcap") && e.contains("magic"), "{e}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Any file order, any chunk size: the indexed read is the written messages sorted by
    /// stamp, within any window.
    #[test]
    fn indexed_reads_are_the_messages_sorted_by_stamp(
        order in prop::collection::vec((0usize..3, 0u64..1_000_000, 1usize..200), 1..300),
        chunk_bytes in 256u64..8192,
        a in 0u64..1_000_000,
        b in 0u64..1_000_000,
        topic_mask in 1u8..8,
    ) {
        // unique stamps, so the order is one
        let mut seen = BTreeSet::new();
        let messages: Vec<Msg> = order
            .into_iter()
            .filter(|(_, s, _)| seen.insert(*s))
            .map(|(t, s, n)| (t, s, vec![u8::try_from(s % 251).expect("small"); n]))
            .collect();
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("any.mcap");
        write(&path, &messages, chunk_bytes);
        let rec = Recording::open(&path).expect("open");
        prop_assert_eq!(read(&rec, &Window::default()), expected(&messages, &Window::default()));
        let window = Window {
            topics: Some((0..3).filter(|i| topic_mask & (1 << i) != 0).map(|i| TOPICS[i].to_owned()).collect()),
            start_ns: Some(a.min(b)),
            end_ns: Some(a.max(b)),
        };
        prop_assert_eq!(read(&rec, &window), expected(&messages, &window));
    }
}
