//! The commands behind each `gprflow` subcommand. Each returns the process exit code.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::launch::{self, LaunchEvent, LaunchObserver, LaunchOptions};
use gprflow::record::{self, Recording};
use gprflow::stage::{InputPorts, NodeSpec, bind_signals};

use crate::catalog;

/// Arguments of `gprflow launch`.
#[derive(Debug)]
pub struct LaunchArgs {
    /// Graph file.
    pub graph: PathBuf,
    /// `key=value` overrides.
    pub set: Vec<String>,
    /// Record to this file.
    pub record: Option<PathBuf>,
    /// Topics to record instead of the graph's `record:` list.
    pub record_topics: Vec<String>,
    /// Only this host's nodes.
    pub host: Option<String>,
    /// Seconds to wait for the other hosts.
    pub remote_timeout_s: f64,
    /// Topic buffer depth.
    pub buffer: usize,
    /// Plan only.
    pub dry_run: bool,
    /// Write the processes' end-of-run reports here (JSON).
    pub report: Option<PathBuf>,
    /// Log filter, handed on to the stages.
    pub log: String,
    /// Named bus.
    pub bus: Option<String>,
    /// Source nodes fed from outside the run.
    pub external: Vec<String>,
    /// Start-up handshake limit, seconds.
    pub handshake_timeout_s: f64,
}

fn seconds_arg(flag: &str, value: f64) -> Result<std::time::Duration> {
    if !(value.is_finite() && value > 0.0) {
        bail!("{flag} {value}: must be a positive number of seconds");
    }
    Ok(std::time::Duration::from_secs_f64(value.min(1e6)))
}

fn parse_overrides(set: &[String]) -> Result<Vec<(String, String)>> {
    set.iter()
        .map(|kv| {
            kv.split_once('=')
                .map(|(k, v)| (k.trim().to_owned(), v.to_owned()))
                .with_context(|| format!("--set `{kv}`: expected KEY=VALUE"))
        })
        .collect()
}

/// Shows logs and a progress bar while a graph runs.
struct Console {
    bar: indicatif::ProgressBar,
}

impl LaunchObserver for Console {
    fn event(&mut self, event: LaunchEvent<'_>) {
        match event {
            LaunchEvent::Started { node, pid } => tracing::debug!("started {node} (pid {pid})"),
            LaunchEvent::Progress { node, done, total } => {
                if self.bar.length() != Some(total) {
                    self.bar.set_length(total);
                    self.bar.set_message(format!("{node}: messages"));
                }
                self.bar.set_position(done);
            }
            LaunchEvent::Log { node, line } => self.bar.suspend(|| eprintln!("[{node}] {line}")),
            LaunchEvent::Exited { node, status } => tracing::debug!("{node}: {status}"),
            LaunchEvent::Stopping { reason } => self.bar.suspend(|| eprintln!("stopping all stages: {reason}")),
        }
    }
}

