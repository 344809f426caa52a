//! Tests of graph files, against a fake catalog built from test-only stages.

use std::path::{Path, PathBuf};

use proptest::prelude::*;
use serde::Deserialize;
use serde_json::{Value, json};

use super::*;
use gprflow_stage::{InputPorts, InputSpec, ParamError, PortSpec, StageCatalog, StageInfo, parse_params};

const TRACE: &str = "gprflow_msgs/msg/Trace";
const IMU: &str = "sensor_msgs/msg/Imu";

/// A test-only stage kind: fixed ports, parameters checked by `check`, and outputs that
/// are `outputs` or, when `outputs_from_params`, named by `params.channels`.
struct FakeStage {
    name: &'static str,
    inputs: InputPorts,
    outputs: Vec<PortSpec>,
    outputs_from_params: bool,
    check: fn(&Value) -> Result<(), ParamError>,
}

impl FakeStage {
    /// A stage kind with these ports that takes any parameters.
    fn new(name: &'static str, inputs: InputPorts, outputs: &[(&str, &str)]) -> Self {
        Self {
            name,
            inputs,
            outputs: outputs
                .iter()
                .map(|(name, msg_type)| PortSpec::new(name, msg_type))
                .collect(),
            outputs_from_params: false,
            check: |_| Ok(()),
        }
    }

    /// Checks parameters with `check`.
    fn params(mut self, check: fn(&Value) -> Result<(), ParamError>) -> Self {
        self.check = check;
        self
    }

    /// Outputs named by `params.channels`, as a replay's are by its recording.
    fn outputs_from_params(mut self) -> Self {
        self.outputs_from_params = true;
        self
    }
}

impl StageInfo for FakeStage {
    fn name(&self) -> &str {
        self.name
    }

    fn about(&self) -> &str {
        "test stage"
    }

    fn inputs(&self) -> InputPorts {
        self.inputs.clone()
    }

    fn outputs(&self, params: &Value) -> Result<Vec<PortSpec>, ParamError> {
        if !self.outputs_from_params {
            return Ok(self.outputs.clone());
        }
        let channels = params
            .get("channels")
            .and_then(Value::as_object)
            .ok_or_else(|| ParamError {
                path: vec!["channels".to_owned()],
                message: "no channels".to_owned(),
            })?;
        Ok(channels
            .iter()
            .map(|(name, msg_type)| PortSpec::new(name, msg_type.as_str().unwrap_or_default()))
            .collect())
    }

    fn params_schema(&self) -> schemars::Schema {
        schemars::json_schema!({ "type": "object" })
    }

    fn check_params(&self, params: &Value) -> Result<(), ParamError> {
        (self.check)(params)
    }
}

/// Parameters of the fake `toy_source`, as the real one (`stages/toy`) declares them.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct SourceParams {
    count: Option<u64>,
    samples: Option<u32>,
    period_s: Option<f64>,
    start_ns: Option<i64>,
    seed: Option<u64>,
}

/// Parameters of the fake `toy_gain`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct GainParams {
    gain: Option<f64>,
    offset: Option<f64>,
}

/// Parameters of the fake `record`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct RecordParams {
    path: String,
}

/// Parameters of the fake `replay`; `channels` stands in for the recording's channels.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct ReplayParams {
    path: String,
    pace: Option<String>,
    channels: Option<serde_json::Map<String, Value>>,
}

fn input(name: &str, msg_type: &str, optional: bool) -> InputSpec {
    InputSpec {
        port: PortSpec::new(name, msg_type),
        optional,
    }
}

/// The real stage kinds' declarations (toy_source, toy_gain, record, replay), plus two
/// more for multi-input and message-type tests.
fn catalog() -> StageCatalog {
    let none = || InputPorts::Fixed(vec![]);
    [
        // the real stage's value check too (its `check_params`)
        FakeStage::new("toy_source", none(), &[("trace", TRACE)]).params(|p| {
            let source = parse_params::<SourceParams>(p)?;
            gprflow_stage::params::optional("period_s", source.period_s, gprflow_stage::params::non_negative)
        }),
        FakeStage::new(
            "toy_gain",
            InputPorts::Fixed(vec![input("trace", TRACE, false)]),
            &[("trace", TRACE)],
        )
        .params(|p| parse_params::<GainParams>(p).map(drop)),
        FakeStage::new("record", InputPorts::Any, &[]).params(|p| parse_params::<RecordParams>(p).map(drop)),
        FakeStage::new("replay", none(), &[])
            .params(|p| parse_params::<ReplayParams>(p).map(drop))
            .outputs_from_params(),
        FakeStage::new("imu_source", none(), &[("imu", IMU)]),
        FakeStage::new(
            "fuse",
            InputPorts::Fixed(vec![input("trace", TRACE, false), input("imu", IMU, true)]),
            &[("trace", TRACE)],
        ),
    ]
    .into_iter()
    .fold(StageCatalog::new(), |catalog, stage| catalog.with(Box::new(stage)))
}

