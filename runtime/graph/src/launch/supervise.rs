//! Running a plan: one process per node, their logs forwarded, failures stopping the rest,
//! and the report of how each ended.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use gprflow_stage::{NodeSpec, PROGRESS_TAG, REPORT_TAG, RunReport};

use gprflow_bus::iox::{DeclaredTopic, IoxTransport};

use super::{LaunchError, LaunchOptions, POLL, Plan, STDERR_TAIL_LINES, cleanup_run};

/// What the launcher tells its observer.
#[derive(Debug)]
pub enum LaunchEvent<'a> {
    /// A process started.
    Started {
        /// Node.
        node: &'a str,
        /// Process id.
        pid: u32,
    },
    /// A stage reported progress.
    Progress {
        /// Node.
        node: &'a str,
        /// Units done.
        done: u64,
        /// Units in total.
        total: u64,
    },
    /// A line a stage wrote to stderr.
    Log {
        /// Node.
        node: &'a str,
        /// The line.
        line: &'a str,
    },
    /// A process ended.
    Exited {
        /// Node.
        node: &'a str,
        /// How.
        status: &'a str,
    },
    /// Stopping every process (failure or interrupt).
    Stopping {
        /// Why.
        reason: &'a str,
    },
}

/// Receives [`LaunchEvent`]s (progress bars, logs).
pub trait LaunchObserver {
    /// One event.
    fn event(&mut self, event: LaunchEvent<'_>);
}

/// How one process ended.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeOutcome {
    /// Node.
    pub node: String,
    /// Exit code, when it exited.
    pub code: Option<i32>,
    /// Signal, when one killed it.
    pub signal: Option<i32>,
    /// Last lines of its stderr.
    pub stderr_tail: Vec<String>,
    /// Stopped by the launcher (after another failure or an interrupt).
    pub stopped_by_launcher: bool,
    /// What the stage reported at its end (counts, latency, CPU time, peak RSS), when it
    /// finished its run and reported.
    pub report: Option<RunReport>,
}

impl NodeOutcome {
    /// Exited with code 0.
    pub fn succeeded(&self) -> bool {
        self.code == Some(0)
    }

    /// Human description of how it ended.
    pub fn describe(&self) -> String {
        match (self.code, self.signal) {
            (Some(c), _) => format!("exit code {c}"),
            (None, Some(s)) => format!("killed by signal {s}"),
            (None, None) => "unknown".to_owned(),
        }
    }
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct LaunchReport {
    /// Run identifier.
    pub run_id: String,
    /// Every process, in graph order.
    pub nodes: Vec<NodeOutcome>,
    /// Interrupted by SIGINT/SIGTERM.
    pub interrupted: bool,
    /// The first process that failed on its own.
    pub first_failure: Option<String>,
    /// Shared-memory files of the run removed after the processes ended (left by killed
    /// processes).
    pub cleaned_up: Vec<String>,
    /// Wall time.
    pub wall: Duration,
}

impl LaunchReport {
    /// Every process succeeded and nobody interrupted the run.
    pub fn succeeded(&self) -> bool {
        !self.interrupted && self.first_failure.is_none() && self.nodes.iter().all(NodeOutcome::succeeded)
    }
}

struct Running {
    node: String,
    child: Child,
    tail: Arc<Mutex<VecDeque<String>>>,
    report: Arc<Mutex<Option<RunReport>>>,
    reader: Option<std::thread::JoinHandle<()>>,
    status: Option<ExitStatus>,
    stopped_by_launcher: bool,
}

enum Line {
    Log(usize, String),
    Progress(usize, u64, u64),
}

fn spawn(
    spec: &NodeSpec,
    exec: Option<&str>,
    spec_file: &Path,
    opts: &LaunchOptions,
    index: usize,
    lines: SyncSender<Line>,
) -> Result<Running, LaunchError> {
    let mut cmd = match exec {
        Some(e) => Command::new(e),
        None => {
            let mut c = Command::new(&opts.exe);
            c.arg("stage").arg(&spec.stage);
            if let Some(filter) = &opts.log_filter {
                c.arg("--log").arg(filter);
            }
            c
        }
    };
    cmd.arg("--spec")
        .arg(spec_file)
        .stdin(Stdio::null())
        .stdout(Stdio::inherit())
        .stderr(Stdio::piped());
    // SAFETY: the closure runs between fork and exec and only calls prctl, which is
    // async-signal-safe.
    unsafe {
        cmd.pre_exec(|| {
            nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM).map_err(std::io::Error::from)
        });
    }
    let what = match exec {
        Some(e) => format!("node `{}`: cannot start `{e}`", spec.node),
        None => format!("node `{}`: cannot start `{}`", spec.node, opts.exe.display()),
    };
    let mut child = cmd.spawn().map_err(|source| LaunchError::Io { what, source })?;
    let tail = Arc::new(Mutex::new(VecDeque::with_capacity(STDERR_TAIL_LINES)));
    let report = Arc::new(Mutex::new(None));
    let reader = child.stderr.take().map(|stderr| {
        let (tail, report) = (tail.clone(), report.clone());
        std::thread::Builder::new()
            .name(format!("stderr-{}", spec.node))
            .spawn(move || forward_stderr(stderr, index, &tail, &report, &lines))
    });
    let reader = match reader {
        Some(Ok(handle)) => Some(handle),
        Some(Err(source)) => {
            return Err(LaunchError::Io {
                what: "cannot start a log reader thread".to_owned(),
                source,
            });
        }
        None => None,
    };
    Ok(Running {
        node: spec.node.clone(),
        child,
        tail,
        report,
        reader,
        status: None,
        stopped_by_launcher: false,
    })
}

