//! `gprflow replay` and `gprflow record`: a recording published onto a named bus, and a bus's
//! topics written to a recording, by processes of their own beside a launched graph.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use gprflow::bus::iox::{BusTopic, IoxTransport, bus_prefix};
use gprflow::bus::{Delivery, Inbox, Transport, glob_matches};
use gprflow::record::{ChannelId, Recorder, Recording, ReplayStage, RunMetadata};
use gprflow::stage::{NodeSpec, OutputBinding, bind_signals, run_node, show_progress_with};

/// Which bus a command talks on.
#[derive(Debug, Clone)]
pub enum BusName {
    /// A named bus (`launch --bus NAME`).
    Named(String),
    /// The bus of one run, by its id (printed by `launch`).
    Run(String),
}

impl BusName {
    fn prefix(&self) -> Result<String> {
        match self {
            Self::Named(name) => bus_prefix(name).map_err(anyhow::Error::msg),
            Self::Run(id) if !id.is_empty() && id.bytes().all(|b| b.is_ascii_hexdigit()) => Ok(format!("gf{id}_")),
            Self::Run(id) => bail!("--run `{id}`: a run id is the hexadecimal id `gprflow launch` prints"),
        }
    }
}

impl std::fmt::Display for BusName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Named(name) => write!(f, "bus `{name}`"),
            Self::Run(id) => write!(f, "the bus of run {id}"),
        }
    }
}

/// How fast `gprflow replay` goes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// As fast as the readers take it.
    Max,
    /// This many times the recorded pace.
    Times(f64),
}

impl std::str::FromStr for Rate {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "max" {
            return Ok(Self::Max);
        }
        match s.parse::<f64>() {
            Ok(x) if x.is_finite() && x > 0.0 => Ok(Self::Times(x)),
            _ => Err(format!("`{s}`: give a speed factor > 0 (1: recorded pace) or `max`")),
        }
    }
}

/// Arguments of `gprflow replay`.
#[derive(Debug)]
pub struct ReplayArgs {
    /// Recording.
    pub file: PathBuf,
    /// Where to publish.
    pub bus: BusName,
    /// Pace.
    pub rate: Rate,
    /// Passes (0: until stopped).
    pub loops: u32,
    /// Topic globs.
    pub topics: Vec<String>,
    /// `OLD=NEW` topic renames.
    pub remap: Vec<String>,
    /// Window start, seconds after the first message.
    pub start_s: Option<f64>,
    /// Window end, seconds after the first message.
    pub end_s: Option<f64>,
    /// Readers to wait for on every topic (default: what the run on the bus declared).
    pub readers: Option<usize>,
    /// How long to wait for the readers.
    pub wait_s: f64,
}

fn parse_remaps(remap: &[String]) -> Result<BTreeMap<String, String>> {
    remap
        .iter()
        .map(|r| {
            let (from, to) = r
                .split_once('=')
                .with_context(|| format!("--remap `{r}`: expected RECORDED_TOPIC=BUS_TOPIC"))?;
            let (from, to) = (from.trim().trim_start_matches('/'), to.trim().trim_start_matches('/'));
            if from.is_empty() || to.is_empty() {
                bail!("--remap `{r}`: both topics must be named");
            }
            Ok((from.to_owned(), to.to_owned()))
        })
        .collect()
}

fn wait_time(flag: &str, seconds: f64) -> Result<Duration> {
    if !(seconds.is_finite() && seconds >= 0.0) {
        bail!("{flag} {seconds}: must be a number of seconds >= 0");
    }
    Ok(Duration::from_secs_f64(seconds.min(1e6)))
}

fn progress_bar(message: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::with_draw_target(None, indicatif::ProgressDrawTarget::stderr());
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} {wide_bar} {pos}/{len} [{elapsed_precise}<{eta_precise}]")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(message.to_owned());
    bar
}

