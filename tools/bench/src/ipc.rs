//! The IPC benchmark: one hop between two processes over iceoryx2 and over a Unix socket,
//! next to an in-process copy; on request also over zenoh, to a partner that may run in
//! another network namespace.
//!
//! # Method
//! The driver (this process) starts a partner: itself again (`std::env::current_exe()`) in
//! the hidden `echo` role, with its stdin and stdout as a control channel (one JSON line per
//! phase and per answer) and a Unix stream socket between the two (an abstract address,
//! `@gfb{pid}_uds`, accepted once). Both open an iceoryx2 node under the run's own prefix
//! `gfb{pid}_`. Then, for 4 KiB and 1 MiB payloads and each wait mode, phases run one after
//! the other:
//!
//! - **ping-pong** (latency): the driver sends message `seq`, the partner answers with a
//!   message of the same size, `warmup + count` times. Each round trip is timed from before
//!   the driver fills its request until it has checked the reply; one hop = round trip / 2.
//! - **stream** (throughput): the driver sends `warmup` messages, waits for an
//!   acknowledgement, then sends `count` messages as fast as back-pressure lets it and stops
//!   the clock when the partner acknowledges the last one.
//!
//! Every message is produced and consumed honestly: the sender writes every payload byte (a
//! counter pattern, see [`crate::payload`]) — over iceoryx2 straight into loaned shared
//! memory via `Publisher::send_with` — and the receiver reads one byte per 64-byte cache
//! line (`--touch-stride`) and checks it against the pattern (iceoryx2: in place in shared
//! memory; socket: after reading the whole frame into its buffer). Both processes build
//! their topics from the same function ([`crate::plan::Phase::forward_topic`]); before the
//! first message each subscriber attaches and each publisher waits for the other side's
//! subscriber (`Subscriber::attach`, `bus::wait_for_subscribers`).
//!
//! **zenoh** (`--zenoh-listen ENDPOINT`): the driver opens a zenoh session
//! (`gprflow::bus::zenoh::ZenohTransport`) listening on `ENDPOINT`, then starts a second
//! partner, `echo --zenoh-connect` (`--zenoh-connect`, by default the same endpoint), inside
//! network namespace `--zenoh-partner-netns` through `ip netns exec` when given. That
//! partner serves only the zenoh phases, with the same control channel on its stdin and
//! stdout; the phases are the same ones over the same [`crate::bus_hop::BusEndpoint`]. zenoh
//! copies every payload into its buffers on send and out of them on receive, so its receiver
//! checks a copy rather than the sender's memory.
//!
//! Wait modes: **event** sleeps until woken (`Subscriber::wait`, i.e. the iceoryx2 event
//! service or, over zenoh, a condition variable; a blocking socket read). **spin** (`--spin`)
//! busy-polls `Subscriber::try_receive` or a non-blocking socket. The iceoryx2 publisher
//! sends its wake-up event in both modes. Nothing is pinned to a CPU.
//!
//! In-process baselines: `copy_from_slice` between two preallocated buffers, and writing the
//! pattern alone, each timed one operation at a time.
//!
//! A partner exits when the driver closes its stdin (or dies); SIGINT/SIGTERM stop both
//! cleanly. After both have ended, the driver removes the run's remaining iceoryx2 files
//! (`gprflow::launch::cleanup_run`): iceoryx2 keeps a node-counter segment per prefix on
//! purpose; anything else found there is reported as a leak.

use std::io::{BufRead, BufReader, ErrorKind, Write};
use std::os::linux::net::SocketAddrExt;
use std::os::unix::net::{SocketAddr, UnixListener, UnixStream};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail, ensure};
use gprflow::bus::Transport;
use gprflow::bus::iox::IoxTransport;
use gprflow::bus::zenoh::ZenohTransport;

