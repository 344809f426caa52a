//! Reading recordings, streamed from the file: memory follows the largest chunk (a few times
//! the recorder's 256 KiB, a few more where chunks overlap in time), never the recording's
//! length.
//!
//! Two ways through a file:
//! - [`Recording::messages`]: messages in log-time (stamp) order within a [`Window`] of topics
//!   and times. A complete file is read through its chunk index (the summary): only the chunks
//!   that overlap the window are read, a seek to a start time reads nothing before it, and
//!   chunks that overlap in time are merged. A file without an index (cut off mid-write, or
//!   written without chunks) is read front to back, in file order (our recorder writes in
//!   stamp order), up to its last complete chunk.
//! - [`Recording::scan`]: every record front to back, in file order, with the metadata and
//!   attachments; for summaries and recovery.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use mcap::sans_io::{IndexedReadEvent, IndexedReader, IndexedReaderOptions, SummaryReadEvent, SummaryReader};

use super::{RecordError, Result};

/// One message of a recording, as [`Recording::scan`] visits it.
#[derive(Debug, Clone, Copy)]
pub struct RecordedMessage<'a> {
    /// Topic as written (`/node/output`).
    pub topic: &'a str,
    /// Schema name (`gprflow_msgs/msg/Trace`), empty when the channel has none.
    pub msg_type: &'a str,
    /// MCAP sequence.
    pub sequence: u32,
    /// Log time (our stamp), ns.
    pub log_time: u64,
    /// Publish time, ns.
    pub publish_time: u64,
    /// CDR payload.
    pub data: &'a [u8],
}

/// One message of a recording, as [`Recording::messages`] yields it.
#[derive(Debug, Clone)]
pub struct Message {
    /// Topic as written (`/node/output`).
    pub topic: Arc<str>,
    /// Schema name, empty when the channel has none.
    pub msg_type: Arc<str>,
    /// MCAP sequence.
    pub sequence: u32,
    /// Log time (our stamp), ns.
    pub log_time: u64,
    /// CDR payload.
    pub data: Vec<u8>,
}

/// A recording on disk. Opening it reads its first bytes only; every read streams from the
/// file. Files cut off mid-write are read up to the last complete chunk, and the readers say
/// where reading stopped. The summary section is read once, when first needed.
#[derive(Clone)]
pub struct Recording {
    path: PathBuf,
    bytes: u64,
    summary: OnceLock<Option<mcap::Summary>>,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("path", &self.path)
            .field("bytes", &self.bytes)
            .finish_non_exhaustive()
    }
}

/// Metadata and attachments of a recording.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Extras {
    /// Metadata records by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Attachments: name and bytes.
    pub attachments: Vec<(String, Vec<u8>)>,
}

/// What of a recording [`Recording::messages`] reads: topics and a log-time window.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Window {
    /// Topics as written (`/node/output`); `None`: every topic.
    pub topics: Option<BTreeSet<String>>,
    /// First log time read (inclusive), ns.
    pub start_ns: Option<u64>,
    /// Log time where reading ends (exclusive), ns.
    pub end_ns: Option<u64>,
}

impl Window {
    fn holds(&self, topic: &str, log_time: u64) -> bool {
        self.topics.as_ref().is_none_or(|t| t.contains(topic))
            && self.start_ns.is_none_or(|s| log_time >= s)
            && self.end_ns.is_none_or(|e| log_time < e)
    }
}

impl Recording {
    /// Opens `path`: checks that it starts like an MCAP file.
    ///
    /// # Errors
    /// Missing or unreadable file, or a file that does not start like an MCAP file.
    pub fn open(path: &Path) -> Result<Self> {
        let io = |source| RecordError::Io {
            path: path.to_owned(),
            source,
        };
        let mut file = File::open(path).map_err(io)?;
        let bytes = file.metadata().map_err(io)?.len();
        let mut magic = [0u8; 8];
        let starts = file.read_exact(&mut magic).is_ok() && magic.as_slice() == mcap::MAGIC;
        if !starts {
            return Err(RecordError::NotMcap {
                path: path.to_owned(),
                what: "missing MCAP magic at the start".to_owned(),
            });
        }
        Ok(Self {
            path: path.to_owned(),
            bytes,
            summary: OnceLock::new(),
        })
    }

