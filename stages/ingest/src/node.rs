//! The `ingest` stage: plays a recording (MCAP, CMU-GPR folder, DZT, DT1/HD) as its raw
//! traces, sweeps, IMU, wheel odometry and ground truth, in stamp order, streamed from disk.
//! Reading and encoding are [`crate::load`]'s; the stage checks its parameters and hands the
//! messages to the player.

use std::path::Path;

use gprflow_record::{Pace, Player, check_window};
use gprflow_stage::params::positive;
use gprflow_stage::{Outputs, ParamError, PortSpec, Ports, Produce, Stage, StageError};

use crate::format::SourceFormat;
use crate::load::{LoadOptions, McapStream, Port, RadarMessages, TopicMap};

/// Parameters of the `ingest` stage.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IngestParams {
    /// The recording: an MCAP file, a CMU-GPR sequence folder, a `.DZT` or a `.DT1`.
    pub source: String,
    /// Its format (default `auto`).
    #[serde(default)]
    pub format: SourceFormat,
    /// `max` (default) or `recorded`.
    #[serde(default)]
    pub pace: Pace,
    /// Speed factor for `recorded` pace (default 1.0).
    #[serde(default = "one")]
    pub speed: f64,
    /// Time between traces when the file has no clock (DZT in wheel mode), s (default 0.01).
    #[serde(default = "default_trace_interval")]
    pub trace_interval_s: f64,
    /// Antenna centre frequency, Hz, when the file does not say (default: 500 MHz for CMU-GPR
    /// folders, the thesis rig's Noggin 500; NaN otherwise).
    #[serde(default)]
    pub center_frequency_hz: Option<f64>,
    /// MCAP sources: the topic behind each output (default: the recording's topic of the
    /// output's type; for sweeps the calibration topic is the one whose name has `calibration`,
    /// for truth the pose topic whose name has `truth`).
    #[serde(default)]
    pub topics: TopicMap,
    /// The wheel's calibration: every wheel distance and speed is multiplied by this (the true
    /// distance per recorded metre; `gprflow calibrate-wheel` measures it on recordings with
    /// ground truth). Default 1: the source's own distances.
    #[serde(default = "one")]
    pub wheel_scale: f64,
    /// Start this many seconds after the recording's first message (default: at it). An MCAP
    /// source seeks there through its chunk index and reads nothing before it.
    #[serde(default)]
    pub start_s: Option<f64>,
    /// Stop this many seconds after the recording's first message (default: at its end).
    #[serde(default)]
    pub end_s: Option<f64>,
}

fn one() -> f64 {
    1.0
}

fn default_trace_interval() -> f64 {
    0.01
}

impl IngestParams {
    /// What the readers of [`crate::load`] need of these parameters.
    fn load_options(&self) -> LoadOptions {
        LoadOptions {
            trace_interval_s: self.trace_interval_s,
            center_frequency_hz: self.center_frequency_hz,
            topics: self.topics.clone(),
            wheel_scale: self.wheel_scale,
        }
    }
}

/// The ingest stage.
#[derive(Debug)]
pub struct IngestStage {
    player: Player,
}

impl Stage for IngestStage {
    type Params = IngestParams;
    const NAME: &'static str = "ingest";
    const ABOUT: &'static str =
        "reads a recording (MCAP, CMU-GPR folder, GSSI DZT, S&S DT1/HD): raw traces, sweeps, IMU, wheel, truth";

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(Port::ALL
            .iter()
            .map(|p| PortSpec::new(p.name(), p.msg_type()))
            .collect())
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        positive("speed", params.speed)?;
        positive("trace_interval_s", params.trace_interval_s)?;
        positive("wheel_scale", params.wheel_scale)?;
        check_window(params.start_s, params.end_s)
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        // port order = output order
        debug_assert!(ports.outputs().iter().zip(Port::ALL).all(|(o, p)| o.name == p.name()));
        let path = Path::new(&params.source);
        let options = params.load_options();
        let format = params.format.resolve(path).map_err(StageError::failed)?;
        if matches!(format, SourceFormat::Mcap | SourceFormat::Auto) {
            // streamed from disk: memory does not grow with the recording
            let stream = McapStream::open(path, &options, params.start_s, params.end_s).map_err(StageError::failed)?;
            tracing::info!("ingest: {}: {}", params.source, stream.summary);
            let total = stream.total();
            let source = stream.map(|(port, stamp, data)| (port as usize, stamp, data));
            return Ok(Self {
                player: Player::streaming(Box::new(source), total, params.pace, params.speed),
            });
        }
        // the rest stream trace by trace (DZT, DT1) or row by row (a CMU-GPR folder, whose files
        // are checked whole first), so memory does not grow with the file; a DZT's start is
        // found without reading what comes before it
        let stream = RadarMessages::open(path, format, &options, params.start_s).map_err(StageError::failed)?;
        tracing::info!("ingest: {}: {}", params.source, stream.summary);
        let total = stream
            .total
            .filter(|_| params.start_s.is_none() && params.end_s.is_none());
        let first = (format == SourceFormat::Dzt).then_some(0);
        let source = window_from_first(stream, first, params.start_s, params.end_s)
            .map(|(port, stamp, data)| (port as usize, stamp, data));
        Ok(Self {
            player: Player::streaming(Box::new(source), total, params.pace, params.speed),
        })
    }

    fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        self.player.produce(out)
    }
}