use crate::IpcArgs;
use crate::bus_hop::{BusEndpoint, Side};
use crate::hop::{self, Outcome};
use crate::memcpy;
use crate::plan::{
    self, Counts, Link, Patience, Phase, Reply, SIZES, TOPIC_BUFFER, Test, WaitMode, ZENOH_KEY_PREFIX, ZenohSetup,
};
use crate::report::{Report, Row, Subject};
use crate::stats::{LatencySummary, Throughput};
use crate::uds_hop::{IO_TIMEOUT, UdsEndpoint};

/// How long the partner may take to start and connect, and to exit at the end.
const PARTNER_TIMEOUT: Duration = Duration::from_secs(10);

/// What a run measures, fixed at start-up.
#[derive(Debug)]
struct RunPlan {
    /// iceoryx2 resource prefix of the run.
    prefix: String,
    /// Abstract name of the Unix socket.
    socket_name: String,
    modes: Vec<WaitMode>,
    counts: Vec<Counts>,
    touch_stride: usize,
    zenoh: Option<ZenohSetup>,
}

impl RunPlan {
    /// The links measured, in table order.
    fn links(&self) -> Vec<Link> {
        let mut links = vec![Link::Iceoryx2, Link::UnixSocket];
        if self.zenoh.is_some() {
            links.push(Link::Zenoh);
        }
        links
    }
}

/// Runs the benchmark and prints the report.
///
/// # Errors
/// Setup failures, a failed phase, or an interrupt.
pub fn run(args: &IpcArgs) -> Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    plan::watch_signals(&stop)?;
    let pid = std::process::id();
    let run_plan = RunPlan {
        prefix: format!("gfb{pid}_"),
        socket_name: format!("gfb{pid}_uds"),
        modes: if args.spin {
            vec![WaitMode::Event, WaitMode::Spin]
        } else {
            vec![WaitMode::Event]
        },
        counts: SIZES.iter().map(|&size| Counts::for_size(size, args)).collect(),
        touch_stride: args.touch_stride.get(),
        zenoh: ZenohSetup::from_args(args),
    };
    let load_before = load_average();

    eprintln!(
        "gprflow-bench ipc: iceoryx2 prefix `{}`, starting the partner process",
        run_plan.prefix
    );
    let measured = measure(&run_plan, &stop);
    // Both processes are gone by now (the partner is reaped even when `measure` failed).
    // iceoryx2 keeps one node-counter segment per prefix on purpose; anything else left
    // means a port was not closed cleanly.
    let removed = gprflow::launch::cleanup_run(&run_plan.prefix);
    let unexpected: Vec<&String> = removed.iter().filter(|p| !p.ends_with(".global_mgmt")).collect();
    if !unexpected.is_empty() {
        eprintln!("warning: the run left iceoryx2 resources behind (now removed): {unexpected:?}");
    }
    let rows = measured?;

    let report = Report {
        quick: args.quick,
        cpus: std::thread::available_parallelism().map_or(0, std::num::NonZero::get),
        load_average: [load_before, load_average()],
        targets: Report::targets_of(&rows, &run_plan.modes),
        counts: run_plan.counts,
        touch_stride_bytes: run_plan.touch_stride,
        topic_buffer: TOPIC_BUFFER,
        zenoh: run_plan.zenoh,
        removed_after_run: removed,
        rows,
    };
    let mut out = std::io::stdout().lock();
    out.write_all(report.markdown().as_bytes())?;
    out.flush()?;
    if let Some(path) = &args.json {
        let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        serde_json::to_writer_pretty(std::io::BufWriter::new(file), &report)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("results written to {}", path.display());
    }
    Ok(())
}

