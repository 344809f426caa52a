//! MCAP recordings: writing ([`Recorder`]), reading ([`Recording`]), summaries
//! ([`Inspection`]) and recovery of files cut off mid-write ([`recover`]).
//!
//! Recordings use the ROS 2 profile: `schema encoding = ros2msg`, `message encoding = cdr`,
//! topics named `/node/output`. A message's log time is its stamp (sensor time), so a file
//! is ordered by sensor time and replays at recorded pace; the publish time is the wall
//! clock when the recorder received it. The MCAP `sequence` is the topic's bus sequence
//! number. Every recording carries a `gprflow` metadata record (version, commit, run,
//! graph) and the graph file and resolved node parameters as attachments.

mod read;
mod stages;

pub use read::{Extras, Message, Messages, RecordedMessage, Recording, Window};

pub use stages::{
    LOOP_GAP_NS, PROMISE_EVERY_NS, Pace, Player, RecordParams, RecordStage, ReplayParams, ReplayStage, check_window,
    seconds_window,
};

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use gprflow_msg as msg;

/// Chunk size: small enough that a crash loses little, large enough to compress well.
const CHUNK_BYTES: u64 = 256 * 1024;
/// A chunk is closed at least this often, bounding what a crash can lose.
const FLUSH_EVERY: Duration = Duration::from_secs(1);

/// Errors of recording and reading.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// File system error.
    #[error("{path}: {source}")]
    Io {
        /// File concerned.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The MCAP library failed.
    #[error("{path}: {what}")]
    Mcap {
        /// File concerned.
        path: PathBuf,
        /// What failed.
        what: String,
    },
    /// A topic whose message type gprflow does not know (no schema to write).
    #[error("{path}: topic `{topic}`: unknown message type `{msg_type}`")]
    UnknownType {
        /// File concerned.
        path: PathBuf,
        /// Topic.
        topic: String,
        /// Type name.
        msg_type: String,
    },
    /// Not an MCAP file at all, or nothing readable.
    #[error("{path}: not a readable MCAP file: {what}")]
    NotMcap {
        /// File concerned.
        path: PathBuf,
        /// What the reader said.
        what: String,
    },
}

/// Result of recording operations.
pub type Result<T, E = RecordError> = std::result::Result<T, E>;

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// What a recording says about the run that made it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct RunMetadata {
    /// gprflow version.
    pub version: String,
    /// Source commit, when known at build time.
    pub commit: String,
    /// Run identifier.
    pub run_id: String,
    /// Graph name.
    pub graph_name: String,
    /// Graph file path as given.
    pub graph_file: String,
    /// The graph file's text.
    pub graph_text: String,
    /// Resolved node parameters, JSON.
    pub nodes_json: String,
}

impl RunMetadata {
    /// The version and commit of this build, with the other fields empty.
    pub fn this_build() -> Self {
        Self {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            commit: option_env!("GPRFLOW_COMMIT").unwrap_or("unknown").to_owned(),
            ..Self::default()
        }
    }
}

/// Writes a recording.
pub struct Recorder {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    schemas: BTreeMap<String, u16>,
    last_flush: Instant,
    finished: bool,
    /// `None`: a live recording (wall-clock publish times, chunks closed every second).
    /// `Some(t)`: a reproducible one (publish time = log time, attachments stamped `t`,
    /// chunks closed by size only), so the same messages give the same bytes.
    reproducible_at: Option<u64>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

/// A channel of a [`Recorder`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelId(u16);

impl Recorder {
    /// Creates `path` (zstd chunks) and writes the run metadata and attachments.
    ///
    /// # Errors
    /// File or MCAP errors.
    pub fn create(path: &Path, meta: &RunMetadata) -> Result<Self> {
        Self::create_inner(path, meta, None)
    }

