//! The built-in `record` and `replay` stages.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use super::{ChannelId, Recorder, Recording, RunMetadata, Window};
use gprflow_bus::glob_matches;
use gprflow_stage::{
    Input, InputPorts, Outputs, ParamError, PortSpec, Ports, Produce, Stage, StageError, report_progress,
};

/// Parameters of [`RecordStage`].
#[derive(Debug, Clone, Default, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RecordParams {
    /// Output MCAP file.
    pub path: String,
    /// Run description stored in the file (filled in by the launcher).
    #[serde(default)]
    pub run: RunMetadata,
}

impl schemars::JsonSchema for RunMetadata {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "RunMetadata".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({ "type": "object" })
    }
}

/// Writes every input, in stamp order, to an MCAP file.
#[derive(Debug)]
pub struct RecordStage {
    recorder: Recorder,
    channels: Vec<ChannelId>,
}

impl Stage for RecordStage {
    type Params = RecordParams;
    const NAME: &'static str = "record";
    const ABOUT: &'static str = "records its inputs to an MCAP file (zstd chunks, ros2msg schemas, CDR)";

    fn inputs() -> InputPorts {
        InputPorts::Any
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(Vec::new())
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let mut recorder = Recorder::create(params.path.as_ref(), &params.run).map_err(StageError::failed)?;
        let channels = ports
            .inputs()
            .iter()
            .map(|b| recorder.add_topic(&b.topic, &b.msg_type))
            .collect::<Result<Vec<_>, _>>()
            .map_err(StageError::failed)?;
        Ok(Self { recorder, channels })
    }

    fn on_message(&mut self, input: Input<'_>, _out: &mut Outputs) -> Result<(), StageError> {
        self.recorder
            .write(
                self.channels[input.id.0],
                input.seq(),
                input.stamp_ns(),
                input.payload(),
            )
            .map_err(StageError::failed)
    }

    fn finish(&mut self, _out: &mut Outputs) -> Result<(), StageError> {
        self.recorder.finish().map_err(StageError::failed)
    }
}

/// How fast a replay goes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Pace {
    /// As fast as the consumers take it (back-pressure sets the pace).
    #[default]
    Max,
    /// At the pace of the log times (scaled by `speed`).
    Recorded,
}

fn default_speed() -> f64 {
    1.0
}

fn default_topics() -> Vec<String> {
    vec!["*".to_owned()]
}

/// Parameters of [`ReplayStage`].
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ReplayParams {
    /// MCAP file to replay.
    pub path: String,
    /// `max` (default) or `recorded`.
    #[serde(default)]
    pub pace: Pace,
    /// Speed factor for `recorded` pace (default 1.0).
    #[serde(default = "default_speed")]
    pub speed: f64,
    /// Topics to replay, glob patterns over `node/output` (default all).
    #[serde(default = "default_topics")]
    pub topics: Vec<String>,
    /// Start this many seconds after the recording's first message (the chunks before it are
    /// not read).
    #[serde(default)]
    pub start_s: Option<f64>,
    /// End this many seconds after the recording's first message.
    #[serde(default)]
    pub end_s: Option<f64>,
    /// Times to play the recording (0: until stopped). Each pass after the first is stamped
    /// later by the span of the one before plus [`LOOP_GAP_NS`], so that time keeps moving
    /// forward.
    #[serde(default = "default_loops")]
    pub loops: u32,
}

fn default_loops() -> u32 {
    1
}

/// Sensor time between the last message of one pass of a looped replay and the first of the
/// next.
pub const LOOP_GAP_NS: i64 = 1_000_000_000;

/// What a replay reads: the file, the window and which recorded topic goes to which output.
struct ReplaySource {
    path: std::path::PathBuf,
    window: Window,
    outputs: HashMap<String, usize>,
}

impl ReplaySource {
    /// One pass over the window, stamps moved by `offset_ns`; the first and last stamps seen
    /// are kept in `span`.
    fn pass(
        &self,
        offset_ns: i64,
        span: std::sync::Arc<std::sync::Mutex<(i64, i64)>>,
    ) -> Result<impl Iterator<Item = (usize, i64, Vec<u8>)> + Send + use<>, StageError> {
        let rec = Recording::open(&self.path).map_err(StageError::failed)?;
        let messages = rec.messages(&self.window).map_err(StageError::failed)?;
        let outputs = self.outputs.clone();
        Ok(messages.filter_map(move |m| {
            let i = *outputs.get(&*m.topic)?;
            let stamp = i64::try_from(m.log_time).unwrap_or(i64::MAX);
            if let Ok(mut s) = span.lock() {
                s.0 = s.0.min(stamp);
                s.1 = s.1.max(stamp);
            }
            Some((i, stamp.saturating_add(offset_ns), m.data))
        }))
    }
}