/// Runs every phase with the partner processes and the in-process baselines.
fn measure(run: &RunPlan, stop: &Arc<AtomicBool>) -> Result<Vec<Row>> {
    let mut peers = Peers::start(run, stop)?;
    let patience = Patience::new(Arc::clone(stop), Some(IO_TIMEOUT));
    let links = run.links();

    let mut rows = Vec::new();
    let mut next_id = 0;
    for c in &run.counts {
        for &mode in &run.modes {
            for &link in &links {
                let mut phase = |test, warmup, count| {
                    next_id += 1;
                    Phase {
                        id: next_id,
                        link,
                        test,
                        mode,
                        size: c.size,
                        warmup,
                        count,
                        touch_stride: run.touch_stride,
                    }
                };
                let ping_pong = phase(Test::PingPong, c.round_trip_warmup, c.round_trips);
                let stream = phase(Test::Stream, c.stream_warmup, c.stream_messages);
                let latency = one_hop(peers.run(&ping_pong, &patience)?)?;
                let elapsed = match peers.run(&stream, &patience)? {
                    Outcome::Stream(elapsed) => elapsed,
                    Outcome::RoundTrips(_) => bail!("a stream phase returned round trips"),
                };
                let subject = match link {
                    Link::Iceoryx2 => Subject::Iceoryx2,
                    Link::UnixSocket => Subject::UnixSocket,
                    Link::Zenoh => Subject::Zenoh,
                };
                rows.push(Row {
                    subject,
                    wait: Some(mode),
                    size_bytes: c.size,
                    latency,
                    throughput: Throughput::new(c.stream_messages, c.size, elapsed),
                });
            }
        }
        eprintln!("  {} bytes: in-process copy and fill", c.size);
        let warmup = c.copies / 10;
        for (subject, timed) in [
            (Subject::Memcpy, memcpy::copy(c.size, warmup, c.copies)),
            (Subject::PatternFill, memcpy::fill(c.size, warmup, c.copies)),
        ] {
            let mut samples = timed.samples_ns;
            rows.push(Row {
                subject,
                wait: None,
                size_bytes: c.size,
                latency: LatencySummary::from_ns(&mut samples, 1.0).ok_or_else(|| anyhow!("no samples"))?,
                throughput: Throughput::new(c.copies, c.size, timed.elapsed),
            });
        }
    }
    peers.finish()?;
    Ok(rows)
}

/// The driver's transports and the partner processes at their other ends.
#[derive(Debug)]
struct Peers {
    iox: IoxTransport,
    /// Serves iceoryx2 and the socket.
    local: Partner,
    /// The driver's zenoh session and the partner connected to it.
    zenoh: Option<(ZenohTransport, Partner)>,
}

impl Peers {
    fn start(run: &RunPlan, stop: &Arc<AtomicBool>) -> Result<Self> {
        let local = Partner::spawn_local(&run.prefix, &run.socket_name)?;
        let iox = IoxTransport::new("bench_driver", &run.prefix, Arc::clone(stop))?;
        let zenoh = match &run.zenoh {
            Some(setup) => {
                // Listening before the partner starts connecting.
                let session = ZenohTransport::open(&setup.driver_decl(), ZENOH_KEY_PREFIX, Arc::clone(stop))
                    .with_context(|| format!("zenoh session listening on {}", setup.listen))?;
                eprintln!(
                    "gprflow-bench ipc: zenoh listening on {}, starting the zenoh partner{}",
                    setup.listen,
                    setup
                        .partner_netns
                        .as_deref()
                        .map_or_else(String::new, |ns| format!(" in network namespace `{ns}`"))
                );
                Some((session, Partner::spawn_zenoh(setup)?))
            }
            None => None,
        };
        Ok(Self { iox, local, zenoh })
    }

    /// Runs one phase with the partner of its link.
    fn run(&mut self, phase: &Phase, patience: &Patience) -> Result<Outcome> {
        eprintln!(
            "  {} bytes, {:?} {:?}, {} wait: {} (+{} warm-up)",
            phase.size,
            phase.link,
            phase.test,
            phase.mode.label(),
            phase.count,
            phase.warmup
        );
        match phase.link {
            Link::Iceoryx2 => self.local.run_on_bus(&self.iox, phase, patience),
            Link::UnixSocket => self.local.run_on_socket(phase, patience),
            Link::Zenoh => {
                let (session, partner) = self
                    .zenoh
                    .as_mut()
                    .ok_or_else(|| anyhow!("a zenoh phase without --zenoh-listen"))?;
                partner.run_on_bus(session, phase, patience)
            }
        }
    }