const TOY: &str = r#"name: toy
inputs: { recording: recordings/toy.mcap, count: "100" }
nodes:
  gen:    { stage: toy_source, params: { count: "${count}" } }
  gain:   { stage: toy_gain, inputs: { trace: gen/trace }, params: { gain: 2.0 } }
  mine:   { exec: ./my_stage, inputs: { trace: gain/trace }, outputs: { trace: gprflow_msgs/msg/Trace } }
  reg:    { stage: toy_gain, inputs: { trace: { from: gain/trace, feedback_delay_s: 0.5 } } }
hosts:
  robot: { nodes: [gen, gain], zenoh: { listen: [tcp/127.0.0.1:7447] } }
  base:  { nodes: [mine, reg], zenoh: { connect: [tcp/127.0.0.1:7447] } }
record: { topics: ["*"] }
"#;

fn parse_text(text: &str) -> Result<Graph, GraphError> {
    parse(text, Path::new("t.yaml"), &[], &catalog())
}

fn parse_with(text: &str, overrides: &[(&str, &str)]) -> Result<Graph, GraphError> {
    let overrides: Vec<(String, String)> = overrides
        .iter()
        .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
        .collect();
    parse(text, Path::new("t.yaml"), &overrides, &catalog())
}

/// Parses `text`, expecting an error; returns it.
#[track_caller]
fn error_of(text: &str) -> GraphError {
    match parse_text(text) {
        Ok(graph) => panic!("expected an error, got a graph with nodes {:?}", graph.nodes),
        Err(error) => error,
    }
}

#[track_caller]
fn assert_kind(text: &str, kind: GraphErrorKind) -> GraphError {
    let error = error_of(text);
    assert_eq!(error.kind(), kind, "{error}");
    error
}

#[track_caller]
fn graph_of(text: &str) -> Graph {
    match parse_text(text) {
        Ok(graph) => graph,
        Err(error) => panic!("{error}"),
    }
}

/// A file with these nodes (one per line, already indented) and nothing else.
fn with_nodes(nodes: &str) -> String {
    format!("name: t\nnodes:\n{nodes}")
}

// ---------------------------------------------------------------- valid graphs

#[test]
fn toy_graph_reads_in_full() {
    let graph = graph_of(TOY);
    assert_eq!(graph.name, "toy");
    assert_eq!(graph.file, PathBuf::from("t.yaml"));
    assert_eq!(graph.text, TOY);
    let names: Vec<&str> = graph.nodes.iter().map(|n| n.name.as_str()).collect();
    assert_eq!(names, ["gen", "gain", "mine", "reg"], "file order");

    let gen_node = graph.node("gen").expect("gen");
    assert_eq!(gen_node.kind, NodeKind::Stage("toy_source".to_owned()));
    assert_eq!(
        gen_node.params,
        json!({ "count": 100 }),
        "whole `${{count}}` becomes a number"
    );
    assert_eq!(gen_node.outputs, [PortSpec::new("trace", TRACE)]);
    assert!(gen_node.inputs.is_empty());

    let gain = graph.node("gain").expect("gain");
    assert_eq!(gain.params, json!({ "gain": 2.0 }));
    assert_eq!(
        gain.inputs,
        [Input {
            name: "trace".to_owned(),
            from_node: "gen".to_owned(),
            from_output: "trace".to_owned(),
            msg_type: TRACE.to_owned(),
            feedback_delay_ns: None,
            latest_only: false,
        }]
    );
    assert_eq!(
        graph.node("reg").expect("reg").params,
        json!({}),
        "absent params: empty object"
    );
    assert!(graph.node("nope").is_none());

    assert_eq!(graph.vars.get("count").map(String::as_str), Some("100"));
    assert_eq!(
        graph.vars.get("recording").map(String::as_str),
        Some("recordings/toy.mcap")
    );
    assert_eq!(
        graph.record,
        Some(RecordDecl {
            topics: vec!["*".to_owned()],
            host: None,
        })
    );
}

