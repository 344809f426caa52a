//! The built-in `record` and `replay` stages.

use std::time::{Duration, Instant};

use super::{ChannelId, Recorder, Recording, RunMetadata};
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

/// A list of encoded messages sent in stamp order at a pace: the part every source stage that
/// publishes what it read shares (the `replay` stage, the `ingest` stage). As its stamps
/// advance it promises them on every output, so that a consumer merging an idle output (a
/// topic with one message at the start) with a busy one never waits for the idle one.
#[derive(Debug)]
pub struct Player {
    /// (output index, stamp ns, CDR payload), in stamp order.
    messages: Vec<(usize, i64, Vec<u8>)>,
    next: usize,
    pace: Pace,
    speed: f64,
    started: Instant,
    last_progress: Instant,
    /// Stamp last promised on every output.
    promised_ns: i64,
}

/// How far a source's stamps advance before it promises them on every output (sensor time).
pub const PROMISE_EVERY_NS: i64 = 5_000_000;

impl Player {
    /// A player of `messages` (output index, stamp ns, payload), which must be in stamp order;
    /// `speed` scales the recorded pace.
    pub fn new(messages: Vec<(usize, i64, Vec<u8>)>, pace: Pace, speed: f64) -> Self {
        Self {
            messages,
            next: 0,
            pace,
            speed,
            started: Instant::now(),
            last_progress: Instant::now(),
            promised_ns: i64::MIN,
        }
    }

    /// Messages to send.
    pub fn len(&self) -> usize {
        self.messages.len()
    }

    /// True when there is nothing to send.
    pub fn is_empty(&self) -> bool {
        self.messages.is_empty()
    }

    /// Sends the next message (or waits for its time at `recorded` pace); for
    /// [`Stage::produce`].
    ///
    /// # Errors
    /// Bus errors.
    pub fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        let Some((index, stamp, data)) = self.messages.get(self.next) else {
            report_progress(self.next, self.messages.len());
            return Ok(Produce::Done);
        };
        if self.pace == Pace::Recorded {
            let first = self.messages.first().map_or(*stamp, |m| m.1);
            let offset = Duration::from_secs_f64((stamp - first).max(0) as f64 * 1e-9 / self.speed);
            if let Some(wait) = offset.checked_sub(self.started.elapsed()) {
                std::thread::sleep(wait.min(Duration::from_millis(100)));
                return Ok(Produce::More);
            }
        }
        out.send_bytes(*index, *stamp, data)?;
        if *stamp >= self.promised_ns.saturating_add(PROMISE_EVERY_NS) {
            out.promise(*stamp)?;
            self.promised_ns = *stamp;
        }
        self.next += 1;
        if self.last_progress.elapsed() > Duration::from_millis(200) {
            self.last_progress = Instant::now();
            report_progress(self.next, self.messages.len());
        }
        Ok(Produce::More)
    }
}

/// Publishes the messages of a recording, each on the output named after its topic.
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
        gprflow_stage::params::positive("speed", params.speed)
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let rec = Recording::open(params.path.as_ref()).map_err(StageError::failed)?;
        let mut messages = Vec::new();
        let (_, stopped) = rec.scan(|m| {
            let name = m.topic.trim_start_matches('/');
            if let Some(i) = ports.outputs().iter().position(|o| o.name == name) {
                messages.push((i, i64::try_from(m.log_time).unwrap_or(i64::MAX), m.data.to_vec()));
            }
        });
        if let Some(at) = stopped {
            tracing::warn!(
                "{}: read stopped early ({at}); replaying the {} messages before it",
                params.path,
                messages.len()
            );
        }
        Ok(Self {
            player: Player::new(messages, params.pace, params.speed),
        })
    }

    fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        self.player.produce(out)
    }
}
