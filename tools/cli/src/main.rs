//! `gprflow`: launch graphs, run stages, inspect and recover recordings.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// GPR localisation and mapping pipelines.
#[derive(Debug, Parser)]
#[command(name = "gprflow", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info` or `gprflow=debug`.
    #[arg(long, global = true, default_value = "info")]
    log: String,
}

/// Input formats of `gprflow convert --to mcap`.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum InputFormat {
    /// From the path: a folder is a CMU-GPR sequence, else by extension.
    Auto,
    /// An MCAP recording.
    Mcap,
    /// A CMU-GPR sequence folder.
    CmuGpr,
    /// GSSI SIR .DZT.
    Dzt,
    /// Sensors & Software .DT1 with its .HD.
    Dt1,
}

impl From<InputFormat> for gprflow_ingest::SourceFormat {
    fn from(f: InputFormat) -> Self {
        use gprflow_ingest::SourceFormat as S;
        match f {
            InputFormat::Auto => S::Auto,
            InputFormat::Mcap => S::Mcap,
            InputFormat::CmuGpr => S::CmuGpr,
            InputFormat::Dzt => S::Dzt,
            InputFormat::Dt1 => S::Dt1,
        }
    }
}

/// The bus a command talks on.
#[derive(Debug, clap::Args)]
#[group(required = true, multiple = false)]
struct BusArgs {
    /// A named bus: the one of `gprflow launch ... --bus NAME`.
    #[arg(long, value_name = "NAME")]
    bus: Option<String>,
    /// The bus of one run of `gprflow launch` (without --bus), by the id it printed.
    #[arg(long, value_name = "RUN_ID")]
    run: Option<String>,
}