/// `gprflow launch`.
///
/// # Errors
/// Graph, plan and start-up errors.
pub fn launch(args: &LaunchArgs) -> Result<ExitCode> {
    let overrides = parse_overrides(&args.set)?;
    let graph = gprflow::graph::load(&args.graph, &overrides, &catalog())?;
    let exe = std::env::current_exe().context("cannot find the gprflow executable")?;
    let mut opts = LaunchOptions::new(exe);
    opts.record.clone_from(&args.record);
    opts.host.clone_from(&args.host);
    opts.remote_timeout = seconds_arg("--remote-timeout-s", args.remote_timeout_s)?;
    opts.handshake_timeout = seconds_arg("--handshake-timeout-s", args.handshake_timeout_s)?;
    opts.bus.clone_from(&args.bus);
    opts.external.clone_from(&args.external);
    opts.record_topics.clone_from(&args.record_topics);
    opts.buffer = args.buffer.max(1);
    opts.log_filter = Some(args.log.clone());
    let plan = launch::plan(&graph, &opts)?;
    if args.dry_run {
        let specs: Vec<&NodeSpec> = plan.nodes.iter().map(|(s, _)| s).collect();
        writeln!(std::io::stdout().lock(), "{}", serde_json::to_string_pretty(&specs)?)?;
        return Ok(ExitCode::SUCCESS);
    }
    let stop = bind_signals().context("cannot install signal handlers")?;
    eprintln!(
        "gprflow: graph `{}` run {} ({} processes)",
        graph.name,
        plan.run_id,
        plan.nodes.len()
    );
    if let (Some(bus), false) = (&args.bus, plan.external.is_empty()) {
        let topics: Vec<&str> = plan
            .external
            .iter()
            .filter(|t| t.readers > 0)
            .map(|t| t.config.name.as_str())
            .collect();
        eprintln!(
            "gprflow: waiting up to {:.0} s for {} on bus `{bus}` (gprflow replay FILE --bus {bus})",
            args.handshake_timeout_s,
            topics.join(", ")
        );
    }
    let bar = indicatif::ProgressBar::with_draw_target(None, indicatif::ProgressDrawTarget::stderr());
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} {wide_bar} {pos}/{len} [{elapsed_precise}<{eta_precise}]")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut console = Console { bar };
    let report = launch::launch(&plan, &opts, &stop, &mut console)?;
    console.bar.finish_and_clear();
    for n in &report.nodes {
        let failed_first = report.first_failure.as_deref() == Some(&n.node);
        if failed_first {
            eprintln!(
                "error: node `{}` failed ({}); last lines of its stderr:",
                n.node,
                n.describe()
            );
            for l in &n.stderr_tail {
                eprintln!("  | {l}");
            }
        } else if !n.succeeded() && !n.stopped_by_launcher {
            eprintln!("error: node `{}` ended with {}", n.node, n.describe());
        }
    }
    if let Some(path) = &args.report {
        write_run_report(path, &graph.name, &report)?;
    }
    if !report.cleaned_up.is_empty() {
        eprintln!(
            "removed {} stale shared-memory resources of run {}",
            report.cleaned_up.len(),
            report.run_id
        );
    }
    if report.succeeded() {
        eprintln!(
            "graph `{}` finished in {:.2} s ({} processes)",
            graph.name,
            report.wall.as_secs_f64(),
            report.nodes.len()
        );
        if let Some(r) = &args.record {
            eprintln!("recorded {}", r.display());
        }
        Ok(ExitCode::SUCCESS)
    } else if report.interrupted {
        eprintln!("interrupted");
        Ok(ExitCode::from(130))
    } else {
        Ok(ExitCode::from(1))
    }
}

/// Writes what every process of a run reported at its end, and the run's wall time, to
/// `path` (JSON).
fn write_run_report(path: &Path, graph: &str, report: &launch::LaunchReport) -> Result<()> {
    let nodes: Vec<serde_json::Value> = report
        .nodes
        .iter()
        .map(|n| {
            serde_json::json!({
                "node": n.node,
                "ended": n.describe(),
                "report": n.report,
            })
        })
        .collect();
    let json = serde_json::json!({
        "graph": graph,
        "run_id": report.run_id,
        "succeeded": report.succeeded(),
        "wall_s": report.wall.as_secs_f64(),
        "nodes": nodes,
    });
    std::fs::write(path, serde_json::to_string_pretty(&json)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))
}

/// `gprflow stage`.
///
/// # Errors
/// Unreadable spec or the stage's error.
pub fn stage(kind: &str, spec_file: &Path) -> Result<ExitCode> {
    let text = std::fs::read_to_string(spec_file).with_context(|| format!("cannot read {}", spec_file.display()))?;
    let spec: NodeSpec =
        serde_json::from_str(&text).with_context(|| format!("{}: not a node spec", spec_file.display()))?;
    let stop = bind_signals().context("cannot install signal handlers")?;
    let report = crate::run_stage(kind, &spec, &stop).with_context(|| format!("node `{}` ({kind})", spec.node))?;
    gprflow::stage::hand_report(&report);
    Ok(ExitCode::SUCCESS)
}