#[test]
fn topics_consumers_and_recording() {
    let graph = graph_of(TOY);
    let topics = graph.topics();
    let expected = ["gen/trace", "gain/trace", "mine/trace", "reg/trace"].map(|t| (t.to_owned(), TRACE.to_owned()));
    assert_eq!(topics, expected);

    let consumers: Vec<(&str, &str)> = graph
        .consumers("gain", "trace")
        .iter()
        .map(|(n, i)| (n.name.as_str(), i.name.as_str()))
        .collect();
    assert_eq!(consumers, [("mine", "trace"), ("reg", "trace")]);
    assert!(graph.consumers("gain", "nope").is_empty());
    assert!(graph.consumers("reg", "trace").is_empty());
    assert!(graph.record_matches("gen/trace"));

    let some = graph_of(&TOY.replace(r#"topics: ["*"]"#, r#"topics: ["g*/trace", "mine/*"]"#));
    assert!(some.record_matches("gen/trace"));
    assert!(some.record_matches("gain/trace"));
    assert!(some.record_matches("mine/trace"));
    assert!(!some.record_matches("reg/trace"));
    assert!(!some.record_matches("gen/traces"));

    let none = graph_of(&TOY.replace("record: { topics: [\"*\"] }\n", ""));
    assert_eq!(none.record, None);
    assert!(!none.record_matches("gen/trace"));
}

#[test]
fn hosts_place_nodes() {
    let graph = graph_of(TOY);
    assert_eq!(
        graph.hosts,
        [
            Host {
                name: "robot".to_owned(),
                nodes: vec!["gen".to_owned(), "gain".to_owned()],
                zenoh: ZenohDecl {
                    listen: vec!["tcp/127.0.0.1:7447".to_owned()],
                    ..ZenohDecl::default()
                },
            },
            Host {
                name: "base".to_owned(),
                nodes: vec!["mine".to_owned(), "reg".to_owned()],
                zenoh: ZenohDecl {
                    listen: vec![],
                    connect: vec!["tcp/127.0.0.1:7447".to_owned()],
                    ..ZenohDecl::default()
                },
            },
        ]
    );
    let no_hosts = graph_of(&TOY[..TOY.find("hosts:").unwrap_or(TOY.len())]);
    assert!(no_hosts.hosts.is_empty());

    let with_mode = graph_of(&TOY.replace("zenoh: { connect:", "zenoh: { mode: client, connect:"));
    assert_eq!(with_mode.hosts[1].zenoh.mode.as_deref(), Some("client"));
    let without_zenoh = graph_of(&TOY.replace(", zenoh: { listen: [tcp/127.0.0.1:7447] }", ""));
    assert_eq!(without_zenoh.hosts[0].zenoh, ZenohDecl::default());
}

#[test]
fn long_form_inputs() {
    let graph = graph_of(TOY);
    let reg = graph.node("reg").expect("reg");
    assert_eq!(reg.inputs[0].feedback_delay_ns, Some(500_000_000));
    assert!(!reg.inputs[0].latest_only);
    assert_eq!(reg.inputs[0].topic(), "gain/trace");

    let latest = graph_of(&TOY.replace("feedback_delay_s: 0.5", "latest_only: true"));
    let reg = latest.node("reg").expect("reg");
    assert_eq!(reg.inputs[0].feedback_delay_ns, None);
    assert!(reg.inputs[0].latest_only);

    let error = assert_kind(
        &TOY.replace("feedback_delay_s: 0.5", "feedback_delay: 0.5"),
        GraphErrorKind::Structure,
    );
    assert!(error.to_string().contains("feedback_delay"), "{error}");
    assert_kind(&TOY.replace("from: gain/trace, ", ""), GraphErrorKind::Structure);
}

#[test]
fn inputs_are_sorted_by_name() {
    let graph = graph_of(&with_nodes(
        "  imu: { stage: imu_source }\n  gen: { stage: toy_source }\n  \
         fuse: { stage: fuse, inputs: { trace: gen/trace, imu: imu/imu } }\n",
    ));
    let fuse = graph.node("fuse").expect("fuse");
    let names: Vec<&str> = fuse.inputs.iter().map(|i| i.name.as_str()).collect();
    assert_eq!(names, ["imu", "trace"]);
    assert_eq!(fuse.inputs[0].msg_type, IMU);
    // `imu` is optional.
    graph_of(&with_nodes(
        "  gen: { stage: toy_source }\n  fuse: { stage: fuse, inputs: { trace: gen/trace } }\n",
    ));
}

#[test]
fn exec_nodes_declare_outputs_and_take_any_inputs() {
    let graph = graph_of(&with_nodes(
        "  gen: { stage: toy_source }\n  imu: { stage: imu_source }\n  \
         mine: { exec: ./my_stage --fast, inputs: { a: gen/trace, b: imu/imu }, \
         outputs: { z: pkg/msg/Z, a: gprflow_msgs/msg/Trace }, params: { k: 1 } }\n",
    ));
    let mine = graph.node("mine").expect("mine");
    assert_eq!(mine.kind, NodeKind::Exec("./my_stage --fast".to_owned()));
    assert_eq!(
        mine.outputs,
        [PortSpec::new("z", "pkg/msg/Z"), PortSpec::new("a", TRACE)],
        "file order"
    );
    assert_eq!(mine.inputs[1].msg_type, IMU);
    assert_eq!(mine.params, json!({ "k": 1 }));

    // No outputs at all is fine for an exec node (a sink).
    let sink = graph_of(&with_nodes(
        "  gen: { stage: toy_source }\n  sink: { exec: ./sink, inputs: { x: gen/trace } }\n",
    ));
    assert!(sink.node("sink").expect("sink").outputs.is_empty());
}

#[test]
fn record_stage_takes_any_inputs() {
    let graph = graph_of(&with_nodes(
        "  gen: { stage: toy_source }\n  imu: { stage: imu_source }\n  \
         rec: { stage: record, inputs: { gen: gen/trace, imu: imu/imu }, params: { path: out.mcap } }\n",
    ));
    assert_eq!(graph.node("rec").expect("rec").inputs.len(), 2);
    assert!(graph.node("rec").expect("rec").outputs.is_empty());
}

#[test]
fn references_split_at_the_first_slash() {
    let graph = graph_of(&with_nodes(
        "  replay: { stage: replay, params: { path: r.mcap, channels: { gen/trace: gprflow_msgs/msg/Trace } } }\n  \
         gain: { stage: toy_gain, inputs: { trace: replay/gen/trace } }\n",
    ));
    let input = &graph.node("gain").expect("gain").inputs[0];
    assert_eq!(
        (input.from_node.as_str(), input.from_output.as_str()),
        ("replay", "gen/trace")
    );
    assert_eq!(graph.topics()[0].0, "replay/gen/trace");
}

#[test]
fn a_cycle_closed_by_a_feedback_input_is_fine() {
    let graph = graph_of(&with_nodes(
        "  gen: { stage: toy_source }\n  \
         mix: { exec: ./mix, inputs: { trace: gen/trace, est: { from: est/trace, feedback_delay_s: 0.25 } }, \
         outputs: { trace: gprflow_msgs/msg/Trace } }\n  \
         est: { stage: toy_gain, inputs: { trace: mix/trace } }\n",
    ));
    let mix = graph.node("mix").expect("mix");
    assert_eq!(mix.inputs[0].name, "est");
    assert_eq!(mix.inputs[0].feedback_delay_ns, Some(250_000_000));
}

#[test]
fn block_style_reads_like_flow_style() {
    let block = "name: toy\ninputs:\n  count: '7'\nnodes:\n  gen:\n    stage: toy_source\n    params:\n      count: ${count}\n  \
                 gain:\n    stage: toy_gain\n    inputs:\n      trace:\n        from: gen/trace\n        latest_only: true\n";
    let graph = graph_of(block);
    assert_eq!(graph.node("gen").expect("gen").params, json!({ "count": 7 }));
    assert!(graph.node("gain").expect("gain").inputs[0].latest_only);
}

// ---------------------------------------------------------------- variables

#[test]
fn variables_substitute_and_override() {
    let text = r#"name: v
inputs: { dir: data, count: "5", label: run, flag: "true" }
nodes:
  gen: { stage: toy_source, params: { count: "${count}" } }
  rec: { stage: record, inputs: { t: gen/trace }, params: { path: "${dir}/${label}.mcap" } }
  mine: { exec: "${dir}/my_stage", params: { list: ["${count}", "n${count}"], nested: { f: "${flag}", l: "${label}" } } }
"#;
    let graph = parse_with(text, &[]).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(graph.node("gen").expect("gen").params, json!({ "count": 5 }));
    assert_eq!(
        graph.node("rec").expect("rec").params,
        json!({ "path": "data/run.mcap" })
    );
    let mine = graph.node("mine").expect("mine");
    assert_eq!(mine.kind, NodeKind::Exec("data/my_stage".to_owned()));
    assert_eq!(
        mine.params,
        json!({ "list": [5, "n5"], "nested": { "f": true, "l": "run" } })
    );

    let graph =
        parse_with(text, &[("count", "12"), ("dir", "/tmp/x"), ("label", "0x")]).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(graph.vars.get("count").map(String::as_str), Some("12"));
    assert_eq!(graph.node("gen").expect("gen").params, json!({ "count": 12 }));
    assert_eq!(
        graph.node("rec").expect("rec").params,
        json!({ "path": "/tmp/x/0x.mcap" })
    );
    assert_eq!(
        graph.node("mine").expect("mine").params["nested"]["l"],
        json!("0x"),
        "not a number: a string"
    );

    // A value that is not a number stays a string, and the stage says so.
    let error = parse_with(text, &[("count", "many")]).expect_err("bad count");
    assert_eq!(error.kind(), GraphErrorKind::BadParam, "{error}");
}

#[test]
fn unknown_variables_are_errors() {
    let text =
        "name: v\ninputs: { count: \"5\" }\nnodes:\n  gen: { stage: toy_source, params: { count: \"${cuont}\" } }\n";
    let error = parse_with(text, &[]).expect_err("error");
    assert_eq!(error.kind(), GraphErrorKind::UnknownVariable);
    assert_eq!(
        error.to_string(),
        "t.yaml:4:46: nodes.gen.params.count: unknown variable `cuont` (variables are: count); declare it under `inputs:`"
    );

    let error = parse_with(&text.replace("cuont", "count"), &[("seed", "3")]).expect_err("error");
    assert_eq!(error.kind(), GraphErrorKind::UnknownVariable);
    assert_eq!(
        error.to_string(),
        "t.yaml:2:1: inputs: `--set seed=...` names no variable of this graph (variables are: count)"
    );

    let error = parse_with(&text.replace("${cuont}", "${count"), &[]).expect_err("error");
    assert_eq!(error.kind(), GraphErrorKind::UnknownVariable);
    assert!(matches!(error, GraphError::UnclosedVariable { .. }), "{error}");

    let exec = "name: v\nnodes:\n  x: { exec: \"${bin}/x\" }\n";
    let error = parse_with(exec, &[]).expect_err("error");
    assert_eq!(error.kind(), GraphErrorKind::UnknownVariable);
    assert_eq!(
        error.location().and_then(|l| l.position),
        Some(Position { line: 3, column: 14 })
    );
    assert!(error.to_string().contains("(variables are: none)"), "{error}");
}

// ---------------------------------------------------------------- one test per error kind

#[test]
fn io_error() {
    let error = load(Path::new("/nonexistent/graph.yaml"), &[], &catalog()).expect_err("error");
    assert_eq!(error.kind(), GraphErrorKind::Io);
    assert!(error.location().is_none());
    assert!(
        error
            .to_string()
            .starts_with("/nonexistent/graph.yaml: cannot read graph file: "),
        "{error}"
    );
}

#[test]
fn load_reads_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("toy.yaml");
    std::fs::write(&path, TOY).expect("write");
    let graph = load(&path, &[("count".to_owned(), "3".to_owned())], &catalog()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(graph.file, path);
    assert_eq!(graph.text, TOY);
    assert_eq!(graph.node("gen").expect("gen").params, json!({ "count": 3 }));
}

#[test]
fn syntax_error() {
    let error = assert_kind("name: t\nnodes:\n  gen: { stage: toy_source\n", GraphErrorKind::Syntax);
    let at = error.location().expect("location");
    assert!(at.position.is_some(), "{error}");
    assert_kind("name: t\n nodes: [\n", GraphErrorKind::Syntax);
    assert_kind("name: t\n\tnodes: {}\n", GraphErrorKind::Syntax);
}

#[test]
fn structure_errors() {
    let error = assert_kind(
        &TOY.replace("inputs: { trace: gen/trace }", "inptus: { trace: gen/trace }"),
        GraphErrorKind::Structure,
    );
    assert_eq!(
        error.location().map(|l| l.key_path.as_str()),
        Some("nodes.gain.inptus"),
        "{error}"
    );
    assert!(error.to_string().contains("inptus"), "{error}");

    // Missing and wrongly typed fields of the format.
    let error = assert_kind("nodes: {}\n", GraphErrorKind::Structure);
    assert_eq!(error.to_string(), "t.yaml:1:1: missing field `name`");
    let error = assert_kind(
        "name: t\nnodes:\n  gen:\n    stage: toy_source\n    inptus: {}\n",
        GraphErrorKind::Structure,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:5:5: nodes.gen.inptus: unknown field `inptus`, expected one of stage, exec, inputs, outputs, params, when"
    );
    let error = assert_kind(
        "name: t\nnodes:\n  gen:\n    exec: ./x\n    inputs: { a: { form: gen/x } }\n",
        GraphErrorKind::Structure,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:5:20: nodes.gen.inputs.a.form: unknown field `form`, expected one of from, feedback_delay_s, latest_only"
    );
    assert_kind("name: t\n", GraphErrorKind::Structure);
    assert_kind("name: t\nnodes: [a, b]\n", GraphErrorKind::Structure);
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source, params: 5 }\n",
        GraphErrorKind::Structure,
    );
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source }\nhosts: { a: { nodes: gen } }\n",
        GraphErrorKind::Structure,
    );
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source }\nhosts: { a: { nodes: [gen], zenoh: { lisen: [] } } }\n",
        GraphErrorKind::Structure,
    );
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source }\nrecord: { topic: [a] }\n",
        GraphErrorKind::Structure,
    );
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source }\n---\nname: u\n",
        GraphErrorKind::Structure,
    );
    assert_kind("", GraphErrorKind::Structure);

    // Exactly one of `stage` and `exec`; `outputs` only with `exec`.
    let error = assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source, exec: ./x }\n",
        GraphErrorKind::Structure,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:3:29: nodes.gen.exec: a node has `stage:` or `exec:`, not both"
    );
    let error = assert_kind("name: t\nnodes:\n  gen: { params: {} }\n", GraphErrorKind::Structure);
    assert_eq!(
        error.to_string(),
        "t.yaml:3:3: nodes.gen: node `gen` needs `stage:` (a stage kind) or `exec:` (an executable)"
    );
    let error = assert_kind(
        "name: t\nnodes:\n  a/b: { stage: toy_source }\n",
        GraphErrorKind::Structure,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:3:3: nodes.a/b: node name `a/b` must be non-empty and without `/`"
    );
    assert_kind(
        "name: t\nnodes:\n  gen: { stage: toy_source, outputs: { a: b } }\n",
        GraphErrorKind::Structure,
    );
}