    /// Like [`create`](Self::create), but the file depends only on what is written: publish
    /// times equal log times, attachments are stamped `stamp_ns` and chunks close by size
    /// alone. For recordings made by programs (the simulator), where the same input must
    /// give the same bytes.
    ///
    /// # Errors
    /// File or MCAP errors.
    pub fn create_reproducible(path: &Path, meta: &RunMetadata, stamp_ns: u64) -> Result<Self> {
        Self::create_inner(path, meta, Some(stamp_ns))
    }

    fn create_inner(path: &Path, meta: &RunMetadata, reproducible_at: Option<u64>) -> Result<Self> {
        let file = File::create(path).map_err(|source| RecordError::Io {
            path: path.to_owned(),
            source,
        })?;
        let mcap_err = |e: mcap::McapError| RecordError::Mcap {
            path: path.to_owned(),
            what: e.to_string(),
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(CHUNK_BYTES))
            .profile("ros2")
            .library(format!("gprflow {}", meta.version))
            .create(BufWriter::new(file))
            .map_err(mcap_err)?;
        let mut fields = BTreeMap::new();
        for (k, v) in [
            ("version", &meta.version),
            ("commit", &meta.commit),
            ("run_id", &meta.run_id),
            ("graph_name", &meta.graph_name),
            ("graph_file", &meta.graph_file),
        ] {
            fields.insert(k.to_owned(), v.clone());
        }
        writer
            .write_metadata(&mcap::records::Metadata {
                name: "gprflow".to_owned(),
                metadata: fields,
            })
            .map_err(mcap_err)?;
        let t = reproducible_at.unwrap_or_else(now_ns);
        for (name, media_type, data) in [
            ("graph.yaml", "application/yaml", &meta.graph_text),
            ("nodes.json", "application/json", &meta.nodes_json),
        ] {
            if data.is_empty() {
                continue;
            }
            writer
                .attach(&mcap::Attachment {
                    log_time: t,
                    create_time: t,
                    name: name.to_owned(),
                    media_type: media_type.to_owned(),
                    data: std::borrow::Cow::Borrowed(data.as_bytes()),
                })
                .map_err(mcap_err)?;
        }
        Ok(Self {
            path: path.to_owned(),
            writer,
            schemas: BTreeMap::new(),
            last_flush: Instant::now(),
            finished: false,
            reproducible_at,
        })
    }

    fn mcap_err(&self, e: mcap::McapError) -> RecordError {
        RecordError::Mcap {
            path: self.path.clone(),
            what: e.to_string(),
        }
    }

    /// Adds a channel for `topic` (`node/output`, written as `/node/output`) of `msg_type`.
    ///
    /// # Errors
    /// [`RecordError::UnknownType`] or MCAP errors.
    pub fn add_topic(&mut self, topic: &str, msg_type: &str) -> Result<ChannelId> {
        let schema_id = match self.schemas.get(msg_type) {
            Some(id) => *id,
            None => {
                let t = msg::message_type(msg_type).ok_or_else(|| RecordError::UnknownType {
                    path: self.path.clone(),
                    topic: topic.to_owned(),
                    msg_type: msg_type.to_owned(),
                })?;
                let id = self
                    .writer
                    .add_schema(msg_type, "ros2msg", t.schema_text().as_bytes())
                    .map_err(|e| self.mcap_err(e))?;
                self.schemas.insert(msg_type.to_owned(), id);
                id
            }
        };
        let name = format!("/{}", topic.trim_start_matches('/'));
        let id = self
            .writer
            .add_channel(schema_id, &name, "cdr", &BTreeMap::new())
            .map_err(|e| self.mcap_err(e))?;
        Ok(ChannelId(id))
    }