fn forward_stderr(
    stderr: std::process::ChildStderr,
    index: usize,
    tail: &Mutex<VecDeque<String>>,
    report: &Mutex<Option<RunReport>>,
    lines: &SyncSender<Line>,
) {
    for line in BufReader::new(stderr).lines() {
        let Ok(line) = line else { break };
        if let Some(rest) = line.strip_prefix(REPORT_TAG) {
            match serde_json::from_str::<RunReport>(rest.trim()) {
                Ok(r) => *report.lock().unwrap_or_else(PoisonError::into_inner) = Some(r),
                Err(e) => tracing::warn!("a stage's end-of-run report does not read ({e}): {rest}"),
            }
            continue;
        }
        if let Some(rest) = line.strip_prefix(PROGRESS_TAG) {
            let mut nums = rest.split_whitespace().filter_map(|n| n.parse::<u64>().ok());
            if let (Some(done), Some(total)) = (nums.next(), nums.next()) {
                let _ = lines.send(Line::Progress(index, done, total));
            }
            continue;
        }
        {
            let mut t = tail.lock().unwrap_or_else(PoisonError::into_inner);
            if t.len() == STDERR_TAIL_LINES {
                t.pop_front();
            }
            t.push_back(line.clone());
        }
        let _ = lines.send(Line::Log(index, line));
    }
}

fn signal(child: &Child, sig: nix::sys::signal::Signal) {
    if let Ok(pid) = i32::try_from(child.id()) {
        let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), sig);
    }
}

fn drain(rx: &Receiver<Line>, running: &[Running], observer: &mut dyn LaunchObserver) {
    while let Ok(line) = rx.try_recv() {
        match line {
            Line::Log(i, l) => observer.event(LaunchEvent::Log {
                node: &running[i].node,
                line: &l,
            }),
            Line::Progress(i, done, total) => observer.event(LaunchEvent::Progress {
                node: &running[i].node,
                done,
                total,
            }),
        }
    }
}

