//! `gprflow-bench`: benchmark programs of the gprflow runtime.
//!
//! `gprflow-bench [ipc] [--quick] [--spin] [--iterations N] [--messages N] [--touch-stride B] [--json FILE]
//! [--zenoh-listen ENDPOINT [--zenoh-connect ENDPOINT] [--zenoh-partner-netns NS]]`
//! measures one hop between two processes over the iceoryx2 transport of the bus
//! (`gprflow::bus::iox::IoxTransport`) and over a Unix domain socket, next to a plain
//! in-process `memcpy`, for 4 KiB and 1 MiB messages; with `--zenoh-listen`, also over the
//! zenoh transport (`gprflow::bus::zenoh::ZenohTransport`, TCP), optionally to a partner in
//! another network namespace (`tools/peer/bench_zenoh.sh` sets two up). The method is
//! described in [`ipc`].
//!
//! The program re-executes itself as its partner processes (`gprflow-bench echo ...`,
//! hidden): that role only answers the driver and is of no use on its own.

mod bus_hop;
mod echo;
mod hop;
mod ipc;
mod memcpy;
mod payload;
mod plan;
mod report;
mod stats;
mod uds_hop;

use std::num::NonZeroUsize;
use std::path::PathBuf;

use clap::{ArgGroup, Args, Parser, Subcommand};

/// Command line of `gprflow-bench`.
#[derive(Debug, Parser)]
#[command(
    name = "gprflow-bench",
    about = "gprflow benchmarks",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    /// Options of `ipc`, the default benchmark.
    #[command(flatten)]
    ipc: IpcArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// One-hop latency and throughput: iceoryx2 vs Unix domain socket vs memcpy, and zenoh
    /// when asked (default).
    Ipc(IpcArgs),
    /// The partner process of `ipc` (started by it; not for direct use).
    #[command(hide = true)]
    Echo(EchoArgs),
}

/// Options of the IPC benchmark.
#[derive(Debug, Clone, Args)]
pub struct IpcArgs {
    /// Measured ping-pong round trips per size (default 2000 for 4 KiB, 500 for 1 MiB;
    /// warm-up round trips come on top and are not recorded).
    #[arg(long, value_name = "N")]
    pub iterations: Option<usize>,
    /// Measured messages of the one-way streaming test per size (default 20000 for 4 KiB,
    /// 2000 for 1 MiB; warm-up messages come on top).
    #[arg(long, value_name = "N")]
    pub messages: Option<usize>,
    /// A few iterations only: a smoke test, not a measurement.
    #[arg(long)]
    pub quick: bool,
    /// Also measure with busy polling (spinning on `try_receive` / non-blocking reads) next to
    /// the event-driven wake-up.
    #[arg(long)]
    pub spin: bool,
    /// Receivers check one payload byte in this many (64: every cache line; the message
    /// size or more: only the first byte, i.e. the data is produced but not consumed).
    #[arg(long, value_name = "BYTES", default_value_t = payload::DEFAULT_TOUCH_STRIDE)]
    pub touch_stride: NonZeroUsize,
    /// Also write the results as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
    /// Also measure the zenoh transport: the driver's session listens on this endpoint of
    /// its host (`tcp/10.77.50.1:7447`) and a second partner process connects to it.
    #[arg(long, value_name = "ENDPOINT")]
    pub zenoh_listen: Option<String>,
    /// The endpoint the zenoh partner connects to (default: the `--zenoh-listen` one).
    #[arg(long, value_name = "ENDPOINT", requires = "zenoh_listen")]
    pub zenoh_connect: Option<String>,
    /// Start the zenoh partner in this network namespace (`ip netns exec NS`, needs root);
    /// by default it runs in the driver's.
    #[arg(long, value_name = "NS", requires = "zenoh_listen")]
    pub zenoh_partner_netns: Option<String>,
}

/// Options of a partner process: the links it serves.
#[derive(Debug, Clone, Args)]
#[command(group(ArgGroup::new("links").required(true).multiple(true).args(["prefix", "zenoh_connect"])))]
pub struct EchoArgs {
    /// iceoryx2 resource prefix of the run (serves the iceoryx2 and socket phases).
    #[arg(long, requires = "socket")]
    pub prefix: Option<String>,
    /// Abstract Unix socket name to connect to.
    #[arg(long, requires = "prefix")]
    pub socket: Option<String>,
    /// zenoh endpoint of the driver to connect to (serves the zenoh phases).
    #[arg(long, value_name = "ENDPOINT")]
    pub zenoh_connect: Option<String>,
}

fn main() -> anyhow::Result<()> {
    // iceoryx2 warns on every start that no config file was loaded; keep the report readable.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    let cli = Cli::parse();
    match cli.command {
        None => ipc::run(&cli.ipc),
        Some(Command::Ipc(args)) => ipc::run(&args),
        Some(Command::Echo(args)) => echo::run(&args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ENDPOINT: &str = "tcp/10.77.50.1:7447";

    #[test]
    fn zenoh_options_come_with_a_listening_endpoint() {
        let parse = |args: &[&str]| Cli::try_parse_from(["gprflow-bench"].iter().chain(args));
        assert!(parse(&["ipc", "--zenoh-partner-netns", "ns2"]).is_err());
        assert!(parse(&["ipc", "--zenoh-connect", ENDPOINT]).is_err());
        let Ok(cli) = parse(&["--zenoh-listen", ENDPOINT, "--zenoh-partner-netns", "ns2"]) else {
            panic!("the default command takes the zenoh options");
        };
        assert_eq!(cli.ipc.zenoh_listen.as_deref(), Some(ENDPOINT));
        assert_eq!(cli.ipc.zenoh_partner_netns.as_deref(), Some("ns2"));
    }

    #[test]
    fn a_partner_serves_at_least_one_link() {
        let parse = |args: &[&str]| Cli::try_parse_from(["gprflow-bench", "echo"].iter().chain(args));
        assert!(parse(&[]).is_err());
        assert!(parse(&["--prefix", "gfb1_"]).is_err(), "iceoryx2 comes with the socket");
        assert!(parse(&["--prefix", "gfb1_", "--socket", "gfb1_uds"]).is_ok());
        assert!(parse(&["--zenoh-connect", ENDPOINT]).is_ok());
    }
}