    /// File path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// File size, bytes.
    pub fn len_bytes(&self) -> u64 {
        self.bytes
    }

    fn file(&self) -> Result<File> {
        File::open(&self.path).map_err(|source| RecordError::Io {
            path: self.path.clone(),
            source,
        })
    }

    /// The summary section (channels, schemas, statistics, chunk index), read from the end of
    /// the file once; `None` when the file has none (cut off mid-write) or it does not read.
    pub fn summary(&self) -> Option<&mcap::Summary> {
        self.summary.get_or_init(|| self.read_summary()).as_ref()
    }

    fn read_summary(&self) -> Option<mcap::Summary> {
        let mut file = self.file().ok()?;
        let mut reader =
            SummaryReader::new_with_options(mcap::sans_io::SummaryReaderOptions::default().with_file_size(self.bytes));
        while let Some(event) = reader.next_event() {
            match event.ok()? {
                SummaryReadEvent::ReadRequest(need) => {
                    let read = file.read(reader.insert(need)).ok()?;
                    reader.notify_read(read);
                }
                SummaryReadEvent::SeekRequest(to) => reader.notify_seeked(file.seek(to).ok()?),
            }
        }
        reader.finish()
    }

    /// Log time of the first message, ns: from the statistics of the summary, else from the
    /// first message in the file.
    pub fn start_ns(&self) -> Option<u64> {
        if let Some(stats) = self.summary().and_then(|s| s.stats.as_ref()) {
            return Some(stats.message_start_time);
        }
        self.messages(&Window::default()).ok()?.next().map(|m| m.log_time)
    }

    /// Messages within `window`, in log-time order (see the module documentation), streamed.
    /// A read that stops early (a cut-off or corrupt file) ends the iteration after every
    /// complete chunk before the damage; [`Messages::stopped`] then says where, and a warning
    /// naming the file is logged.
    ///
    /// # Errors
    /// The file cannot be opened.
    pub fn messages(&self, window: &Window) -> Result<Messages> {
        let source = match self.summary().filter(|s| !s.chunk_indexes.is_empty()) {
            Some(summary) => {
                let mut options = IndexedReaderOptions::new();
                if let Some(topics) = &window.topics {
                    options = options.include_topics(topics.iter().cloned());
                }
                if let Some(start) = window.start_ns {
                    options = options.starting_at(start);
                }
                if let Some(end) = window.end_ns {
                    options = options.ending_before(end);
                }
                let total = summary.stats.as_ref().map(|stats| {
                    summary
                        .channels
                        .values()
                        .filter(|c| window.topics.as_ref().is_none_or(|t| t.contains(&c.topic)))
                        .map(|c| stats.channel_message_counts.get(&c.id).copied().unwrap_or(0))
                        .sum::<u64>()
                });
                let reader = IndexedReader::new_with_options(summary, options).map_err(|e| RecordError::Mcap {
                    path: self.path.clone(),
                    what: format!("chunk index: {e}"),
                })?;
                let channels = summary.channels.values().map(|c| (c.id, channel_names(c))).collect();
                Source::Indexed {
                    file: self.file()?,
                    reader: Box::new(reader),
                    channels,
                    buf: Vec::new(),
                    // the count is exact only for a whole-time window
                    total: total.filter(|_| window.start_ns.is_none() && window.end_ns.is_none()),
                }
            }
            None => Source::Linear {
                reader: Box::new(mcap::io::MessageReader::new(BufReader::with_capacity(
                    1 << 20,
                    self.file()?,
                ))),
                channels: HashMap::new(),
            },
        };
        Ok(Messages {
            path: self.path.clone(),
            source,
            window: window.clone(),
            count: 0,
            stopped: None,
        })
    }