    /// Closes the driver's ends, lets both partners exit and checks that they did so cleanly.
    fn finish(self) -> Result<()> {
        let Self { iox, local, zenoh } = self;
        drop(iox);
        let local = local.finish();
        let zenoh = zenoh.map_or(Ok(()), |(session, partner)| {
            drop(session);
            partner.finish().context("the zenoh partner")
        });
        local.and(zenoh)
    }
}

/// The 1-minute load average (other work on the machine skews every figure), if readable.
fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// One-hop latency from a ping-pong outcome.
fn one_hop(outcome: Outcome) -> Result<LatencySummary> {
    match outcome {
        Outcome::RoundTrips(mut round_trips_ns) => {
            LatencySummary::from_ns(&mut round_trips_ns, 2.0).ok_or_else(|| anyhow!("no round trips recorded"))
        }
        Outcome::Stream(_) => bail!("a ping-pong phase returned a stream time"),
    }
}

/// The driver's handle on a partner process. Dropping it makes the partner exit (its stdin
/// and socket close) and reaps it, killing it if it does not go in time.
#[derive(Debug)]
struct Partner {
    child: Child,
    control: Control,
    /// The Unix socket, for the partner that serves it.
    socket: Option<UnixStream>,
}

/// The partner's stdin (phases) and stdout (answers).
#[derive(Debug)]
struct Control {
    phases: Option<ChildStdin>,
    replies: BufReader<ChildStdout>,
}

impl Control {
    fn send(&mut self, phase: &Phase) -> Result<()> {
        let stdin = self
            .phases
            .as_mut()
            .ok_or_else(|| anyhow!("the partner's stdin is closed"))?;
        let mut line = serde_json::to_vec(phase)?;
        line.push(b'\n');
        stdin.write_all(&line)?;
        stdin.flush().context("sending a phase to the partner")
    }

    fn expect(&mut self, want: &Reply) -> Result<()> {
        let mut line = String::new();
        let n = self
            .replies
            .read_line(&mut line)
            .context("reading the partner's answer")?;
        ensure!(n > 0, "the partner exited (see its error above)");
        let got: Reply = serde_json::from_str(line.trim_end())
            .with_context(|| format!("unexpected line from the partner: `{}`", line.trim_end()))?;
        ensure!(&got == want, "the partner answered {got:?} instead of {want:?}");
        Ok(())
    }
}

impl Partner {
    /// Starts the partner of iceoryx2 and the socket, and accepts its socket connection on
    /// the abstract address `socket_name`.
    fn spawn_local(prefix: &str, socket_name: &str) -> Result<Self> {
        let addr = SocketAddr::from_abstract_name(socket_name.as_bytes()).context("socket name")?;
        let listener = UnixListener::bind_addr(&addr).with_context(|| format!("binding socket @{socket_name}"))?;
        listener.set_nonblocking(true)?;
        let exe = std::env::current_exe().context("finding this program to start the partner")?;
        let mut command = Command::new(exe);
        command.args(["echo", "--prefix", prefix, "--socket", socket_name]);
        let mut partner = Self::spawn(command)?;
        // On an error, dropping `partner` closes its stdin and the partner exits.
        partner.socket = Some(partner.accept(&listener)?);
        Ok(partner)
    }