    /// Writes one message; closes the current chunk when the last one is older than a second.
    ///
    /// # Errors
    /// MCAP errors.
    pub fn write(&mut self, channel: ChannelId, seq: u64, stamp_ns: i64, payload: &[u8]) -> Result<()> {
        let header = mcap::records::MessageHeader {
            channel_id: channel.0,
            // MCAP sequences are 32-bit; bus sequence numbers wrap there
            sequence: (seq & u64::from(u32::MAX)) as u32,
            log_time: u64::try_from(stamp_ns).unwrap_or(0),
            publish_time: if self.reproducible_at.is_some() {
                u64::try_from(stamp_ns).unwrap_or(0)
            } else {
                now_ns()
            },
        };
        self.writer
            .write_to_known_channel(&header, payload)
            .map_err(|e| self.mcap_err(e))?;
        if self.reproducible_at.is_none() && self.last_flush.elapsed() >= FLUSH_EVERY {
            self.writer.flush().map_err(|e| self.mcap_err(e))?;
            self.last_flush = Instant::now();
        }
        Ok(())
    }

    /// Adds a named metadata record (string key-value pairs).
    ///
    /// # Errors
    /// MCAP errors.
    pub fn write_metadata(&mut self, name: &str, fields: BTreeMap<String, String>) -> Result<()> {
        self.writer
            .write_metadata(&mcap::records::Metadata {
                name: name.to_owned(),
                metadata: fields,
            })
            .map_err(|e| self.mcap_err(e))
    }

    /// Adds an attachment (a file carried inside the recording).
    ///
    /// # Errors
    /// MCAP errors.
    pub fn attach(&mut self, name: &str, media_type: &str, data: &[u8]) -> Result<()> {
        let t = self.reproducible_at.unwrap_or_else(now_ns);
        self.writer
            .attach(&mcap::Attachment {
                log_time: t,
                create_time: t,
                name: name.to_owned(),
                media_type: media_type.to_owned(),
                data: std::borrow::Cow::Borrowed(data),
            })
            .map_err(|e| self.mcap_err(e))
    }

    /// Writes the summary and footer.
    ///
    /// # Errors
    /// MCAP errors.
    pub fn finish(&mut self) -> Result<()> {
        if !self.finished {
            self.finished = true;
            self.writer.finish().map_err(|e| self.mcap_err(e))?;
        }
        Ok(())
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if let Err(e) = self.finish() {
            tracing::error!("{e}");
        }
    }
}

/// Per-topic figures of a recording.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TopicSummary {
    /// Topic.
    pub topic: String,
    /// Message type.
    pub msg_type: String,
    /// Messages.
    pub count: u64,
    /// First and last log time, ns.
    pub first_ns: u64,
    /// Last log time, ns.
    pub last_ns: u64,
    /// Messages per second over the topic's own span.
    pub rate_hz: f64,
    /// Payloads that failed to decode as the declared type.
    pub decode_errors: u64,
    /// Sequence numbers missing (gaps) on the topic.
    pub seq_gaps: u64,
}

/// What `gprflow inspect` shows.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Inspection {
    /// File.
    pub path: String,
    /// File size, bytes.
    pub bytes: u64,
    /// Topics in order of first appearance.
    pub topics: Vec<TopicSummary>,
    /// Messages in total.
    pub messages: u64,
    /// First and last log time, ns.
    pub start_ns: u64,
    /// Last log time, ns.
    pub end_ns: u64,
    /// Metadata records.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Attachment names.
    pub attachments: Vec<String>,
    /// Where reading stopped early, if it did.
    pub truncated: Option<String>,
    /// First decode errors: topic, sequence, error.
    pub decode_errors: Vec<(String, u32, String)>,
}