fn replayed_topics(params: &ReplayParams) -> Result<Vec<PortSpec>, ParamError> {
    let rec = Recording::open(params.path.as_ref()).map_err(|e| ParamError::new("path", e.to_string()))?;
    Ok(rec
        .topics()
        .into_iter()
        .map(|(topic, ty)| PortSpec::new(topic.trim_start_matches('/'), &ty))
        .filter(|p| params.topics.iter().any(|g| glob_matches(g, &p.name)))
        .collect())
}

/// Checks a window of `start_s` .. `end_s` seconds (parameters of the sources that take one).
///
/// # Errors
/// A start or end that is negative or not a number, or an end not after the start.
pub fn check_window(start_s: Option<f64>, end_s: Option<f64>) -> Result<(), ParamError> {
    for (key, value) in [("start_s", start_s), ("end_s", end_s)] {
        if let Some(v) = value
            && !(v.is_finite() && v >= 0.0)
        {
            return Err(ParamError::new(
                key,
                format!("must be a number of seconds >= 0, not {v}"),
            ));
        }
    }
    if let (Some(s), Some(e)) = (start_s, end_s)
        && e <= s
    {
        return Err(ParamError::new(
            "end_s",
            format!("must come after start_s ({s} s), not {e} s"),
        ));
    }
    Ok(())
}

/// The log-time window from `start_s` to `end_s` seconds after the recording's first message
/// (checked by [`check_window`]), every topic.
pub fn seconds_window(rec: &Recording, start_s: Option<f64>, end_s: Option<f64>) -> Window {
    let first = if start_s.is_some() || end_s.is_some() {
        rec.start_ns().unwrap_or(0)
    } else {
        0
    };
    let at = |s: f64| first.saturating_add((s * 1e9).round() as u64);
    Window {
        topics: None,
        start_ns: start_s.map(at),
        end_ns: end_s.map(at),
    }
}

/// Encoded messages sent in stamp order at a pace: the part every source stage that publishes
/// what it read shares (the `replay` stage, the `ingest` stage). It pulls them one at a time
/// from its source (a recording streamed from disk, or a list), so it holds one message at a
/// time. As its stamps advance it promises them on every output, so that a consumer merging an
/// idle output (a topic with one message at the start) with a busy one never waits for the idle
/// one.
pub struct Player {
    /// (output index, stamp ns, CDR payload), in stamp order.
    source: Box<dyn Iterator<Item = (usize, i64, Vec<u8>)> + Send>,
    /// The message waiting for its time (`recorded` pace).
    waiting: Option<(usize, i64, Vec<u8>)>,
    /// Messages in all, when known (for progress).
    total: Option<usize>,
    sent: usize,
    pace: Pace,
    speed: f64,
    started: Instant,
    first_ns: Option<i64>,
    last_ns: i64,
    /// Messages whose stamp came before the one sent before them.
    out_of_order: u64,
    last_progress: Instant,
    /// Stamp last promised on every output.
    promised_ns: i64,
}

impl std::fmt::Debug for Player {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Player")
            .field("total", &self.total)
            .field("sent", &self.sent)
            .field("pace", &self.pace)
            .field("speed", &self.speed)
            .finish_non_exhaustive()
    }
}

/// How far a source's stamps advance before it promises them on every output (sensor time).
pub const PROMISE_EVERY_NS: i64 = 5_000_000;

impl Player {
    /// A player of `messages` (output index, stamp ns, payload), which must be in stamp order;
    /// `speed` scales the recorded pace.
    pub fn new(messages: Vec<(usize, i64, Vec<u8>)>, pace: Pace, speed: f64) -> Self {
        let total = messages.len();
        Self::streaming(messages.into_iter(), Some(total), pace, speed)
    }

    /// A player pulling its messages (output index, stamp ns, payload; in stamp order) from
    /// `source` as it sends them; `total` is their number when known.
    pub fn streaming(
        source: impl Iterator<Item = (usize, i64, Vec<u8>)> + Send + 'static,
        total: Option<usize>,
        pace: Pace,
        speed: f64,
    ) -> Self {
        Self {
            source: Box::new(source),
            waiting: None,
            total,
            sent: 0,
            pace,
            speed,
            started: Instant::now(),
            first_ns: None,
            last_ns: i64::MIN,
            out_of_order: 0,
            last_progress: Instant::now(),
            promised_ns: i64::MIN,
        }
    }