/// Runs `plan` to the end, or until a process fails or `stop` turns true.
///
/// # Errors
/// [`LaunchError::Io`] when a spec file cannot be written or a process cannot start (the
/// ones already started are stopped first).
pub fn launch(
    plan: &Plan,
    opts: &LaunchOptions,
    stop: &Arc<AtomicBool>,
    observer: &mut dyn LaunchObserver,
) -> Result<LaunchReport, LaunchError> {
    let started = Instant::now();
    let dir = std::env::temp_dir().join(format!("gprflow-{}", plan.run_id));
    std::fs::create_dir_all(&dir).map_err(|source| LaunchError::Io {
        what: format!("cannot create {}", dir.display()),
        source,
    })?;
    // topics published from outside the run are declared with their readers first, so that
    // the outside publisher waits for all of them
    let _declared = declare_external(plan, stop)?;
    let (tx, rx) = sync_channel::<Line>(4096);
    let mut running: Vec<Running> = Vec::new();
    let mut start_error = None;
    for (i, (spec, exec)) in plan.nodes.iter().enumerate() {
        let file = dir.join(format!("{}.json", spec.node));
        let written = serde_json::to_vec_pretty(spec)
            .map_err(std::io::Error::other)
            .and_then(|json| std::fs::write(&file, json));
        if let Err(source) = written {
            start_error = Some(LaunchError::Io {
                what: format!("cannot write {}", file.display()),
                source,
            });
            break;
        }
        match spawn(spec, exec.as_deref(), &file, opts, i, tx.clone()) {
            Ok(r) => {
                observer.event(LaunchEvent::Started {
                    node: &spec.node,
                    pid: r.child.id(),
                });
                running.push(r);
            }
            Err(e) => {
                start_error = Some(e);
                break;
            }
        }
    }
    drop(tx);

    let mut first_failure = None;
    let mut interrupted = false;
    let mut stopping_since: Option<Instant> = None;
    let mut killed = false;
    if start_error.is_some() {
        stopping_since = Some(Instant::now());
        for r in &mut running {
            r.stopped_by_launcher = true;
            signal(&r.child, nix::sys::signal::Signal::SIGTERM);
        }
    }
    while running.iter().any(|r| r.status.is_none()) {
        drain(&rx, &running, observer);
        for r in &mut running {
            if r.status.is_some() {
                continue;
            }
            if let Ok(Some(status)) = r.child.try_wait() {
                r.status = Some(status);
                let outcome = describe_status(status);
                observer.event(LaunchEvent::Exited {
                    node: &r.node,
                    status: &outcome,
                });
                if !status.success() && stopping_since.is_none() && first_failure.is_none() {
                    first_failure = Some(r.node.clone());
                }
            }
        }
        let want_stop = first_failure.is_some() || stop.load(Ordering::Relaxed);
        if want_stop && stopping_since.is_none() {
            interrupted = first_failure.is_none();
            let reason = match &first_failure {
                Some(n) => format!("node `{n}` failed"),
                None => "interrupted".to_owned(),
            };
            observer.event(LaunchEvent::Stopping { reason: &reason });
            stopping_since = Some(Instant::now());
            for r in running.iter_mut().filter(|r| r.status.is_none()) {
                r.stopped_by_launcher = true;
                signal(&r.child, nix::sys::signal::Signal::SIGTERM);
            }
        }
        if let Some(since) = stopping_since
            && !killed
            && since.elapsed() > opts.stop_grace
        {
            killed = true;
            for r in running.iter().filter(|r| r.status.is_none()) {
                signal(&r.child, nix::sys::signal::Signal::SIGKILL);
            }
        }
        std::thread::sleep(POLL);
    }
    for r in &mut running {
        if let Some(h) = r.reader.take() {
            let _ = h.join();
        }
    }
    drain(&rx, &running, observer);
    drop(_declared);
    // a named bus is shared: only what dead processes left is removed
    let cleaned_up = if plan.shared_bus {
        if let Ok(t) = IoxTransport::new("gprflow_cleanup", &plan.prefix, stop.clone()) {
            t.cleanup_dead_nodes();
        }
        Vec::new()
    } else {
        cleanup_run(&plan.prefix)
    };
    let _ = std::fs::remove_dir_all(&dir);
    if let Some(e) = start_error {
        return Err(e);
    }
    Ok(LaunchReport {
        run_id: plan.run_id.clone(),
        nodes: running
            .iter()
            .map(|r| NodeOutcome {
                node: r.node.clone(),
                code: r.status.and_then(|s| s.code()),
                signal: r.status.and_then(|s| s.signal()),
                stderr_tail: r
                    .tail
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .iter()
                    .cloned()
                    .collect(),
                stopped_by_launcher: r.stopped_by_launcher,
                report: r.report.lock().unwrap_or_else(PoisonError::into_inner).take(),
            })
            .collect(),
        interrupted,
        first_failure,
        cleaned_up,
        wall: started.elapsed(),
    })
}

/// Declares the `--external` topics on the run's bus; they stay declared while the result lives.
fn declare_external(
    plan: &Plan,
    stop: &Arc<AtomicBool>,
) -> Result<Option<(IoxTransport, Vec<DeclaredTopic>)>, LaunchError> {
    if plan.external.is_empty() {
        return Ok(None);
    }
    let fail = |e: gprflow_bus::BusError| LaunchError::Plan(format!("--external: {e}"));
    let transport =
        IoxTransport::new(&format!("gprflow_launch_{}", plan.run_id), &plan.prefix, stop.clone()).map_err(fail)?;
    let declared = plan
        .external
        .iter()
        .map(|t| transport.declare(&t.config, t.readers))
        .collect::<Result<Vec<_>, _>>()
        .map_err(fail)?;
    Ok(Some((transport, declared)))
}

fn describe_status(status: ExitStatus) -> String {
    match (status.code(), status.signal()) {
        (Some(c), _) => format!("exit code {c}"),
        (None, Some(s)) => format!("killed by signal {s}"),
        _ => "ended".to_owned(),
    }
}