/// The messages of `source` (in stamp order) from `start_s` to `end_s` seconds after `first`
/// (ns; `None`: its first message's stamp).
fn window_from_first(
    source: impl Iterator<Item = (Port, i64, Vec<u8>)>,
    mut first: Option<i64>,
    start_s: Option<f64>,
    end_s: Option<f64>,
) -> impl Iterator<Item = (Port, i64, Vec<u8>)> {
    source
        .map(move |m| {
            let first = *first.get_or_insert(m.1);
            let at = |s: f64| first.saturating_add((s * 1e9).round() as i64);
            (start_s.map(at), end_s.map(at), m)
        })
        .take_while(|(_, end, m)| end.is_none_or(|e| m.1 < e))
        .filter(|(start, _, m)| start.is_none_or(|s| m.1 >= s))
        .map(|(_, _, m)| m)
}

#[cfg(test)]
mod tests {
    use gprflow_stage::NodeSpec;

    use super::*;

    fn params() -> IngestParams {
        serde_json::from_value(serde_json::json!({"source": "x.dt1"})).expect("parses")
    }

    fn create(params: IngestParams) -> Result<IngestStage, StageError> {
        let spec = NodeSpec {
            run_id: "test".into(),
            prefix: "test".into(),
            node: "ingest".into(),
            stage: "ingest".into(),
            params: serde_json::Value::Null,
            inputs: Vec::new(),
            outputs: Vec::new(),
            handshake_timeout_ms: 0,
        };
        IngestStage::create(params, &Ports::new(&spec))
    }

    #[test]
    fn the_load_options_default_as_the_parameters_do() {
        let (from_params, default) = (params().load_options(), LoadOptions::default());
        assert_eq!(from_params.trace_interval_s, default.trace_interval_s);
        assert_eq!(from_params.center_frequency_hz, default.center_frequency_hz);
        assert_eq!(from_params.wheel_scale, default.wheel_scale);
        assert!(from_params.topics.gpr.is_none() && from_params.topics.truth.is_none());
    }

    #[test]
    fn bad_intervals_and_scales_are_refused_with_the_key() {
        let refused = |p: IngestParams| match IngestStage::check_params(&p) {
            Err(e) => e.to_string(),
            other => panic!("not a parameter error: {other:?}"),
        };
        let e = refused(IngestParams {
            trace_interval_s: 0.0,
            ..params()
        });
        assert!(e.starts_with("trace_interval_s: must be a positive number"), "{e}");
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = refused(IngestParams {
                wheel_scale: bad,
                ..params()
            });
            assert!(e.starts_with("wheel_scale: must be a positive number"), "{e}");
        }
    }

    #[test]
    fn a_cmu_folders_window_is_what_the_whole_folder_gives_from_its_first_message() {
        let dir = tempfile::tempdir().expect("tempdir");
        let rows = |header: &str, from_s: f64| {
            let body: String = (0..10)
                .map(|i| format!("{:.9},{i}\n", from_s + 0.1 * f64::from(i)))
                .collect();
            format!("{header}\n{body}")
        };
        std::fs::write(dir.path().join("gpr_meas.csv"), rows("t,amp_1", 10.05)).expect("write");
        std::fs::write(dir.path().join("we_odom_meas.csv"), rows("t,dist", 10.0)).expect("write");
        let options = LoadOptions::default();
        let whole = crate::load::load(dir.path(), SourceFormat::CmuGpr, &options).expect("loads");
        let first = whole.messages[0].1;
        let at = |s: f64| first + (s * 1e9).round() as i64;
        for (start_s, end_s) in [
            (None, None),
            (Some(0.25), None),
            (Some(0.25), Some(0.6)),
            (None, Some(0.3)),
        ] {
            let want: Vec<_> = whole
                .messages
                .iter()
                .filter(|m| start_s.is_none_or(|s| m.1 >= at(s)) && end_s.is_none_or(|e| m.1 < at(e)))
                .cloned()
                .collect();
            let stream = RadarMessages::open(dir.path(), SourceFormat::CmuGpr, &options, start_s).expect("opens");
            let got: Vec<_> = window_from_first(stream, None, start_s, end_s).collect();
            assert!(!want.is_empty() && got == want, "{start_s:?}..{end_s:?}");
        }
    }

    #[test]
    fn an_unknown_format_fails_the_stage_naming_the_file() {
        match create(IngestParams {
            source: "notes.txt".into(),
            ..params()
        }) {
            Err(StageError::Failed(e)) => assert!(e.to_string().contains("notes.txt: cannot tell the format"), "{e}"),
            other => panic!("not a failure: {other:?}"),
        }
    }
}