/// `gprflow inspect`.
///
/// # Errors
/// Unreadable recording.
pub fn inspect(file: &Path, json: bool, dump_json: bool) -> Result<ExitCode> {
    if file.is_dir() && file.join("manifest.json").exists() {
        return inspect_map(file, json);
    }
    let rec = Recording::open(file)?;
    let mut out = std::io::stdout().lock();
    if dump_json {
        let mut failed = None;
        let (_, stopped) = rec.scan(|m| {
            if failed.is_some() {
                return;
            }
            let message = gprflow::msg::decode_to_json(m.msg_type, m.data)
                .unwrap_or_else(|e| serde_json::json!({ "decode_error": e.to_string() }));
            let line = serde_json::json!({
                "topic": m.topic, "sequence": m.sequence, "log_time": m.log_time,
                "schema": m.msg_type, "message": message,
            });
            if let Err(e) = writeln!(out, "{line}") {
                failed = Some(e);
            }
        });
        if let Some(e) = failed {
            return Err(e.into());
        }
        if let Some(at) = stopped {
            eprintln!(
                "warning: {}: reading stopped early {at}; run `gprflow recover`",
                file.display()
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    let summary = record::inspect(&rec);
    if json {
        writeln!(out, "{}", serde_json::to_string_pretty(&summary)?)?;
    } else {
        let span = (summary.end_ns.saturating_sub(summary.start_ns)) as f64 * 1e-9;
        writeln!(out, "file:      {} ({} bytes)", summary.path, summary.bytes)?;
        writeln!(out, "messages:  {} over {:.3} s", summary.messages, span)?;
        if let Some(m) = summary.metadata.get("gprflow") {
            let get = |k: &str| m.get(k).map_or("?", String::as_str);
            writeln!(
                out,
                "run:       {} graph `{}` ({}), gprflow {} ({})",
                get("run_id"),
                get("graph_name"),
                get("graph_file"),
                get("version"),
                get("commit")
            )?;
        }
        if !summary.attachments.is_empty() {
            writeln!(out, "attached:  {}", summary.attachments.join(", "))?;
        }
        writeln!(
            out,
            "{:<28} {:<32} {:>8} {:>10} {:>9}",
            "topic", "type", "count", "rate Hz", "problems"
        )?;
        for t in &summary.topics {
            let problems = match (t.decode_errors, t.seq_gaps) {
                (0, 0) => String::new(),
                (d, g) => format!("{d} undecodable, {g} seq gaps"),
            };
            writeln!(
                out,
                "{:<28} {:<32} {:>8} {:>10.2} {problems}",
                t.topic, t.msg_type, t.count, t.rate_hz
            )?;
        }
        for (topic, seq, e) in &summary.decode_errors {
            writeln!(out, "decode error: {topic} seq {seq}: {e}")?;
        }
    }
    if let Some(at) = &summary.truncated {
        eprintln!(
            "warning: {}: reading stopped early {at}; every complete chunk before it was read. `gprflow recover` rewrites it.",
            file.display()
        );
        return Ok(ExitCode::from(1));
    }
    if !summary.decode_errors.is_empty() {
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

/// `gprflow recover`.
///
/// # Errors
/// Unreadable input or unwritable output.
pub fn recover(file: &Path, output: &Path) -> Result<ExitCode> {
    if file == output {
        bail!("refusing to overwrite {} in place; give another output", file.display());
    }
    let (kept, stopped) = record::recover(file, output)?;
    match stopped {
        Some(at) => eprintln!(
            "recovered {kept} messages into {} (the input stopped {at})",
            output.display()
        ),
        None => eprintln!(
            "{} was complete; rewrote {kept} messages into {}",
            file.display(),
            output.display()
        ),
    }
    Ok(ExitCode::SUCCESS)
}

/// `gprflow stages`.
///
/// # Errors
/// Output errors.
pub fn stages() -> Result<ExitCode> {
    let mut out = std::io::stdout().lock();
    for s in catalog().iter() {
        writeln!(out, "{:<12} {}", s.name(), s.about())?;
        match s.inputs() {
            InputPorts::Any => writeln!(out, "    in:  any topics")?,
            InputPorts::Fixed(inputs) => {
                for i in inputs {
                    writeln!(
                        out,
                        "    in:  {} ({}){}",
                        i.port.name,
                        i.port.msg_type,
                        if i.optional { ", optional" } else { "" }
                    )?;
                }
            }
        }
        match s.outputs(&serde_json::Value::Null) {
            Ok(outputs) => {
                for o in outputs {
                    writeln!(out, "    out: {} ({})", o.name, o.msg_type)?;
                }
            }
            // required parameters (a source's file): `gprflow check` on a graph lists them
            Err(e) => writeln!(out, "    out: known once its parameters are given ({e})")?,
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `gprflow check`.
///
/// # Errors
/// The graph's first error.
pub fn check(graph: &Path, set: &[String]) -> Result<ExitCode> {
    let g = gprflow::graph::load(graph, &parse_overrides(set)?, &catalog())?;
    eprintln!(
        "{}: graph `{}` is valid ({} nodes, {} topics)",
        graph.display(),
        g.name,
        g.nodes.len(),
        g.topics().len()
    );
    Ok(ExitCode::SUCCESS)
}

/// `gprflow lgpr-merge FROM... --into MAP`: each store's columns added to `MAP` as one more
/// pass.
///
/// # Errors
/// A store that is `MAP` itself, that cannot be read whole or whose samples differ from
/// `MAP`'s; a write that fails.
pub fn lgpr_merge(from: &[PathBuf], into: &Path) -> Result<ExitCode> {
    use gprflow_lgpr::map::{MapReader, MapWriter};
    let same = |a: &Path| match (a.canonicalize(), into.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    for dir in from {
        if same(dir) {
            bail!("{}: cannot add a map to itself", dir.display());
        }
        let reader = MapReader::open(dir)?;
        let info = reader.info();
        let mut writer = MapWriter::open(into, info.tile_m, info.samples, info.sample_interval_ns)?;
        let added = writer.add_map(&reader)?;
        let after = writer.finish()?;
        writeln!(
            std::io::stdout().lock(),
            "{}: {added} columns ({:.1} m) added to {}: {} passes, {} columns, {:.1} m",
            dir.display(),
            info.length_m,
            into.display(),
            after.passes,
            after.columns,
            after.length_m
        )?;
    }
    Ok(ExitCode::SUCCESS)
}

/// `gprflow inspect MAP_DIR`: an LGPR map store's manifest, tiles, size per km, and every
/// tile read back (damage reported with the tile, the block and the columns kept).
fn inspect_map(dir: &Path, json: bool) -> Result<ExitCode> {
    use gprflow_lgpr::map::MapReader;
    let map = MapReader::open(dir)?;
    let info = map.info().clone();
    let tiles = map.tiles()?;
    let bytes: u64 = tiles.values().sum();
    let (mut columns, mut damaged) = (0usize, Vec::new());
    let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for key in tiles.keys() {
        let t = map.read_tile(*key, None)?;
        columns += t.columns.len();
        for p in &t.columns.positions {
            (x0, y0, x1, y1) = (x0.min(p[0]), y0.min(p[1]), x1.max(p[0]), y1.max(p[1]));
        }
        if let Some(d) = t.damage {
            damaged.push(d.to_string());
        }
    }
    let km = info.length_m / 1000.0;
    let mb_per_km = if km > 0.0 { bytes as f64 / 1e6 / km } else { 0.0 };
    // what the columns would take as raw 8-bit samples with their headers
    let raw = columns as f64 * (gprflow_lgpr::map::store::COLUMN_HEADER + info.samples as usize) as f64;
    let mut out = std::io::stdout().lock();
    if json {
        let v = serde_json::json!({
            "format": info.format, "version": info.version, "tile_m": info.tile_m, "samples": info.samples,
            "sample_interval_ns": info.sample_interval_ns, "passes": info.passes, "length_m": info.length_m,
            "tiles": tiles.len(), "columns": columns, "bytes": bytes, "mb_per_km": mb_per_km,
            "compression": if bytes > 0 { raw / bytes as f64 } else { 0.0 },
            "bounds_m": [x0, y0, x1, y1], "damaged": damaged,
        });
        writeln!(out, "{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        writeln!(out, "{}: {} version {}", dir.display(), info.format, info.version)?;
        writeln!(
            out,
            "  {} passes, {:.1} m mapped, {} tiles of {} m, {columns} columns of {} samples ({:.4} ns apart)",
            info.passes,
            info.length_m,
            tiles.len(),
            info.tile_m,
            info.samples,
            info.sample_interval_ns
        )?;
        writeln!(
            out,
            "  {:.1} MB on disk, {mb_per_km:.1} MB/km (zstd {:.2}:1 over 8-bit samples)",
            bytes as f64 / 1e6,
            if bytes > 0 { raw / bytes as f64 } else { 0.0 }
        )?;
        if columns > 0 {
            writeln!(out, "  bounds x [{x0:.1}, {x1:.1}] m, y [{y0:.1}, {y1:.1}] m")?;
        }
        for d in &damaged {
            writeln!(out, "  damaged: {d}")?;
        }
    }
    Ok(if damaged.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