#[test]
fn unknown_stage() {
    let error = assert_kind(
        &with_nodes("  gen:\n    stage: toy_sauce\n"),
        GraphErrorKind::UnknownStage,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:4:12: nodes.gen.stage: unknown stage `toy_sauce` \
         (stages are: toy_source, toy_gain, record, replay, imu_source, fuse)"
    );
}

#[test]
fn bad_param() {
    let error = assert_kind(&TOY.replace("gain: 2.0", "gian: 2.0"), GraphErrorKind::BadParam);
    let at = error.location().expect("location");
    assert_eq!(at.key_path, "nodes.gain.params.gian");
    assert_eq!(at.position, Some(Position { line: 5, column: 70 }));

    // No key named: points at `params`.
    let error = assert_kind(&TOY.replace("gain: 2.0", "gain: loud"), GraphErrorKind::BadParam);
    let at = error.location().expect("location");
    assert_eq!(at.key_path, "nodes.gain.params");
    assert_eq!(at.position, Some(Position { line: 5, column: 60 }));

    // A missing required parameter: points at the node when it has no `params`.
    let error = assert_kind(&with_nodes("  rep: { stage: replay }\n"), GraphErrorKind::BadParam);
    let at = error.location().expect("location");
    assert_eq!(at.key_path, "nodes.rep.params.path");
    assert_eq!(at.position, Some(Position { line: 3, column: 3 }));

    // Outputs that depend on params fail the same way.
    let error = assert_kind(
        &with_nodes("  rep: { stage: replay, params: { path: x.mcap } }\n"),
        GraphErrorKind::BadParam,
    );
    assert_eq!(
        error.location().map(|l| l.key_path.as_str()),
        Some("nodes.rep.params.channels")
    );
}