impl BusArgs {
    fn name(self) -> gprflow_cli::bus::BusName {
        match (self.bus, self.run) {
            (Some(name), _) => gprflow_cli::bus::BusName::Named(name),
            (None, run) => gprflow_cli::bus::BusName::Run(run.unwrap_or_default()),
        }
    }
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run a graph: one process per node, optionally recorded.
    ///
    /// Examples:
    ///   gprflow launch graphs/toy.yaml --set count=500 -o out/toy.mcap
    ///   gprflow launch graphs/localize.yaml -o out/loc.mcap --report out/loc-report.json
    ///   gprflow launch graphs/odometry.yaml --set recording=recordings/sim/basement-forward_backward.mcap -o out/odometry.mcap
    ///   gprflow launch graphs/localize.yaml --dry-run
    ///
    /// Fed from outside: `gprflow launch graphs/localize.yaml --bus live --external ingest`
    /// runs everything but the `ingest` node, whose topics `gprflow replay FILE --bus live`
    /// (or any publisher on bus `live`) then sends; `gprflow record --bus live` records it.
    ///
    /// Across machines, each runs its share: `gprflow launch graphs/toy-hosts.yaml --host robot`
    /// (and `--host base -o out.mcap` on the host that records).
    #[command(verbatim_doc_comment)]
    Launch {
        /// Graph file (YAML).
        graph: PathBuf,
        /// Override a graph input variable: `--set key=value` (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Record the graph's topics to this MCAP file.
        #[arg(short = 'o', long, visible_alias = "output", value_name = "MCAP")]
        record: Option<PathBuf>,
        /// Record these topics (glob patterns, repeatable) instead of the graph's `record:`
        /// list: `--record-topics '*'` records everything.
        #[arg(long, value_name = "GLOB", num_args = 1.., requires = "record")]
        record_topics: Vec<String>,
        /// Run only this host's share of the graph; topics to and from other hosts travel
        /// over zenoh as the graph's `hosts:` section says.
        #[arg(long)]
        host: Option<String>,
        /// With --host: seconds to wait for the other hosts to come up.
        #[arg(long, default_value_t = 120.0)]
        remote_timeout_s: f64,
        /// Frames each topic buffers per subscriber (how far a busy stage may fall behind
        /// before it holds up the stages upstream).
        #[arg(long, default_value_t = gprflow::bus::DEFAULT_BUFFER)]
        buffer: usize,
        /// Check the graph and print the plan without starting anything.
        #[arg(long)]
        dry_run: bool,
        /// Write what every process reported at its end (messages, callback p50/p99, CPU
        /// time, peak RSS) and the run's wall time to this JSON file.
        #[arg(long, value_name = "FILE")]
        report: Option<PathBuf>,
        /// Run on this named bus (shared memory that `gprflow replay`, `gprflow record` and
        /// other runs on the same bus see) instead of one of the run's own.
        #[arg(long, value_name = "NAME")]
        bus: Option<String>,
        /// Do not start this source node: its topics come from another process on the bus
        /// (`gprflow replay`). Repeatable; needs --bus.
        #[arg(long, value_name = "NODE", requires = "bus")]
        external: Vec<String>,
        /// Seconds each process waits for the processes it talks to at start-up (with
        /// --external: for the outside publisher).
        #[arg(long, default_value_t = 30.0, value_name = "SECONDS")]
        handshake_timeout_s: f64,
    },
    /// Run one stage as this process (the launcher uses it).
    ///
    /// Example (the launcher writes the spec):
    ///   gprflow stage toy_gain --spec /tmp/gprflow-1234/gain.json
    #[command(verbatim_doc_comment)]
    Stage {
        /// Stage kind.
        kind: String,
        /// Node spec written by the launcher (JSON).
        #[arg(long)]
        spec: PathBuf,
    },
    /// Publish a recording's topics on a bus, in stamp order, for a graph launched there.
    ///
    /// It waits until the readers the graph declared for each topic have attached (topics the
    /// graph does not read are left out), then sends at the recorded pace (--rate) or as fast
    /// as they take it (--rate max); --loop plays it
    /// until Ctrl-C, which ends every topic cleanly. Examples (`&`: the graph runs beside it,
    /// as from a second terminal; --readers 0: send at once, to whoever listens):
    ///   gprflow launch graphs/toy.yaml --bus live --external gen -o out/toy-live.mcap & gprflow replay recordings/toy.mcap --bus live --topics 'gen/*' --rate max; wait
    ///   gprflow replay recordings/sim/basement-forward_backward.mcap --bus live --readers 0 --rate 4 --end 1
    #[command(verbatim_doc_comment)]
    Replay {
        /// MCAP file.
        file: PathBuf,
        #[command(flatten)]
        bus: BusArgs,
        /// Speed: a factor of the recorded pace (1: as recorded), or `max`: as fast as the
        /// readers take it.
        #[arg(long, default_value = "1", value_name = "X|max")]
        rate: gprflow_cli::bus::Rate,
        /// Play the recording again and again until Ctrl-C (each pass stamped after the one
        /// before).
        #[arg(long = "loop")]
        repeat: bool,
        /// Topics to publish: glob patterns over the recorded names (repeatable; default all).
        #[arg(long, value_name = "GLOB", default_value = "*")]
        topics: Vec<String>,
        /// Publish recorded topic OLD as NEW: `--remap gpr/trace=ingest/gpr` (repeatable).
        #[arg(long, value_name = "OLD=NEW")]
        remap: Vec<String>,
        /// Start this many seconds after the recording's first message.
        #[arg(long, value_name = "SECONDS")]
        start: Option<f64>,
        /// End this many seconds after the recording's first message.
        #[arg(long, value_name = "SECONDS")]
        end: Option<f64>,
        /// Readers to wait for on every topic (default: as many as the graph on the bus
        /// declared; 0: send at once).
        #[arg(long, value_name = "N")]
        readers: Option<usize>,
        /// Seconds to wait for the graph's readers.
        #[arg(long, default_value_t = 60.0, value_name = "SECONDS")]
        wait_s: f64,
    },
    /// Record the topics of a bus (a graph launched with --bus, or one run) to an MCAP file.
    ///
    /// It joins topics as it finds them (recording from then on) and ends when every one has
    /// ended, after --duration-s, or on Ctrl-C (the file is complete either way). Example
    /// (`&`: beside a graph on bus `rec` and a replay that feeds it):
    ///   gprflow launch graphs/toy.yaml --bus rec --external gen & sleep 1; gprflow record --bus rec -o out/bus.mcap & sleep 1; gprflow replay recordings/toy.mcap --bus rec --topics 'gen/*' --rate max; wait
    #[command(verbatim_doc_comment)]
    Record {
        /// Topics to record: glob patterns over `node/output` (default all).
        #[arg(value_name = "GLOB", default_value = "*")]
        topics: Vec<String>,
        #[command(flatten)]
        bus: BusArgs,
        /// Output MCAP file.
        #[arg(short, long, value_name = "MCAP")]
        output: PathBuf,
        /// Stop after this many seconds.
        #[arg(long, value_name = "SECONDS")]
        duration_s: Option<f64>,
        /// Seconds to wait for a first topic to record.
        #[arg(long, default_value_t = 60.0, value_name = "SECONDS")]
        wait_s: f64,
    },
    /// Show a recording's topics, types, counts, rates and time span.
    ///
    /// Examples:
    ///   gprflow inspect recordings/toy.mcap
    ///   gprflow inspect recordings/sim/basement-forward_backward.mcap --json
    #[command(verbatim_doc_comment)]
    Inspect {
        /// MCAP file.
        file: PathBuf,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Print every message decoded, one JSON object per line.
        #[arg(long)]
        dump_json: bool,
    },
    /// Rewrite a recording cut off mid-write into a complete file.
    ///
    /// Example (a complete file is copied as it is):
    ///   gprflow recover recordings/toy.mcap -o out/recovered.mcap
    #[command(verbatim_doc_comment)]
    Recover {
        /// The damaged MCAP file.
        file: PathBuf,
        /// Where to write the recovered file.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// List the stages this build knows, with their ports.
    ///
    /// Example:
    ///   gprflow stages
    #[command(verbatim_doc_comment)]
    Stages,
    /// Simulate a run of a scenario (world, trajectory, sensors) into a recording.
    ///
    /// Examples:
    ///   gprflow sim tools/sim/scenarios/basement.yaml --run loop --duration 20 -o out/basement-loop.mcap
    ///   gprflow sim --schema
    #[command(verbatim_doc_comment)]
    Sim {
        /// Scenario file (YAML; fields in tools/sim/scenarios/README.md).
        #[arg(required_unless_present = "schema")]
        scenario: Option<PathBuf>,
        /// MCAP file to write.
        #[arg(short, long, required_unless_present = "schema")]
        output: Option<PathBuf>,
        /// Which of the scenario's runs (default: the first).
        #[arg(long)]
        run: Option<String>,
        /// Output format.
        #[arg(long, value_enum, default_value = "mcap")]
        format: gprflow_cli::sim::SimFormat,
        /// Stop after this many seconds of sensor time.
        #[arg(long, value_name = "SECONDS")]
        duration: Option<f64>,
        /// Draw the run's sensor noise and vibration afresh: repeat K of the same run in the
        /// same world (0, the default: the scenario's own draw).
        #[arg(long, value_name = "K", default_value_t = 0)]
        repeat: u32,
        /// Print the JSON schema of scenario files and exit.
        #[arg(long)]
        schema: bool,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Accuracy of a run against ground truth: ATE (raw and SE(3)-aligned), RPE, lines.
    ///
    /// Examples:
    ///   gprflow eval recordings/golden/localize.mcap --truth recordings/sim/basement-forward_backward.mcap
    ///   gprflow eval recordings/golden/localize.mcap --truth recordings/sim/basement-forward_backward.mcap --compare odometry=out/odometry.mcap --plot out/localize.png
    ///   gprflow eval recordings/golden/odometry.mcap --truth recordings/sim/garage-loops-60s.mcap --json
    /// (out/odometry.mcap: the odometry graph on the basement sample, as in `gprflow launch --help`)
    #[command(verbatim_doc_comment)]
    Eval {
        /// The run (an MCAP recording).
        run: PathBuf,
        /// Recording holding the ground truth (default: the run itself).
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Estimate topic (default: the run's trajectory, state estimates or odometry).
        #[arg(long)]
        topic: Option<String>,
        /// Ground-truth topic.
        #[arg(long, default_value = gprflow_cli::eval::TRUTH_TOPIC)]
        truth_topic: String,
        /// RPE distance in frames.
        #[arg(long, default_value_t = 1)]
        delta: usize,
        /// Longest truth gap to interpolate over, ms.
        #[arg(long, default_value_t = 200.0)]
        max_gap_ms: f64,
        /// Output format.
        #[arg(long, value_enum, default_value = "text")]
        format: gprflow_cli::eval::ReportFormat,
        /// Print JSON (the same as `--format json`).
        #[arg(long, conflicts_with = "format")]
        json: bool,
        /// Also write the associated poses as PREFIX_est.txt and PREFIX_gt.txt (TUM).
        #[arg(long, value_name = "PREFIX")]
        write_tum: Option<PathBuf>,
        /// Draw the trajectories and the error over time into this PNG.
        #[arg(long, value_name = "PNG")]
        plot: Option<PathBuf>,
        /// Another pose topic of the run to draw (odometry, ...); repeatable.
        #[arg(long, value_name = "TOPIC")]
        also: Vec<String>,
        /// Another run to draw and evaluate beside it (its estimate, e.g. the odometry-only
        /// run of the same recording), as `FILE` or `LABEL=FILE`; repeatable.
        #[arg(long, value_name = "[LABEL=]MCAP")]
        compare: Vec<String>,
    },
    /// Adds LGPR map stores to another, each as one more pass.
    ///
    /// A pass aligned against a map (graphs/lgpr-map-align.yaml) is written to a store of its
    /// own, since its tracker reads the map while it runs; this joins it to the map
    /// (docs/lgpr.md, "A map of two lanes").
    ///
    /// Example (a map of the committed 5 s highway sample, then a copy of it with that pass
    /// twice):
    ///   gprflow launch graphs/lgpr-map.yaml --set map=out/hw5-merge.lgprmap
    ///   gprflow lgpr-merge out/hw5-merge.lgprmap --into out/hw5-twice.lgprmap
    ///   gprflow lgpr-merge out/hw5-merge.lgprmap --into out/hw5-twice.lgprmap
    #[command(verbatim_doc_comment)]
    LgprMerge {
        /// The stores to add.
        #[arg(required = true)]
        from: Vec<PathBuf>,
        /// The store they join (created when missing).
        #[arg(long)]
        into: PathBuf,
    },
    /// LGPR tracking accuracy against the mapping pass (seed 001 eq. 11).
    ///
    /// Along-, cross-track and total RMS over distance for the LGPR and the GPS/INS, lock
    /// share, and the paper's figures (error vs speed, error CDF, error vs correlation, error
    /// vs lateral offset).
    ///
    /// Example (on the runs of the LGPR tour in README.md, which take minutes to make):
    ///   gprflow lgpr-eval out/hw-fixes.mcap --baseline out/hw-map.mcap --plot-dir out/lgpr-figures
    #[command(verbatim_doc_comment)]
    LgprEval {
        /// Tracking runs (recordings of graphs/lgpr-track.yaml: map fixes, truth, GPS/INS).
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// The mapping pass's recording (its truth and GPS/INS).
        #[arg(long)]
        baseline: PathBuf,
        /// Largest true lateral offset from the mapping pass evaluated, m (seed 001: 1.3).
        #[arg(long, default_value_t = 1.3)]
        max_offset_m: f64,
        /// Evaluate this pose topic (a fused estimate, e.g. /estimate/state) instead of the
        /// map fixes, from the run's first locked map fix on (as the fixes are); its lock %
        /// is left empty ("-", JSON null): every pose counts as a fix.
        #[arg(long)]
        topic: Option<String>,
        /// Output format.
        #[arg(long, value_enum, default_value = "text")]
        format: gprflow_cli::eval::ReportFormat,
        /// Print JSON (the same as `--format json`).
        #[arg(long, conflicts_with = "format")]
        json: bool,
        /// Write the figures (PNG) into this directory.
        #[arg(long, value_name = "DIR")]
        plot_dir: Option<PathBuf>,
        /// Write every evaluated fix of each run (stamp, speed, offset, errors, correlation,
        /// lock) as DIR/RUN.csv.
        #[arg(long, value_name = "DIR")]
        samples_dir: Option<PathBuf>,
    },
    /// The wheel's scale against ground truth: the graphs' `wheel_scale` for a rig.
    ///
    /// True ground metres per recorded wheel metre over recordings of one rig: the value for
    /// the graphs' `wheel_scale` variable (ingest's `wheel_scale`); and, with that scale, the
    /// RMS of the wheel's along-track error per period (the estimator's state period by
    /// default), the truth's own noise included: a bound for the estimator's `wheel_sigma_m`.
    ///
    /// Example (tools/scripts/calibrate-wheel.sh calibrates the simulated rig on the training
    /// runs):
    ///   gprflow calibrate-wheel recordings/sim/basement-forward_backward.mcap
    #[command(verbatim_doc_comment)]
    CalibrateWheel {
        /// Recordings with wheel odometry and ground truth.
        #[arg(required = true)]
        recordings: Vec<PathBuf>,
        /// Wheel topic (default: the recording's WheelOdometry topic).
        #[arg(long)]
        wheel_topic: Option<String>,
        /// Ground-truth topic.
        #[arg(long, default_value = gprflow_cli::eval::TRUTH_TOPIC)]
        truth_topic: String,
        /// Longest truth gap to interpolate over, ms.
        #[arg(long, default_value_t = 200.0)]
        max_gap_ms: f64,
        /// Period of the error figure, ms (the estimator's state period).
        #[arg(long, default_value_t = 100.0)]
        period_ms: f64,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Convert a radar file to a recording, or a recording's trajectory to a TUM file.
    ///
    /// The output format comes from the output's extension (.mcap, or .tum/.txt), or `--to`.
    ///
    /// Examples:
    ///   gprflow convert recordings/real-gpr/GSSI_FILE____032.DZT -o out/dzt.mcap
    ///   gprflow convert recordings/sim/basement-forward_backward.mcap --topic /truth/pose -o out/truth.tum
    ///   gprflow convert recordings/real-gpr/SnS_ComOffs_XLINE00.DT1 -o out/dt1.mcap
    /// (a CMU-GPR sequence folder converts the same way)
    #[command(verbatim_doc_comment)]
    Convert {
        /// Input: a CMU-GPR sequence folder, a .DZT, a .DT1 (with its .HD) or a recording.
        input: PathBuf,
        /// Output format: `mcap` (radar files) or `tum` (a recording's trajectory); default
        /// from the output's extension.
        #[arg(long, value_parser = ["mcap", "tum"])]
        to: Option<String>,
        /// Input format for `--to mcap` (default: from the path).
        #[arg(long, value_enum, default_value = "auto")]
        format: InputFormat,
        /// Pose topic to convert to TUM (default: the run's estimate).
        #[arg(long)]
        topic: Option<String>,
        /// Output file.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Draw traces (or one submap) as a radargram picture.
    ///
    /// A PNG with distance, two-way-time and optional depth axes and a colour scale.
    ///
    /// Examples:
    ///   gprflow radargram recordings/sim/basement-forward_backward.mcap --to 30 -o out/basement.png
    ///   gprflow radargram recordings/real-gpr/GSSI_FILE____032.DZT --velocity 0.1 -o out/dzt.png
    ///   gprflow radargram recordings/golden/submaps.mcap --topic /filter/submap --gain none --colormap seismic -o out/submap.png
    #[command(verbatim_doc_comment)]
    Radargram {
        /// Recording, or a radar file (CMU-GPR folder, .DZT, .DT1).
        input: PathBuf,
        /// Submap topic only: the id of the submap to draw (default: the most salient).
        #[arg(long)]
        submap: Option<u32>,
        /// Trace or submap topic (recordings only).
        #[arg(long, default_value = "/gpr/trace")]
        topic: String,
        /// Start, seconds after the first trace.
        #[arg(long, default_value_t = 0.0)]
        from: f64,
        /// End, seconds after the first trace.
        #[arg(long)]
        to: Option<f64>,
        /// Line observations (detected hyperbolas) to draw over the picture (default: the
        /// recording's first LineObservation topic, if any).
        #[arg(long)]
        features: Option<String>,
        /// Draw no line observations.
        #[arg(long, conflicts_with = "features")]
        no_features: bool,
        /// Wave speed in the ground, m/ns, for a depth axis (depth = v t / 2; dry sand about
        /// 0.15, wet soil about 0.06).
        #[arg(long, value_name = "M_PER_NS")]
        velocity: Option<f64>,
        /// Gain with two-way time.
        #[arg(long, value_enum, default_value = "linear")]
        gain: gprflow_viz::Gain,
        /// Percentile of amplitudes at the ends of the colour scale (larger values saturate).
        #[arg(long, default_value_t = 99.0, value_name = "PERCENT")]
        clip: f64,
        /// Colour map.
        #[arg(long, value_enum, default_value = "grey")]
        colormap: gprflow_cli::plot::Colormap,
        /// Keep the mean trace (by default it is subtracted: the direct wave and ringing).
        #[arg(long)]
        keep_background: bool,
        /// PNG to write.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Compare two recordings: exit 0 within tolerance, 1 on a regression, 2 on an error.
    ///
    /// Examples:
    ///   gprflow diff recordings/golden/toy.mcap recordings/golden/toy.mcap
    ///   gprflow diff recordings/golden/localize.mcap out/loc.mcap --abs-tol 1e-6 --json
    #[command(verbatim_doc_comment)]
    Diff {
        /// Reference recording.
        a: PathBuf,
        /// Recording to compare.
        b: PathBuf,
        /// Absolute tolerance for numeric fields.
        #[arg(long, default_value_t = 0.0)]
        abs_tol: f64,
        /// Relative tolerance for numeric fields.
        #[arg(long, default_value_t = 0.0)]
        rel_tol: f64,
        /// Tolerance file instead of the flags (YAML: `default: {abs, rel}` and
        /// `rules: [{topic, field, abs, rel}]`, globs, first match wins).
        #[arg(long, conflicts_with_all = ["abs_tol", "rel_tol"])]
        tolerances: Option<PathBuf>,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Check a graph file without running it (errors name file, line and key).
    ///
    /// Examples:
    ///   gprflow check graphs/toy.yaml
    ///   gprflow check graphs/localize.yaml --set method=learned
    #[command(verbatim_doc_comment)]
    Check {
        /// Graph file.
        graph: PathBuf,
        /// Override a graph input variable.
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Run an experiment file's matrix (worlds x models, with repeats) and print its tables.
    ///
    /// The tables are written between the markers of the markdown file the experiment names.
    ///
    /// Examples:
    ///   gprflow experiment tools/experiments/tables.yaml --dry-run
    ///   gprflow experiment tools/experiments/tables.yaml --variant by_hand --repeats 0 --dry-run
    ///   gprflow experiment tools/experiments/repeats.yaml --set stamps=overlap --reuse --dry-run
    /// (without --dry-run: the localisation tables of docs/results.md, about 20 minutes)
    #[command(verbatim_doc_comment)]
    Experiment {
        /// Experiment file (YAML; its fields are described in tools/experiments/tables.yaml).
        file: PathBuf,
        /// One of the file's variants (e.g. `by_hand`: every world's by_hand run).
        #[arg(long)]
        variant: Option<String>,
        /// Repeats per world instead of the file's.
        #[arg(short = 'n', long, value_name = "N")]
        repeats: Option<u32>,
        /// A graph variable for every model whose graph declares it (repeatable); the runs go
        /// to a folder named after them and the tables are not written.
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Keep the runs whose eval result (JSON) is already there.
        #[arg(long)]
        reuse: bool,
        /// Print the tables only; write nothing into the markdown file.
        #[arg(long)]
        no_write: bool,
        /// Folder for recordings and runs instead of the file's.
        #[arg(short, long, value_name = "DIR")]
        output: Option<PathBuf>,
        /// Print the commands it would run, and stop.
        #[arg(long)]
        dry_run: bool,
    },
    /// Benchmarks.
    #[command(verbatim_doc_comment)]
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
    /// Print a shell completion script.
    ///
    /// Examples:
    ///   gprflow completions bash > out/gprflow.bash
    ///   (then `source out/gprflow.bash`, or install it as
    ///   ~/.local/share/bash-completion/completions/gprflow)
    #[command(verbatim_doc_comment)]
    Completions {
        /// Shell.
        shell: clap_complete::Shell,
    },
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// Solve a problem exported by the GTSAM peer in batch and incrementally; print final
    /// error, ATE and per-update timings.
    ///
    /// Example (`tools/peer/gtsam_problem.py` writes other problems):
    ///   gprflow bench estimate stages/estimate/tests/fixtures/peer_n300.txt --json
    #[command(verbatim_doc_comment)]
    #[command(verbatim_doc_comment)]
    Estimate {
        /// Problem file (`tools/peer/gtsam_problem.py N -o FILE`).
        problem: PathBuf,
        /// Line factors: off, known (true map lines) or estimated (lines are variables).
        #[arg(long, default_value = "off", value_parser = ["off", "known", "estimated"])]
        lines: String,
        /// Batch solve only.
        #[arg(long)]
        batch_only: bool,
        /// Smoother of the incremental run: incremental (partial re-elimination of the whole
        /// graph) or fixed-lag (a window plus full re-solves).
        #[arg(long, default_value = "incremental", value_parser = ["incremental", "fixed-lag"])]
        smoother: String,
        /// Window of the fixed-lag smoother, states.
        #[arg(long, default_value_t = 30)]
        lag: usize,
        /// Fixed-lag smoother: marginalise the states leaving the window into a prior instead
        /// of holding them at their estimate.
        #[arg(long)]
        marginalise: bool,
        /// Feed the incremental run one state every 1/HZ seconds, as a live pipeline would
        /// (the problem's own rate is 10 Hz); default: as fast as the updates go.
        #[arg(long, value_name = "HZ")]
        pace_hz: Option<f64>,
        /// Threads that linearise in the batch solve (1: single-threaded, the benchmark's
        /// figure; more split the factors between threads).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=256))]
        threads: u16,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

/// Keeps memory that the process frees for its own reuse instead of handing it back to the
/// kernel at once. glibc returns a freed block of over 128 KiB (its default mmap threshold,
/// raised to at most 32 MiB as blocks are freed) or a free top of its heap over twice that,
/// so the estimator's re-solves, which build and drop factorisations of tens of MiB, took
/// fresh zeroed pages from the kernel for every solve (page clearing alone was 7 % of the
/// estimator's CPU on a 21-minute localisation run). A process's peak memory is reached
/// either way; what it frees after its peak now stays with it until it exits.
/// `one_arena`: every thread allocates from one arena ([`gprflow_cli::one_malloc_arena`]).
fn keep_freed_memory(one_arena: bool) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const KEEP_BYTES: libc::c_int = 1 << 30;
        // SAFETY: mallopt only sets malloc's parameters; called in main before any other
        // thread exists.
        let (mmap, trim, arenas) = unsafe {
            (
                libc::mallopt(libc::M_MMAP_THRESHOLD, KEEP_BYTES),
                libc::mallopt(libc::M_TRIM_THRESHOLD, KEEP_BYTES),
                if one_arena {
                    libc::mallopt(libc::M_ARENA_MAX, 1)
                } else {
                    1
                },
            )
        };
        if mmap != 1 || trim != 1 || arenas != 1 {
            tracing::debug!(mmap, trim, arenas, "malloc refused a setting (1 on success)");
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    let _ = one_arena;
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter =
        tracing_subscriber::EnvFilter::try_new(&cli.log).unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
    keep_freed_memory(matches!(&cli.command, Command::Stage { kind, .. } if gprflow_cli::one_malloc_arena(kind)));
    use gprflow_cli::commands;
    let result = match cli.command {
        Command::Launch {
            graph,
            set,
            record,
            record_topics,
            host,
            remote_timeout_s,
            buffer,
            dry_run,
            report,
            bus,
            external,
            handshake_timeout_s,
        } => commands::launch(&commands::LaunchArgs {
            graph,
            set,
            record,
            record_topics,
            host,
            remote_timeout_s,
            buffer,
            dry_run,
            report,
            bus,
            external,
            handshake_timeout_s,
            log: cli.log.clone(),
        }),
        Command::Stage { kind, spec } => commands::stage(&kind, &spec),
        Command::Replay {
            file,
            bus,
            rate,
            repeat,
            topics,
            remap,
            start,
            end,
            readers,
            wait_s,
        } => gprflow_cli::bus::replay(&gprflow_cli::bus::ReplayArgs {
            file,
            bus: bus.name(),
            rate,
            loops: u32::from(!repeat),
            topics,
            remap,
            start_s: start,
            end_s: end,
            readers,
            wait_s,
        }),
        Command::Record {
            topics,
            bus,
            output,
            duration_s,
            wait_s,
        } => gprflow_cli::bus::record(&gprflow_cli::bus::RecordArgs {
            topics,
            bus: bus.name(),
            output,
            duration_s,
            wait_s,
        }),
        Command::Inspect { file, json, dump_json } => commands::inspect(&file, json, dump_json),
        Command::Recover { file, output } => commands::recover(&file, &output),
        Command::Stages => commands::stages(),
        Command::Check { graph, set } => commands::check(&graph, &set),
        Command::Eval {
            run,
            truth,
            topic,
            truth_topic,
            delta,
            max_gap_ms,
            format,
            json,
            write_tum,
            plot,
            also,
            compare,
        } => gprflow_cli::eval::eval_command(&gprflow_cli::eval::EvalArgs {
            run,
            truth,
            topic,
            truth_topic,
            delta,
            max_gap_ms,
            format: if json {
                gprflow_cli::eval::ReportFormat::Json
            } else {
                format
            },
            write_tum,
            plot,
            also,
            compare,
        }),
        Command::LgprMerge { from, into } => gprflow_cli::commands::lgpr_merge(&from, &into),
        Command::LgprEval {
            runs,
            baseline,
            max_offset_m,
            topic,
            format,
            json,
            plot_dir,
            samples_dir,
        } => gprflow_cli::lgpr_eval::lgpr_eval_command(&gprflow_cli::lgpr_eval::LgprEvalArgs {
            runs,
            baseline,
            max_offset_m,
            topic,
            format: if json {
                gprflow_cli::eval::ReportFormat::Json
            } else {
                format
            },
            plot_dir,
            samples_dir,
        }),
        Command::CalibrateWheel {
            recordings,
            wheel_topic,
            truth_topic,
            max_gap_ms,
            period_ms,
            json,
        } => gprflow_cli::calibrate::calibrate_wheel(&gprflow_cli::calibrate::CalibrateWheelArgs {
            recordings,
            wheel_topic,
            truth_topic,
            max_gap_ms,
            period_ms,
            json,
        }),
        Command::Convert {
            input,
            to,
            format,
            topic,
            output,
        } => match gprflow_cli::convert::output_format(to.as_deref(), &output) {
            Ok(gprflow_cli::convert::OutputFormat::Mcap) => {
                gprflow_cli::convert::convert_to_mcap(&input, format.into(), &output)
            }
            Ok(gprflow_cli::convert::OutputFormat::Tum) => {
                gprflow_cli::eval::convert_to_tum(&input, topic.as_deref(), &output)
            }
            Err(e) => Err(e),
        },
        Command::Radargram {
            input,
            submap,
            topic,
            from,
            to,
            features,
            no_features,
            velocity,
            gain,
            clip,
            colormap,
            keep_background,
            output,
        } => gprflow_cli::radargram::radargram_command(&gprflow_cli::radargram::RadargramRequest {
            input: &input,
            topic: &topic,
            window_s: (from, to),
            submap,
            features: features.as_deref(),
            no_features,
            velocity_m_per_ns: velocity,
            gain,
            clip_percentile: clip,
            colormap,
            keep_background,
            output: &output,
        }),
        Command::Diff {
            a,
            b,
            abs_tol,
            rel_tol,
            tolerances,
            json,
        } => match tolerances {
            Some(file) => gprflow::diff::Tolerances::from_file(&file)
                .map_err(anyhow::Error::msg)
                .and_then(|t| gprflow_cli::diff::diff_command(&a, &b, &t, json)),
            None => gprflow_cli::diff::diff_command(
                &a,
                &b,
                &gprflow::diff::Tolerances::uniform(gprflow::diff::Tolerance {
                    abs: abs_tol,
                    rel: rel_tol,
                }),
                json,
            ),
        },
        Command::Sim {
            scenario,
            output,
            run,
            format,
            duration,
            repeat,
            schema,
            json,
        } => gprflow_cli::sim::sim(&gprflow_cli::sim::SimArgs {
            scenario,
            output,
            run,
            format,
            duration_s: duration,
            repeat,
            schema,
            json,
        }),
        Command::Experiment {
            file,
            variant,
            repeats,
            set,
            reuse,
            no_write,
            output,
            dry_run,
        } => gprflow_cli::experiment::parse_sets(&set).and_then(|sets| {
            gprflow_cli::experiment::experiment_command(&gprflow_cli::experiment::ExperimentArgs {
                file,
                choices: gprflow_cli::experiment::plan::Choices {
                    variant,
                    repeats,
                    sets,
                    out: output,
                },
                reuse,
                write: !no_write,
                dry_run,
            })
        }),
        Command::Bench {
            which:
                BenchCommand::Estimate {
                    problem,
                    lines,
                    batch_only,
                    smoother,
                    lag,
                    marginalise,
                    pace_hz,
                    threads,
                    json,
                },
        } => gprflow_cli::bench_estimate::bench_estimate(
            &problem,
            &gprflow_cli::bench_estimate::BenchEstimateArgs {
                lines: match lines.as_str() {
                    "known" => gprflow_estimate::problem::LineMode::Known,
                    "estimated" => gprflow_estimate::problem::LineMode::Estimated,
                    _ => gprflow_estimate::problem::LineMode::Off,
                },
                batch_only,
                fixed_lag: smoother == "fixed-lag",
                lag_states: lag,
                marginalise,
                pace_hz,
                threads: usize::from(threads),
                json,
            },
        ),
        Command::Completions { shell } => {
            clap_complete::generate(
                shell,
                &mut <Cli as clap::CommandFactory>::command(),
                "gprflow",
                &mut std::io::stdout(),
            );
            Ok(ExitCode::SUCCESS)
        }
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", gprflow_cli::error_line(&e));
            ExitCode::from(2)
        }
    }
}
