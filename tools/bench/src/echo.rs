//! The partner process (`gprflow-bench echo`): connects to the driver's socket, opens its
//! iceoryx2 node under the run's prefix, then runs the phases the driver sends as JSON lines
//! on stdin, answering `Ready` / `Done` as JSON lines on stdout.
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

use anyhow::{Context, Result};
use gprflow::bus::iox::IoxTransport;

use crate::EchoArgs;
use crate::hop;
use crate::iox_hop::{IoxEndpoint, Side};
use crate::plan::{self, Link, Patience, Phase, Reply};
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
    let addr = SocketAddr::from_abstract_name(args.socket.as_bytes()).context("socket name")?;
    let mut socket =
        UnixStream::connect_addr(&addr).with_context(|| format!("connecting to socket @{}", args.socket))?;
    let transport = IoxTransport::new("bench_partner", &args.prefix, Arc::clone(&stop))?;
    let patience = Patience::new(Arc::clone(&stop), None);
    let result = serve(&phases, &transport, &mut socket, &patience);
    drop(transport);
    if std::os::unix::process::parent_id() != driver_pid {
        // The driver died without cleaning up: this is the run's last process.
        let removed = gprflow::launch::cleanup_run(&args.prefix);
        eprintln!("gprflow-bench echo: the driver is gone; removed its leftovers: {removed:?}");
    }
    match result {
        Err(_) if patience.stopped() => Ok(()),
        other => other,
    }
}

fn serve(
    phases: &Receiver<Phase>,
    transport: &IoxTransport,
    socket: &mut UnixStream,
    patience: &Patience,
) -> Result<()> {
    let mut out = std::io::stdout().lock();
    loop {
        let phase = match phases.recv_timeout(IDLE_CHECK) {
            Ok(phase) => phase,
            Err(RecvTimeoutError::Timeout) if patience.stopped() => return Ok(()),
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => return Ok(()),
        };
        match phase.link {
            Link::Iceoryx2 => {
                let mut end = IoxEndpoint::open(transport, &phase, Side::Partner, patience.clone())?;
                end.handshake()?;
                reply(&mut out, &Reply::Ready)?;
                hop::answer(&mut end, &phase)?;
            }
            Link::UnixSocket => {
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