#[test]
fn dangling_input() {
    let text = with_nodes("  gen: { stage: toy_source }\n  gain: { stage: toy_gain, inputs: { trace: gen2/trace } }\n");
    let error = assert_kind(&text, GraphErrorKind::DanglingInput);
    assert_eq!(
        error.to_string(),
        "t.yaml:4:45: nodes.gain.inputs.trace: no node `gen2` (nodes are: gen, gain)"
    );

    let text = with_nodes(
        "  gen: { stage: toy_source }\n  gain: { stage: toy_gain, inputs: { trace: { from: gen/trcae } } }\n",
    );
    let error = assert_kind(&text, GraphErrorKind::DanglingInput);
    assert_eq!(
        error.to_string(),
        "t.yaml:4:53: nodes.gain.inputs.trace.from: node `gen` has no output `trcae` (its outputs are: trace)"
    );
}

#[test]
fn missing_input() {
    let error = assert_kind(
        &with_nodes("  gen: { stage: toy_source }\n  gain: { stage: toy_gain }\n"),
        GraphErrorKind::MissingInput,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:4:3: nodes.gain.inputs: stage `toy_gain` needs input `trace` (gprflow_msgs/msg/Trace), which is not wired"
    );
    let error = assert_kind(
        &with_nodes("  imu: { stage: imu_source }\n  fuse: { stage: fuse, inputs: { imu: imu/imu } }\n"),
        GraphErrorKind::MissingInput,
    );
    assert_eq!(
        error.location().and_then(|l| l.position),
        Some(Position { line: 4, column: 24 })
    );
}