    /// Visits every message in file order, then returns the extras and, when the file ends
    /// early (cut off, corrupt), a description of where reading stopped. Every message of
    /// every complete chunk before that point is visited. Streams from the file.
    pub fn scan(&self, mut visit: impl FnMut(&RecordedMessage<'_>)) -> (Extras, Option<String>) {
        use mcap::records::Record;
        use mcap::sans_io::{LinearReadEvent, LinearReader};
        let mut extras = Extras::default();
        let mut file = match self.file() {
            Ok(f) => BufReader::with_capacity(1 << 20, f),
            Err(e) => return (extras, Some(e.to_string())),
        };
        let mut channels: mcap::read::ChannelAccumulator<'static> = Default::default();
        let mut reader = LinearReader::new();
        let mut count = 0u64;
        let stop = |count: u64, what: &dyn std::fmt::Display| Some(format!("after {count} messages: {what}"));
        let stopped = loop {
            let Some(event) = reader.next_event() else {
                break None;
            };
            let (opcode, data) = match event {
                Ok(LinearReadEvent::ReadRequest(need)) => {
                    match file.read(reader.insert(need)) {
                        Ok(read) => reader.notify_read(read),
                        Err(e) => break stop(count, &e),
                    }
                    continue;
                }
                Ok(LinearReadEvent::Record { data, opcode }) => (opcode, data),
                Err(mcap::McapError::UnexpectedEof) => {
                    break stop(count, &"the file has no footer (cut off mid-write?)");
                }
                Err(e) => break stop(count, &e),
            };
            let record = match mcap::parse_record(opcode, data) {
                Ok(r) => r,
                Err(e) => break stop(count, &e),
            };
            match record {
                Record::Schema { header, data } => {
                    if let Err(e) = channels.add_schema_from_slice(header, &data) {
                        break stop(count, &format!("schema: {e}"));
                    }
                }
                Record::Channel(ch) => {
                    if let Err(e) = channels.add_channel(ch) {
                        break stop(count, &format!("channel: {e}"));
                    }
                }
                Record::Message { header, data } => {
                    let Some(ch) = channels.get(header.channel_id) else {
                        break stop(count, &format!("message on unknown channel {}", header.channel_id));
                    };
                    let msg_type = ch.schema.as_ref().map_or("", |s| s.name.as_str());
                    visit(&RecordedMessage {
                        topic: &ch.topic,
                        msg_type,
                        sequence: header.sequence,
                        log_time: header.log_time,
                        publish_time: header.publish_time,
                        data: &data,
                    });
                    count += 1;
                }
                Record::Metadata(m) => {
                    extras.metadata.insert(m.name, m.metadata);
                }
                Record::Attachment { header, data, .. } => {
                    extras.attachments.push((header.name, data.into_owned()));
                }
                _ => {}
            }
        };
        (extras, stopped)
    }

    /// Channels (topic, type) in order of first appearance.
    pub fn topics(&self) -> Vec<(String, String)> {
        // The summary lists every channel without decompressing; fall back to a scan.
        if let Some(summary) = self.summary() {
            let mut chans: Vec<&Arc<mcap::Channel<'_>>> = summary.channels.values().collect();
            chans.sort_by_key(|c| c.id);
            return chans
                .into_iter()
                .map(|c| {
                    (
                        c.topic.clone(),
                        c.schema.as_ref().map_or(String::new(), |s| s.name.clone()),
                    )
                })
                .collect();
        }
        let mut topics: Vec<(String, String)> = Vec::new();
        self.scan(|m| {
            if !topics.iter().any(|(t, _)| t == m.topic) {
                topics.push((m.topic.to_owned(), m.msg_type.to_owned()));
            }
        });
        topics
    }
}

fn channel_names(c: &mcap::Channel<'_>) -> (Arc<str>, Arc<str>) {
    (
        Arc::from(c.topic.as_str()),
        Arc::from(c.schema.as_ref().map_or("", |s| s.name.as_str())),
    )
}

enum Source {
    /// Through the chunk index: log-time order, windowed by the reader.
    Indexed {
        file: File,
        reader: Box<IndexedReader>,
        channels: HashMap<u16, (Arc<str>, Arc<str>)>,
        /// Reused chunk buffer.
        buf: Vec<u8>,
        total: Option<u64>,
    },
    /// Front to back: file order, windowed here.
    Linear {
        reader: Box<mcap::io::MessageReader<BufReader<File>>>,
        channels: HashMap<u16, (Arc<str>, Arc<str>)>,
    },
}

/// The messages of a recording within a [`Window`], streamed from the file
/// ([`Recording::messages`]).
pub struct Messages {
    path: PathBuf,
    source: Source,
    window: Window,
    count: u64,
    stopped: Option<String>,
}

impl std::fmt::Debug for Messages {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Messages")
            .field("path", &self.path)
            .field("indexed", &self.is_indexed())
            .field("count", &self.count)
            .field("stopped", &self.stopped)
            .finish_non_exhaustive()
    }
}