    /// Messages sent so far.
    pub fn sent(&self) -> usize {
        self.sent
    }

    fn progress(&self) {
        report_progress(self.sent, self.total.unwrap_or(0).max(self.sent));
    }

    /// Sends the next message (or waits for its time at `recorded` pace); for
    /// [`Stage::produce`].
    ///
    /// # Errors
    /// Bus errors.
    pub fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        let Some((index, stamp, data)) = self.waiting.take().or_else(|| self.source.next()) else {
            self.progress();
            if self.out_of_order > 0 {
                tracing::warn!(
                    "{} of {} messages came with a stamp before the one sent before them (a file read in file order)",
                    self.out_of_order,
                    self.sent
                );
            }
            return Ok(Produce::Done);
        };
        let first = *self.first_ns.get_or_insert(stamp);
        if self.pace == Pace::Recorded {
            let offset = Duration::from_secs_f64((stamp - first).max(0) as f64 * 1e-9 / self.speed);
            if let Some(wait) = offset.checked_sub(self.started.elapsed()) {
                std::thread::sleep(wait.min(Duration::from_millis(100)));
                self.waiting = Some((index, stamp, data));
                return Ok(Produce::More);
            }
        }
        out.send_bytes(index, stamp, &data)?;
        if stamp < self.last_ns {
            self.out_of_order += 1;
        }
        self.last_ns = stamp;
        if stamp >= self.promised_ns.saturating_add(PROMISE_EVERY_NS) {
            out.promise(stamp)?;
            self.promised_ns = stamp;
        }
        self.sent += 1;
        if self.last_progress.elapsed() > Duration::from_millis(200) {
            self.last_progress = Instant::now();
            self.progress();
        }
        Ok(Produce::More)
    }
}

/// Publishes the messages of a recording, each on the output named after its topic, streamed
/// from the file.
#[derive(Debug)]
pub struct ReplayStage {
    player: Player,
}

impl Stage for ReplayStage {
    type Params = ReplayParams;
    const NAME: &'static str = "replay";
    const ABOUT: &'static str = "replays an MCAP recording, one output per recorded topic";

    fn outputs(params: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        replayed_topics(params)
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        gprflow_stage::params::positive("speed", params.speed)?;
        check_window(params.start_s, params.end_s)
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let rec = Recording::open(params.path.as_ref()).map_err(StageError::failed)?;
        let mut window = seconds_window(&rec, params.start_s, params.end_s);
        // recorded topic -> output index
        let outputs: HashMap<String, usize> = rec
            .topics()
            .into_iter()
            .filter_map(|(topic, _)| {
                let name = topic.trim_start_matches('/');
                let i = ports.outputs().iter().position(|o| o.name == name)?;
                Some((topic, i))
            })
            .collect();
        window.topics = Some(outputs.keys().cloned().collect());
        let total = rec
            .messages(&window)
            .map_err(StageError::failed)?
            .total()
            .and_then(|t| usize::try_from(t).ok());
        let source = ReplaySource {
            path: params.path.into(),
            window,
            outputs,
        };
        let span = std::sync::Arc::new(std::sync::Mutex::new((i64::MAX, i64::MIN)));
        let first = source.pass(0, span.clone())?;
        let loops = params.loops;
        // later passes open the file again when the one before has ended
        let later = (1..)
            .take_while(move |k| loops == 0 || *k < loops)
            .flat_map(move |k: u32| {
                let (first_ns, last_ns) = span.lock().map_or((0, 0), |s| *s);
                let offset = (last_ns.saturating_sub(first_ns)).max(0).saturating_add(LOOP_GAP_NS);
                match source.pass(offset.saturating_mul(i64::from(k)), span.clone()) {
                    Ok(pass) => Some(pass),
                    Err(e) => {
                        tracing::error!("replay pass {}: {e}", k + 1);
                        None
                    }
                }
                .into_iter()
                .flatten()
            });
        let total = total.filter(|_| loops > 0).map(|t| t * loops as usize);
        Ok(Self {
            player: Player::streaming(first.chain(later), total, params.pace, params.speed),
        })
    }

    fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        self.player.produce(out)
    }
}