#[test]
fn unknown_input() {
    let error = assert_kind(
        &with_nodes(
            "  gen: { stage: toy_source }\n  gain: { stage: toy_gain, inputs: { trace: gen/trace, trcae: gen/trace } }\n",
        ),
        GraphErrorKind::UnknownInput,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:4:56: nodes.gain.inputs.trcae: stage `toy_gain` has no input `trcae` (its inputs are: trace)"
    );
    assert_kind(
        &with_nodes("  gen: { stage: toy_source, inputs: { x: gen/trace } }\n"),
        GraphErrorKind::UnknownInput,
    );
}

#[test]
fn type_mismatch() {
    let text = with_nodes(
        "  imu: { exec: ./imu, outputs: { imu: sensor_msgs/msg/Imu } }\n  gain: { stage: toy_gain, inputs: { trace: imu/imu } }\n",
    );
    let error = assert_kind(&text, GraphErrorKind::TypeMismatch);
    assert_eq!(
        error.to_string(),
        "t.yaml:4:45: nodes.gain.inputs.trace: input `trace` takes gprflow_msgs/msg/Trace but `imu/imu` is sensor_msgs/msg/Imu"
    );
}

#[test]
fn duplicate_names() {
    let error = assert_kind(
        &with_nodes("  gen: { stage: toy_source }\n  gen: { stage: toy_source }\n"),
        GraphErrorKind::DuplicateName,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:4:3: nodes.gen: duplicate key `gen` (first at line 3, column 3)"
    );

    // Anywhere in the file, flow style included.
    let error = assert_kind(
        &TOY.replace("gain: 2.0", "gain: 2.0, gain: 3.0"),
        GraphErrorKind::DuplicateName,
    );
    assert_eq!(
        error.location().map(|l| l.key_path.as_str()),
        Some("nodes.gain.params.gain")
    );
    assert_kind("name: a\nname: b\nnodes: {}\n", GraphErrorKind::DuplicateName);
    assert_kind(&TOY.replace("base:  {", "robot:  {"), GraphErrorKind::DuplicateName);

    // A node on two hosts.
    let error = assert_kind(
        &TOY.replace("[mine, reg]", "[mine, reg, gen]"),
        GraphErrorKind::DuplicateName,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:10:31: hosts.base.nodes.2: node `gen` is already on host `robot`; a node runs on one host"
    );
}

#[test]
fn node_on_no_host() {
    let error = assert_kind(&TOY.replace("[mine, reg]", "[mine]"), GraphErrorKind::NodeOnNoHost);
    assert_eq!(
        error.to_string(),
        "t.yaml:7:3: nodes.reg: node `reg` is on no host (hosts are: robot, base); with `hosts:` every node needs one"
    );
    assert_kind(
        &TOY.replace("hosts:\n  robot", "hosts: {}\nxhosts:\n  robot"),
        GraphErrorKind::Structure,
    );
}