/// Summarises a recording: topics, types, counts, rates, time span; decodes every payload
/// of a known type to check it.
pub fn inspect(rec: &Recording) -> Inspection {
    let mut topics: Vec<TopicSummary> = Vec::new();
    let mut last_seq: BTreeMap<String, u32> = BTreeMap::new();
    let mut errors = Vec::new();
    let (extras, truncated) = rec.scan(|m| {
        let idx = match topics.iter().position(|t| t.topic == m.topic) {
            Some(i) => i,
            None => {
                topics.push(TopicSummary {
                    topic: m.topic.to_owned(),
                    msg_type: m.msg_type.to_owned(),
                    first_ns: m.log_time,
                    ..TopicSummary::default()
                });
                topics.len() - 1
            }
        };
        let t = &mut topics[idx];
        t.count += 1;
        t.first_ns = t.first_ns.min(m.log_time);
        t.last_ns = t.last_ns.max(m.log_time);
        if let Some(prev) = last_seq.insert(m.topic.to_owned(), m.sequence) {
            t.seq_gaps += u64::from(m.sequence.wrapping_sub(prev).saturating_sub(1));
        }
        if let Some(ty) = msg::message_type(m.msg_type)
            && let Err(e) = ty.decode_to_json(m.data)
        {
            t.decode_errors += 1;
            if errors.len() < 10 {
                errors.push((m.topic.to_owned(), m.sequence, e.to_string()));
            }
        }
    });
    for t in &mut topics {
        let span = t.last_ns.saturating_sub(t.first_ns) as f64 * 1e-9;
        t.rate_hz = if span > 0.0 {
            (t.count.saturating_sub(1)) as f64 / span
        } else {
            0.0
        };
    }
    Inspection {
        path: rec.path().display().to_string(),
        bytes: rec.len_bytes(),
        messages: topics.iter().map(|t| t.count).sum(),
        start_ns: topics.iter().map(|t| t.first_ns).min().unwrap_or(0),
        end_ns: topics.iter().map(|t| t.last_ns).max().unwrap_or(0),
        topics,
        metadata: extras.metadata,
        attachments: extras.attachments.into_iter().map(|(n, _)| n).collect(),
        truncated,
        decode_errors: errors,
    }
}

/// Rewrites what can be read of `input` (every complete chunk) into a new, complete file
/// `output`, with its metadata and attachments. Returns the number of messages kept and
/// where reading stopped, if it did.
///
/// # Errors
/// File or MCAP errors.
pub fn recover(input: &Path, output: &Path) -> Result<(u64, Option<String>)> {
    let rec = Recording::open(input)?;
    // metadata and attachments come first in our files; gather them before writing
    let (extras, _) = rec.scan(|_| {});
    let get = |k: &str| {
        extras
            .metadata
            .get("gprflow")
            .and_then(|m| m.get(k))
            .cloned()
            .unwrap_or_default()
    };
    let attachment = |name: &str| {
        extras
            .attachments
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, d)| String::from_utf8_lossy(d).into_owned())
            .unwrap_or_default()
    };
    let meta = RunMetadata {
        version: get("version"),
        commit: get("commit"),
        run_id: get("run_id"),
        graph_name: get("graph_name"),
        graph_file: get("graph_file"),
        graph_text: attachment("graph.yaml"),
        nodes_json: attachment("nodes.json"),
    };
    let mut out = Recorder::create(output, &meta)?;
    let mut channels: BTreeMap<String, ChannelId> = BTreeMap::new();
    let mut first_error = None;
    let mut kept = 0u64;
    let (_, stopped) = rec.scan(|m| {
        if first_error.is_some() {
            return;
        }
        let ch = match channels.get(m.topic) {
            Some(c) => *c,
            None => match out.add_topic(m.topic, m.msg_type) {
                Ok(c) => {
                    channels.insert(m.topic.to_owned(), c);
                    c
                }
                Err(e) => {
                    first_error = Some(e);
                    return;
                }
            },
        };
        let stamp = i64::try_from(m.log_time).unwrap_or(i64::MAX);
        match out.write(ch, u64::from(m.sequence), stamp, m.data) {
            Ok(()) => kept += 1,
            Err(e) => first_error = Some(e),
        }
    });
    if let Some(e) = first_error {
        return Err(e);
    }
    out.finish()?;
    Ok((kept, stopped))
}