/// `gprflow replay`: publishes a recording's topics on a bus, in stamp order, for a graph
/// launched with `--bus NAME --external NODE` (or any reader on the bus).
///
/// # Errors
/// A recording that cannot be read, no topic to replay, readers that never come, bus errors.
pub fn replay(args: &ReplayArgs) -> Result<ExitCode> {
    let prefix = args.bus.prefix()?;
    let remaps = parse_remaps(&args.remap)?;
    let wait = wait_time("--wait-s", args.wait_s)?;
    gprflow::record::check_window(args.start_s, args.end_s).map_err(|e| anyhow::anyhow!("--{e}"))?;
    let file = args.file.display();
    let rec = Recording::open(&args.file)?;
    let recorded: Vec<(String, String)> = rec
        .topics()
        .into_iter()
        .map(|(topic, ty)| (topic.trim_start_matches('/').to_owned(), ty))
        .collect();
    let chosen: Vec<&(String, String)> = recorded
        .iter()
        .filter(|(topic, _)| args.topics.iter().any(|g| glob_matches(g, topic)))
        .collect();
    if chosen.is_empty() {
        let names: Vec<&str> = recorded.iter().map(|(t, _)| t.as_str()).collect();
        bail!(
            "{file}: no topic matches --topics {} (its topics: {})",
            args.topics.join(" "),
            names.join(", ")
        );
    }
    for from in remaps.keys() {
        if !chosen.iter().any(|(t, _)| t == from) {
            bail!("--remap {from}=...: {file} has no replayed topic `{from}`");
        }
    }

    let stop = bind_signals().context("cannot install signal handlers")?;
    let transport = IoxTransport::new(&format!("gprflow_replay_{}", std::process::id()), &prefix, stop.clone())?;
    // what each topic is called on the bus, and how many readers to wait for: a launch with
    // --external declares all its outside topics before anything starts, one after the other
    // within milliseconds, so once one of ours is declared and the set has stopped growing for
    // DECLARATIONS_SETTLE, those not declared are read by nobody and are left out
    let on_bus = |topic: &String| remaps.get(topic).unwrap_or(topic).clone();
    let started = Instant::now();
    let mut seen: Option<(Vec<Option<usize>>, Instant)> = None;
    let declared: Vec<Option<usize>> = if args.readers.is_some() {
        Vec::new()
    } else {
        loop {
            let found: Vec<Option<usize>> = chosen
                .iter()
                .map(|(topic, _)| transport.declared_readers(&on_bus(topic)))
                .collect();
            if found.iter().any(Option::is_some) {
                match &seen {
                    Some((before, since)) if *before == found => {
                        if since.elapsed() >= DECLARATIONS_SETTLE {
                            break found;
                        }
                    }
                    _ => seen = Some((found, Instant::now())),
                }
            }
            if started.elapsed() > wait {
                let names: Vec<String> = chosen.iter().map(|(t, _)| format!("`{}`", on_bus(t))).collect();
                bail!(
                    "no run on {} reads {} (waited {:.0} s): launch the graph with `--bus NAME --external NODE`, \
                     or give --readers N",
                    args.bus,
                    names.join(", "),
                    wait.as_secs_f64()
                );
            }
            if stop.load(std::sync::atomic::Ordering::Relaxed) {
                return Ok(ExitCode::from(130));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    };
    let on_the_bus = transport.topics()?;
    let mut outputs = Vec::new();
    let mut unread = Vec::new();
    for (i, (topic, msg_type)) in chosen.iter().enumerate() {
        let name = on_bus(topic);
        let readers = match (args.readers, declared.get(i).copied().flatten()) {
            (Some(n), _) | (None, Some(n)) => n,
            (None, None) => {
                unread.push(name);
                continue;
            }
        };
        // the topic's settings are the run's when it declared them
        let bus_topic: Option<&BusTopic> = on_the_bus.iter().find(|t| t.name == name);
        if let Some(ty) = bus_topic.and_then(|d| d.msg_type.as_ref())
            && ty != msg_type
        {
            bail!(
                "{file}: topic `{topic}` holds {msg_type}, but {} reads `{name}` as {ty}",
                args.bus
            );
        }
        outputs.push(OutputBinding {
            name: topic.clone(),
            topic: name,
            msg_type: msg_type.clone(),
            subscribers: readers,
            required_subscribers: readers,
            buffer: bus_topic.map_or(gprflow::bus::DEFAULT_BUFFER, |d| d.buffer),
            latest_only: bus_topic.is_some_and(|d| d.latest_only),
        });
    }
    if !unread.is_empty() {
        eprintln!(
            "gprflow: not replayed (no reader on {}): {}",
            args.bus,
            unread.join(", ")
        );
    }
    let (pace, speed) = match args.rate {
        Rate::Max => ("max", 1.0),
        Rate::Times(x) => ("recorded", x),
    };
    let spec = NodeSpec {
        run_id: format!("replay-{}", std::process::id()),
        prefix,
        node: "replay".to_owned(),
        stage: "replay".to_owned(),
        params: serde_json::json!({
            "path": args.file.display().to_string(),
            "pace": pace,
            "speed": speed,
            "topics": outputs.iter().map(|o| o.name.clone()).collect::<Vec<_>>(),
            "start_s": args.start_s,
            "end_s": args.end_s,
            "loops": args.loops,
        }),
        inputs: Vec::new(),
        outputs,
        handshake_timeout_ms: u64::try_from(wait.saturating_sub(started.elapsed()).as_millis()).unwrap_or(u64::MAX),
    };
    for o in &spec.outputs {
        eprintln!(
            "gprflow: {} -> `{}` on {} ({} readers)",
            o.name, o.topic, args.bus, o.subscribers
        );
    }
    let bar = progress_bar("replay: messages");
    let shown = bar.clone();
    show_progress_with(move |done, total| {
        if total > 0 {
            shown.set_length(total as u64);
        }
        shown.set_position(done as u64);
    });
    let report = run_node::<ReplayStage>(&spec, &transport, &stop);
    bar.finish_and_clear();
    let report = report.with_context(|| format!("replaying {file}"))?;
    let sent: u64 = report.sent.iter().map(|(_, n)| n).sum();
    eprintln!(
        "{} {sent} messages on {} topics in {:.2} s",
        if report.interrupted {
            "stopped after"
        } else {
            "replayed"
        },
        report.sent.len(),
        report.wall_s
    );
    Ok(if report.interrupted {
        ExitCode::from(130)
    } else {
        ExitCode::SUCCESS
    })
}

/// Arguments of `gprflow record`.
#[derive(Debug)]
pub struct RecordArgs {
    /// Topic globs.
    pub topics: Vec<String>,
    /// Where to listen.
    pub bus: BusName,
    /// Output file.
    pub output: PathBuf,
    /// Stop after this many seconds.
    pub duration_s: Option<f64>,
    /// How long to wait for a first topic.
    pub wait_s: f64,
}

/// One topic being recorded.
struct Tap {
    name: String,
    inbox: Inbox,
    /// Its channel in the file, from its first message.
    channel: Option<ChannelId>,
    msg_type: String,
    written: u64,
    /// Connected to the topic's publisher.
    connected: bool,
    /// Its publisher went away without an end of stream reaching this tap (it had sent it
    /// before the tap connected).
    gone: bool,
}

/// How often the bus is looked at for new topics.
const LOOK_EVERY: Duration = Duration::from_millis(100);
/// How long the replay waits for a run's declared outside topics to stop growing (a launch
/// declares them one after the other, within milliseconds of each other).
const DECLARATIONS_SETTLE: Duration = Duration::from_millis(300);

/// `gprflow record`: writes the topics of a bus that match `topics` to an MCAP file, from
/// when it finds them until every one has ended (or Ctrl-C, or `--duration-s`).
///
/// # Errors
/// The file cannot be written, no topic comes, bus errors.
pub fn record(args: &RecordArgs) -> Result<ExitCode> {
    let prefix = args.bus.prefix()?;
    let wait = wait_time("--wait-s", args.wait_s)?;
    let duration = args.duration_s.map(|s| wait_time("--duration-s", s)).transpose()?;
    let stop = bind_signals().context("cannot install signal handlers")?;
    let stopped = || stop.load(std::sync::atomic::Ordering::Relaxed);
    let transport = IoxTransport::new(&format!("gprflow_record_{}", std::process::id()), &prefix, stop.clone())?;
    let meta = RunMetadata {
        graph_name: "record".to_owned(),
        ..RunMetadata::this_build()
    };
    let mut recorder = Recorder::create(&args.output, &meta)?;
    let started = Instant::now();
    let mut taps: Vec<Tap> = Vec::new();
    let mut untyped: Vec<String> = Vec::new();
    let mut looked = None::<Instant>;
    let mut interrupted = false;
    loop {
        if stopped() {
            interrupted = true;
            break;
        }
        if duration.is_some_and(|d| started.elapsed() >= d) {
            break;
        }
        let look = looked.is_none_or(|t| t.elapsed() >= LOOK_EVERY);
        if look {
            looked = Some(Instant::now());
            for topic in transport.topics()? {
                if !args.topics.iter().any(|g| glob_matches(g, &topic.name))
                    || taps.iter().any(|t| t.name == topic.name)
                {
                    continue;
                }
                let Some(msg_type) = topic.msg_type.clone() else {
                    if !untyped.contains(&topic.name) {
                        tracing::warn!("`{}` keeps no message type on the bus: not recorded", topic.name);
                        untyped.push(topic.name.clone());
                    }
                    continue;
                };
                let subscriber = transport.subscriber(&topic.topic_config())?;
                eprintln!("gprflow: joined `{}` ({msg_type})", topic.name);
                taps.push(Tap {
                    name: topic.name.clone(),
                    inbox: Inbox::joining(subscriber, topic.latest_only),
                    channel: None,
                    msg_type,
                    written: 0,
                    connected: false,
                    gone: false,
                });
            }
        }
        // connect to publishers that came since, at every turn: a replay may send its whole
        // topic within milliseconds of starting
        for tap in taps.iter_mut().filter(|t| !t.connected) {
            tap.connected = tap.inbox.observe()?;
        }
        let mut got = false;
        for tap in &mut taps {
            // a bounded batch per topic, so that one busy topic does not starve the others
            for _ in 0..256 {
                match tap.inbox.try_next()? {
                    Some(Delivery::Data(frame)) => {
                        let channel = match tap.channel {
                            Some(c) => c,
                            None => *tap.channel.insert(recorder.add_topic(&tap.name, &tap.msg_type)?),
                        };
                        recorder.write(channel, frame.header.seq, frame.header.stamp_ns, frame.payload())?;
                        tap.written += 1;
                        got = true;
                    }
                    Some(Delivery::Watermark(_)) => got = true,
                    Some(Delivery::EndOfStream) => break,
                    None => {
                        // drained, and the publisher gone (looked at now and then): its end
                        // of stream went before this tap connected
                        if look && tap.connected && !tap.gone && !tap.inbox.ended() && !tap.inbox.observe()? {
                            tap.gone = true;
                            eprintln!(
                                "gprflow: `{}` ended before its end of stream reached the recorder",
                                tap.name
                            );
                        }
                        break;
                    }
                }
            }
        }
        let recording = taps.iter().any(|t| t.channel.is_some());
        // (not on a turn that brought data: a publisher may send its last frames and go
        // between a tap's drain and the look at its publisher)
        if recording && !got && taps.iter().all(|t| t.inbox.ended() || t.gone) {
            break;
        }
        if !recording && started.elapsed() > wait {
            recorder.finish()?;
            bail!(
                "no topic matching {} was published on {} within {:.0} s",
                args.topics.join(" "),
                args.bus,
                wait.as_secs_f64()
            );
        }
        if !got {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    recorder.finish()?;
    for tap in &taps {
        eprintln!(
            "  {:<32} {:>8} messages{}",
            tap.name,
            tap.written,
            if tap.inbox.stats().dropped > 0 {
                format!(" ({} dropped by the latest-only topic)", tap.inbox.stats().dropped)
            } else {
                String::new()
            }
        );
    }
    eprintln!(
        "{} {} topics to {} in {:.2} s",
        if interrupted { "stopped: wrote" } else { "wrote" },
        taps.iter().filter(|t| t.channel.is_some()).count(),
        args.output.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}