#[test]
fn unknown_host_node() {
    let error = assert_kind(
        &TOY.replace("[mine, reg]", "[mine, reg, gian]"),
        GraphErrorKind::UnknownHostNode,
    );
    assert_eq!(
        error.to_string(),
        "t.yaml:10:31: hosts.base.nodes.2: host `base` lists `gian`, which is not a node (nodes are: gen, gain, mine, reg)"
    );
}

#[test]
fn bad_reference() {
    for reference in ["gen", "gen/", "/trace", "\"\""] {
        let text = with_nodes(&format!(
            "  gen: {{ stage: toy_source }}\n  gain: {{ stage: toy_gain, inputs: {{ trace: {reference} }} }}\n"
        ));
        let error = assert_kind(&text, GraphErrorKind::BadReference);
        assert_eq!(
            error.location().and_then(|l| l.position),
            Some(Position { line: 4, column: 45 }),
            "{error}"
        );
    }
}

#[test]
fn cycles_without_feedback() {
    let text = with_nodes(
        "  gen: { stage: toy_source }\n  \
         mix: { exec: ./mix, inputs: { trace: gen/trace, est: est/trace }, outputs: { trace: gprflow_msgs/msg/Trace } }\n  \
         est: { stage: toy_gain, inputs: { trace: mix/trace } }\n",
    );
    let error = assert_kind(&text, GraphErrorKind::Cycle);
    assert!(
        error
            .to_string()
            .starts_with("t.yaml:5:44: nodes.est.inputs.trace: cycle without a feedback input: mix -> est -> mix"),
        "{error}"
    );

    let self_loop = with_nodes("  gain: { stage: toy_gain, inputs: { trace: gain/trace } }\n");
    let error = assert_kind(&self_loop, GraphErrorKind::Cycle);
    assert!(error.to_string().contains("gain -> gain;"), "{error}");

    let three = with_nodes(
        "  a: { stage: toy_gain, inputs: { trace: c/trace } }\n  \
         b: { stage: toy_gain, inputs: { trace: a/trace } }\n  \
         c: { stage: toy_gain, inputs: { trace: { from: b/trace, latest_only: true } } }\n",
    );
    let error = assert_kind(&three, GraphErrorKind::Cycle);
    assert!(
        error
            .to_string()
            .contains("t.yaml:4:42: nodes.b.inputs.trace: cycle without a feedback input: a -> b -> c -> a;"),
        "{error}"
    );
}

#[test]
fn bad_feedback_delay() {
    for delay in ["0", "-0.5", ".nan", ".inf", "1e-12", "1e300"] {
        let text = TOY.replace("feedback_delay_s: 0.5", &format!("feedback_delay_s: {delay}"));
        let error = assert_kind(&text, GraphErrorKind::BadFeedbackDelay);
        assert_eq!(
            error.location().map(|l| l.key_path.as_str()),
            Some("nodes.reg.inputs.trace.feedback_delay_s")
        );
        assert_eq!(
            error.location().and_then(|l| l.position),
            Some(Position { line: 7, column: 85 }),
            "{error}"
        );
    }
    let tiny = graph_of(&TOY.replace("feedback_delay_s: 0.5", "feedback_delay_s: 1e-9"));
    assert_eq!(tiny.node("reg").expect("reg").inputs[0].feedback_delay_ns, Some(1));
}

#[test]
fn every_kind_has_a_name_that_parses_back() {
    for kind in GraphErrorKind::ALL {
        assert_eq!(kind.name().parse::<GraphErrorKind>(), Ok(kind));
        assert_eq!(kind.to_string(), format!("{kind:?}"));
    }
    assert!("Nope".parse::<GraphErrorKind>().is_err());
}

// ---------------------------------------------------------------- robustness