    /// Starts the zenoh partner, in the network namespace of `setup` if it names one.
    fn spawn_zenoh(setup: &ZenohSetup) -> Result<Self> {
        let exe = std::env::current_exe().context("finding this program to start the partner")?;
        let mut command = match &setup.partner_netns {
            Some(ns) => {
                let mut ip = Command::new("ip");
                ip.args(["netns", "exec", ns]).arg(exe);
                ip
            }
            None => Command::new(exe),
        };
        command.args(["echo", "--zenoh-connect", &setup.connect]);
        Self::spawn(command)
    }

    /// Starts `command` with its stdin and stdout as the control channel.
    fn spawn(mut command: Command) -> Result<Self> {
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting {command:?}"))?;
        // Taking the pipes out of `child`: dropping `child` on an error below closes them,
        // and the partner exits.
        let phases = child.stdin.take();
        let replies = child
            .stdout
            .take()
            .ok_or_else(|| anyhow!("no stdout pipe to the partner"))?;
        Ok(Self {
            child,
            control: Control {
                phases,
                replies: BufReader::new(replies),
            },
            socket: None,
        })
    }

    /// Accepts the partner's connection on `listener` (non-blocking).
    fn accept(&mut self, listener: &UnixListener) -> Result<UnixStream> {
        let started = Instant::now();
        let socket = loop {
            match listener.accept() {
                Ok((socket, _)) => break socket,
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    if let Some(status) = self.child.try_wait()? {
                        bail!("the partner exited before connecting: {status}");
                    }
                    ensure!(
                        started.elapsed() <= PARTNER_TIMEOUT,
                        "the partner did not connect within {PARTNER_TIMEOUT:?}"
                    );
                    std::thread::sleep(Duration::from_millis(2));
                }
                Err(e) => return Err(e).context("accepting the partner's connection"),
            }
        };
        socket.set_nonblocking(false)?;
        socket.set_read_timeout(Some(IO_TIMEOUT))?;
        socket.set_write_timeout(Some(IO_TIMEOUT))?;
        Ok(socket)
    }

    /// Runs one phase over a bus transport on both sides and returns what the driver measured.
    fn run_on_bus(&mut self, bus: &dyn Transport, phase: &Phase, patience: &Patience) -> Result<Outcome> {
        // Both sides shake hands at the same time; the partner answers once done.
        let mut end = BusEndpoint::open(bus, phase, Side::Driver, patience.clone())?;
        self.control.send(phase)?;
        end.handshake()?;
        self.control.expect(&Reply::Ready)?;
        let outcome = hop::drive(&mut end, phase)?;
        self.control.expect(&Reply::Done)?;
        Ok(outcome)
    }

    /// Runs one phase over the Unix socket on both sides and returns what the driver measured.
    fn run_on_socket(&mut self, phase: &Phase, patience: &Patience) -> Result<Outcome> {
        let socket = self
            .socket
            .as_mut()
            .ok_or_else(|| anyhow!("this partner has no socket"))?;
        let mut end = UdsEndpoint::open(socket, phase, patience.clone())?;
        self.control.send(phase)?;
        self.control.expect(&Reply::Ready)?;
        let outcome = hop::drive(&mut end, phase)?;
        self.control.expect(&Reply::Done)?;
        Ok(outcome)
    }

    /// Lets the partner exit and checks that it did so cleanly.
    fn finish(mut self) -> Result<()> {
        let status = self.close_and_reap()?;
        ensure!(status.success(), "the partner ended with {status}");
        Ok(())
    }

    fn close_and_reap(&mut self) -> Result<std::process::ExitStatus> {
        self.control.phases = None;
        if let Some(socket) = &self.socket {
            let _ = socket.shutdown(std::net::Shutdown::Both);
        }
        let started = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if started.elapsed() > PARTNER_TIMEOUT {
                let _ = self.child.kill();
                let _ = self.child.wait();
                bail!("the partner did not exit within {PARTNER_TIMEOUT:?}; killed it");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

impl Drop for Partner {
    fn drop(&mut self) {
        // After `finish` the child is already reaped and this returns at once.
        let _ = self.close_and_reap();
    }
}