impl Messages {
    /// True when the file is read through its chunk index (log-time order); false when it is
    /// read front to back (file order).
    pub fn is_indexed(&self) -> bool {
        matches!(self.source, Source::Indexed { .. })
    }

    /// Messages in the window when the file's statistics say (a whole-time window of an
    /// indexed file).
    pub fn total(&self) -> Option<u64> {
        match &self.source {
            Source::Indexed { total, .. } => *total,
            Source::Linear { .. } => None,
        }
    }

    /// Where reading stopped early, once it has.
    pub fn stopped(&self) -> Option<&str> {
        self.stopped.as_deref()
    }

    fn stop(&mut self, what: String) -> Option<Message> {
        let at = format!("after {} messages: {what}", self.count);
        tracing::warn!(
            "{}: read stopped early ({at}); the {} messages before it were read",
            self.path.display(),
            self.count
        );
        self.stopped = Some(at);
        None
    }

    fn next_indexed(&mut self) -> Option<Message> {
        let Source::Indexed {
            file,
            reader,
            channels,
            buf,
            ..
        } = &mut self.source
        else {
            return None;
        };
        loop {
            let (offset, length) = match reader.next_event()? {
                Ok(IndexedReadEvent::ReadChunkRequest { offset, length }) => (offset, length),
                Ok(IndexedReadEvent::Message { header, data }) => {
                    let Some((topic, msg_type)) = channels.get(&header.channel_id) else {
                        let what = format!("message on unknown channel {}", header.channel_id);
                        return self.stop(what);
                    };
                    self.count += 1;
                    return Some(Message {
                        topic: Arc::clone(topic),
                        msg_type: Arc::clone(msg_type),
                        sequence: header.sequence,
                        log_time: header.log_time,
                        data: data.to_vec(),
                    });
                }
                Err(e) => return self.stop(e.to_string()),
            };
            buf.resize(length, 0);
            if let Err(e) = file.seek(SeekFrom::Start(offset)).and_then(|_| file.read_exact(buf)) {
                return self.stop(format!("chunk at byte {offset}: {e}"));
            }
            if let Err(e) = reader.insert_chunk_record_data(offset, buf) {
                return self.stop(format!("chunk at byte {offset}: {e}"));
            }
        }
    }

    fn next_linear(&mut self) -> Option<Message> {
        let Source::Linear { reader, channels } = &mut self.source else {
            return None;
        };
        loop {
            match reader.next()? {
                Ok(m) => {
                    if !self.window.holds(&m.channel.topic, m.log_time) {
                        continue;
                    }
                    let (topic, msg_type) = channels
                        .entry(m.channel.id)
                        .or_insert_with(|| channel_names(&m.channel));
                    self.count += 1;
                    return Some(Message {
                        topic: Arc::clone(topic),
                        msg_type: Arc::clone(msg_type),
                        sequence: m.sequence,
                        log_time: m.log_time,
                        data: m.data.into_owned(),
                    });
                }
                Err(mcap::McapError::UnexpectedEof) => {
                    return self.stop("the file has no footer (cut off mid-write?)".to_owned());
                }
                Err(e) => return self.stop(e.to_string()),
            }
        }
    }
}

impl Iterator for Messages {
    type Item = Message;

    fn next(&mut self) -> Option<Message> {
        if self.stopped.is_some() {
            return None;
        }
        match self.source {
            Source::Indexed { .. } => self.next_indexed(),
            Source::Linear { .. } => self.next_linear(),
        }
    }
}