/// Every prefix of a valid file, cut at each character, parses or fails without panicking.
#[test]
fn truncated_files_never_panic() {
    let catalog = catalog();
    for (cut, _) in TOY.char_indices() {
        let _ = parse(&TOY[..cut], Path::new("t.yaml"), &[], &catalog);
    }
    let deep = "[".repeat(100_000);
    assert!(parse_text(&deep).is_err());
    let deep_map = format!(
        "name: t\nnodes: {{ a: {{ stage: record, params: {}1{} }} }}\n",
        "{ x: ".repeat(10_000),
        " }".repeat(10_000)
    );
    assert!(parse_text(&deep_map).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// Mutated valid files (characters replaced, inserted, removed) never panic.
    #[test]
    fn mutated_files_never_panic(
        edits in prop::collection::vec(
            (any::<prop::sample::Index>(), prop::sample::select(vec![
                "", ":", "{", "}", "[", "]", ",", "-", " ", "\n", "\t", "/", "$", "${", "*", "&a", "*a",
                "\"", "'", "#", "?", "!", "|", ">", "<<", "gen", "0", ".nan", "\u{0}", "é",
            ])),
            1..6,
        ),
    ) {
        let mut text = TOY.to_owned();
        for (index, insert) in edits {
            let boundaries: Vec<usize> = text.char_indices().map(|(i, _)| i).chain([text.len()]).collect();
            let at = boundaries[index.index(boundaries.len())];
            let end = boundaries.iter().copied().find(|&b| b > at).unwrap_or(at);
            // Replace one character (or insert, when `insert` is empty it removes).
            text.replace_range(at..end, insert);
        }
        let _ = parse_text(&text);
    }

    /// Any text never panics.
    #[test]
    fn arbitrary_text_never_panics(text in "[a-z{}\\[\\]:,/ \n\"'$&*!-]{0,200}") {
        let _ = parse_text(&text);
    }
}

// ---------------------------------------------------------------- schema and fixtures

/// The repository root (graphs/ and tests/graphs/ live there).
fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `graphs/graph.schema.json` is generated from the file format's types; regenerate it
/// with `GPRFLOW_UPDATE_SCHEMA=1 cargo test -p gprflow-graph --lib`.
#[test]
fn checked_in_schema_is_current() {
    let path = repo_root().join("graphs/graph.schema.json");
    let generated = serde_json::to_string_pretty(&json_schema()).expect("schema serialises") + "\n";
    if std::env::var_os("GPRFLOW_UPDATE_SCHEMA").is_some() {
        std::fs::write(&path, &generated).expect("write schema");
        return;
    }
    let checked_in = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        checked_in == generated,
        "{} is out of date with the graph file types; regenerate it with \
         `GPRFLOW_UPDATE_SCHEMA=1 cargo test -p gprflow-graph --lib` and commit the result",
        path.display()
    );
}

#[test]
fn schema_describes_the_format() {
    let schema = serde_json::to_value(json_schema()).expect("schema");
    assert_eq!(schema["required"], json!(["name", "nodes"]));
    assert_eq!(schema["additionalProperties"], json!(false));
    let node = &schema["$defs"]["NodeDecl"];
    assert_eq!(node["additionalProperties"], json!(false));
    assert!(node["oneOf"].is_array());
}

/// The fixtures of `tests/graphs/`: `valid-*` files check, `invalid-*` files fail with the
/// kind named on their first line (`# expect: Kind`).
#[test]
fn fixtures_match_their_expectations() {
    let dir = repo_root().join("tests/graphs");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("tests/graphs")
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.extension().is_some_and(|ext| ext == "yaml"))
        .collect();
    paths.sort();
    assert!(paths.len() >= 15, "fixtures: {paths:?}");
    let catalog = catalog();
    for path in paths {
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
        let result = load(&path, &[], &catalog);
        if name.starts_with("valid-") {
            if let Err(error) = result {
                panic!("{name}: {error}");
            }
        } else {
            let text = std::fs::read_to_string(&path).expect("read");
            let expected: GraphErrorKind = text
                .lines()
                .next()
                .and_then(|line| line.strip_prefix("# expect: "))
                .unwrap_or_else(|| panic!("{name}: first line must be `# expect: Kind`"))
                .trim()
                .parse()
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            match result {
                Ok(_) => panic!("{name}: expected {expected}, got a valid graph"),
                Err(error) => {
                    assert_eq!(error.kind(), expected, "{name}: {error}");
                    assert!(
                        error.location().and_then(|l| l.position).is_some(),
                        "{name}: no position: {error}"
                    );
                }
            }
        }
    }
}

// ---------------------------------------------------------------- nodes that run when asked

const WITH_VIEWER: &str = r#"name: t
inputs: { viewer: "false" }
nodes:
  gen:    { stage: toy_source }
  viewer: { stage: toy_gain, inputs: { trace: gen/trace }, when: "${viewer}" }
hosts:
  robot: { nodes: [gen, viewer] }
"#;

#[test]
fn a_node_whose_when_is_false_is_left_out() {
    let off = graph_of(WITH_VIEWER);
    let names: Vec<&str> = off.nodes.iter().map(|n| n.name.as_str()).collect();
    assert_eq!(names, ["gen"]);
    assert_eq!(off.hosts[0].nodes, ["gen"], "and placed on no host");
    let on = parse_with(WITH_VIEWER, &[("viewer", "true")]).expect("graph");
    let names: Vec<&str> = on.nodes.iter().map(|n| n.name.as_str()).collect();
    assert_eq!(names, ["gen", "viewer"]);
}

#[test]
fn reading_from_a_node_that_does_not_run_is_an_error_naming_it() {
    let text = with_nodes(
        "  gen:  { stage: toy_source, when: \"false\" }\n  gain: { stage: toy_gain, inputs: { trace: gen/trace } }\n",
    );
    let error = error_of(&text);
    let message = error.to_string();
    assert!(message.contains("t.yaml:4:"), "{message}");
    assert!(
        message.contains("`gen/trace` comes from node `gen`, whose `when` is false"),
        "{message}"
    );
}

#[test]
fn when_must_be_true_or_false() {
    let error = parse_with(WITH_VIEWER, &[("viewer", "yes please")]).expect_err("not a boolean");
    let message = error.to_string();
    assert!(message.contains("t.yaml:5:"), "{message}");
    assert!(
        message.contains("`when` must be true or false, not `yes please`"),
        "{message}"
    );
}
