//! A partner process (`gprflow-bench echo`): opens the links it was given — iceoryx2 under
//! the run's prefix and the driver's Unix socket (`--prefix`, `--socket`), a zenoh session
//! that connects to the driver (`--zenoh-connect`), or both — then runs the phases the driver
//! sends as JSON lines on stdin, answering `Ready` / `Done` as JSON lines on stdout.
//!
//! It ends when stdin closes: normally when the driver is done, otherwise because the driver
//! died (its end of the pipe closes with it). Long waits check a stop flag set by that end of
//! file or by SIGINT/SIGTERM; a blocking socket read ends with the driver's socket. When
//! the driver died (this process was re-parented), it removes the run's iceoryx2 files
//! itself, as the driver would have.

use std::io::{BufRead, Write};
use std::os::linux::net::SocketAddrExt;
use std::os::unix::net::{SocketAddr, UnixStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::time::Duration;

use anyhow::{Context, Result, anyhow};
use gprflow::bus::Transport;
use gprflow::bus::iox::IoxTransport;
use gprflow::bus::zenoh::ZenohTransport;

use crate::EchoArgs;
use crate::bus_hop::{BusEndpoint, Side};
use crate::hop;
use crate::plan::{self, Link, Patience, Phase, Reply, ZENOH_KEY_PREFIX};
use crate::uds_hop::UdsEndpoint;

/// How often the idle partner looks at the stop flag.
const IDLE_CHECK: Duration = Duration::from_millis(100);

/// Runs the partner role.
///
/// # Errors
/// Setup failures and failed phases (a stop request ends it without error).
pub fn run(args: &EchoArgs) -> Result<()> {
    let driver_pid = std::os::unix::process::parent_id();
    let stop = Arc::new(AtomicBool::new(false));
    plan::watch_signals(&stop)?;
    let phases = read_phases(Arc::clone(&stop))?;
    let mut links = Links::open(args, &stop)?;
    let patience = Patience::new(Arc::clone(&stop), None);
    let result = serve(&phases, &mut links, &patience);
    drop(links);
    if let Some(prefix) = &args.prefix
        && std::os::unix::process::parent_id() != driver_pid
    {
        // The driver died without cleaning up: this is the run's last process.
        let removed = gprflow::launch::cleanup_run(prefix);
        eprintln!("gprflow-bench echo: the driver is gone; removed its leftovers: {removed:?}");
    }
    match result {
        Err(_) if patience.stopped() => Ok(()),
        other => other,
    }
}

/// The links a partner serves; `None` where it was not given one.
struct Links {
    socket: Option<UnixStream>,
    iox: Option<IoxTransport>,
    zenoh: Option<ZenohTransport>,
}

impl Links {
    fn open(args: &EchoArgs, stop: &Arc<AtomicBool>) -> Result<Self> {
        let socket = args
            .socket
            .as_deref()
            .map(|name| {
                let addr = SocketAddr::from_abstract_name(name.as_bytes()).context("socket name")?;
                UnixStream::connect_addr(&addr).with_context(|| format!("connecting to socket @{name}"))
            })
            .transpose()?;
        let iox = args
            .prefix
            .as_deref()
            .map(|prefix| IoxTransport::new("bench_partner", prefix, Arc::clone(stop)))
            .transpose()?;
        let zenoh = args
            .zenoh_connect
            .as_deref()
            .map(|endpoint| {
                ZenohTransport::open(&plan::zenoh_partner_decl(endpoint), ZENOH_KEY_PREFIX, Arc::clone(stop))
                    .with_context(|| format!("zenoh session connecting to {endpoint}"))
            })
            .transpose()?;
        Ok(Self { socket, iox, zenoh })
    }

    /// The bus transport of `link`.
    fn bus(&self, link: Link) -> Option<&dyn Transport> {
        match link {
            Link::Iceoryx2 => self.iox.as_ref().map(|t| t as &dyn Transport),
            Link::Zenoh => self.zenoh.as_ref().map(|t| t as &dyn Transport),
            Link::UnixSocket => None,
        }
    }
}

fn serve(phases: &Receiver<Phase>, links: &mut Links, patience: &Patience) -> Result<()> {
    let mut out = std::io::stdout().lock();
    loop {
        let phase = match phases.recv_timeout(IDLE_CHECK) {
            Ok(phase) => phase,
            Err(RecvTimeoutError::Timeout) if patience.stopped() => return Ok(()),
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => return Ok(()),
        };
        let unserved = || anyhow!("phase {}: this partner was not given a {:?} link", phase.id, phase.link);
        match phase.link {
            Link::Iceoryx2 | Link::Zenoh => {
                let bus = links.bus(phase.link).ok_or_else(unserved)?;
                let mut end = BusEndpoint::open(bus, &phase, Side::Partner, patience.clone())?;
                end.handshake()?;
                reply(&mut out, &Reply::Ready)?;
                hop::answer(&mut end, &phase)?;
            }
            Link::UnixSocket => {
                let socket = links.socket.as_mut().ok_or_else(unserved)?;
                let mut end = UdsEndpoint::open(socket, &phase, patience.clone())?;
                reply(&mut out, &Reply::Ready)?;
                hop::answer(&mut end, &phase)?;
            }
        }
        // The phase's ports are closed here.
        reply(&mut out, &Reply::Done)?;
    }
}

fn reply(out: &mut impl Write, reply: &Reply) -> Result<()> {
    serde_json::to_writer(&mut *out, reply)?;
    out.write_all(b"\n")?;
    out.flush().context("answering the driver")
}

/// Reads phases from stdin on a thread; at end of file (or garbage) sets `stop`.
fn read_phases(stop: Arc<AtomicBool>) -> Result<Receiver<Phase>> {
    let (tx, rx) = sync_channel(1);
    std::thread::Builder::new()
        .name("bench-stdin".to_owned())
        .spawn(move || {
            for line in std::io::stdin().lock().lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str::<Phase>(&line) {
                    Ok(phase) => {
                        if tx.send(phase).is_err() {
                            break;
                        }
                    }
                    Err(e) => {
                        eprintln!("gprflow-bench echo: bad phase line `{line}`: {e}");
                        break;
                    }
                }
            }
            stop.store(true, Ordering::Relaxed);
        })
        .context("starting the stdin reader")?;
    Ok(rx)
}
