//! The results: a markdown table, the target ratios, and the same as JSON.

use std::fmt::Write as _;

use serde::Serialize;

use crate::plan::{Counts, SIZES, WaitMode, ZenohSetup};
use crate::stats::{LatencySummary, Throughput};

/// The 1 MiB iceoryx2 hop must take less than this fraction of the Unix socket's.
pub const TARGET_IOX_OVER_UDS: f64 = 0.1;
/// The 1 MiB iceoryx2 hop may take at most this multiple of a plain copy.
pub const TARGET_IOX_OVER_MEMCPY: f64 = 2.0;
/// The 4 KiB iceoryx2 hop's p99 must stay below this.
pub const TARGET_IOX_4KIB_P99_US: f64 = 100.0;

/// What a row measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Subject {
    /// One hop between processes over `gprflow::bus::iox::IoxTransport`.
    Iceoryx2,
    /// One hop between processes over a Unix stream socket.
    UnixSocket,
    /// One hop between processes over `gprflow::bus::zenoh::ZenohTransport` (see
    /// [`Report::zenoh`]).
    Zenoh,
    /// `copy_from_slice` between two buffers of one process.
    Memcpy,
    /// Writing the payload pattern into a buffer of one process (the senders' share).
    PatternFill,
}

impl Subject {
    /// Row label; zenoh rows say how the link was set up.
    fn label(self, zenoh: Option<&ZenohSetup>) -> String {
        match self {
            Self::Iceoryx2 => "iceoryx2".to_owned(),
            Self::UnixSocket => "Unix socket".to_owned(),
            Self::Zenoh => zenoh.map_or_else(|| "zenoh".to_owned(), ZenohSetup::label),
            Self::Memcpy => "memcpy".to_owned(),
            Self::PatternFill => "pattern fill".to_owned(),
        }
    }
}

/// One line of the table.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// What was measured.
    pub subject: Subject,
    /// How receivers waited (transports only).
    pub wait: Option<WaitMode>,
    /// Payload bytes.
    pub size_bytes: usize,
    /// One hop (round trip / 2) for transports, one operation for in-process rows.
    pub latency: LatencySummary,
    /// One-way stream for transports; back-to-back operations for in-process rows.
    pub throughput: Throughput,
}

/// The target ratios of one wait mode.
#[derive(Debug, Clone, Serialize)]
pub struct Targets {
    /// Wait mode of the iceoryx2 and socket rows compared.
    pub wait: WaitMode,
    /// (iceoryx2 1 MiB p50) / (Unix socket 1 MiB p50); target below [`TARGET_IOX_OVER_UDS`].
    pub iox_over_uds_1mib_p50: Option<f64>,
    /// (iceoryx2 1 MiB p50) / (memcpy 1 MiB p50); target at most [`TARGET_IOX_OVER_MEMCPY`].
    pub iox_over_memcpy_1mib_p50: Option<f64>,
    /// iceoryx2 4 KiB p99 in microseconds; target below [`TARGET_IOX_4KIB_P99_US`].
    pub iox_4kib_p99_us: Option<f64>,
}

impl Targets {
    fn lines(&self) -> [String; 3] {
        let verdict = |met: Option<bool>| match met {
            Some(true) => "met",
            Some(false) => "NOT met",
            None => "not measured",
        };
        let num = |v: Option<f64>, digits: usize| v.map_or_else(|| "-".to_owned(), |v| format!("{v:.digits$}"));
        [
            format!(
                "- iceoryx2 1 MiB p50 / Unix socket 1 MiB p50 = {} (target < {TARGET_IOX_OVER_UDS}): {}",
                num(self.iox_over_uds_1mib_p50, 3),
                verdict(self.iox_over_uds_1mib_p50.map(|r| r < TARGET_IOX_OVER_UDS))
            ),
            format!(
                "- iceoryx2 1 MiB p50 / memcpy 1 MiB p50 = {} (target <= {TARGET_IOX_OVER_MEMCPY}): {}",
                num(self.iox_over_memcpy_1mib_p50, 2),
                verdict(self.iox_over_memcpy_1mib_p50.map(|r| r <= TARGET_IOX_OVER_MEMCPY))
            ),
            format!(
                "- iceoryx2 4 KiB p99 = {} us (target < {TARGET_IOX_4KIB_P99_US} us): {}",
                num(self.iox_4kib_p99_us, 1),
                verdict(self.iox_4kib_p99_us.map(|v| v < TARGET_IOX_4KIB_P99_US))
            ),
        ]
    }
}

/// Everything a run found.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// `--quick` was given: a smoke test, not a measurement.
    pub quick: bool,
    /// CPUs available to the process.
    pub cpus: usize,
    /// 1-minute load average before and after the run (other work on the machine skews
    /// every figure, the tails most).
    pub load_average: [Option<f64>; 2],
    /// Message counts per size.
    pub counts: Vec<Counts>,
    /// The receiver reads one byte in this many, in place.
    pub touch_stride_bytes: usize,
    /// Frames a subscriber queues (iceoryx2 topics; zenoh's window of unconsumed frames).
    pub topic_buffer: usize,
    /// The zenoh link, when measured.
    pub zenoh: Option<ZenohSetup>,
    /// iceoryx2 files of the run removed after both processes ended (the per-prefix
    /// node-counter segment that iceoryx2 keeps on purpose; anything else is a leak).
    pub removed_after_run: Vec<String>,
    /// Measurements.
    pub rows: Vec<Row>,
    /// Target ratios per wait mode.
    pub targets: Vec<Targets>,
}

impl Report {
    /// Computes the targets of every wait mode in `rows`.
    pub fn targets_of(rows: &[Row], modes: &[WaitMode]) -> Vec<Targets> {
        let [small, large] = SIZES;
        let find = |subject: Subject, wait: Option<WaitMode>, size: usize| {
            rows.iter()
                .find(|r| r.subject == subject && r.wait == wait && r.size_bytes == size)
                .map(|r| r.latency)
        };
        let memcpy_large = find(Subject::Memcpy, None, large);
        modes
            .iter()
            .map(|&wait| {
                let iox_large = find(Subject::Iceoryx2, Some(wait), large);
                let uds_large = find(Subject::UnixSocket, Some(wait), large);
                let ratio = |a: Option<LatencySummary>, b: Option<LatencySummary>| Some(a?.p50_us / b?.p50_us);
                Targets {
                    wait,
                    iox_over_uds_1mib_p50: ratio(iox_large, uds_large),
                    iox_over_memcpy_1mib_p50: ratio(iox_large, memcpy_large),
                    iox_4kib_p99_us: find(Subject::Iceoryx2, Some(wait), small).map(|l| l.p99_us),
                }
            })
            .collect()
    }

    /// The report as markdown: table, targets, method notes.
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "| transport | wait | size | p50 us | p99 us | throughput msg/s | MB/s |"
        );
        let _ = writeln!(s, "|---|---|---|---:|---:|---:|---:|");
        for r in &self.rows {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {:.2} | {:.2} | {:.0} | {:.0} |",
                r.subject.label(self.zenoh.as_ref()),
                r.wait.map_or("-", WaitMode::label),
                size_label(r.size_bytes),
                r.latency.p50_us,
                r.latency.p99_us,
                r.throughput.msgs_per_s,
                r.throughput.gb_per_s * 1e3,
            );
        }
        for t in &self.targets {
            let _ = writeln!(s, "\nTargets, {} wait:", t.wait.label());
            for line in t.lines() {
                let _ = writeln!(s, "{line}");
            }
        }
        let load = |l: Option<f64>| l.map_or_else(|| "?".to_owned(), |l| format!("{l:.2}"));
        let _ = writeln!(
            s,
            "\nMethod ({} CPUs, 1-min load average {} before, {} after{}):",
            self.cpus,
            load(self.load_average[0]),
            load(self.load_average[1]),
            if self.quick {
                "; --quick: a smoke test, NOT a measurement"
            } else {
                ""
            }
        );
        for c in &self.counts {
            let _ = writeln!(
                s,
                "- {}: {} round trips (+{} warm-up), stream of {} messages (+{} warm-up), {} in-process operations",
                size_label(c.size),
                c.round_trips,
                c.round_trip_warmup,
                c.stream_messages,
                c.stream_warmup,
                c.copies
            );
        }
        let _ = writeln!(
            s,
            "- p50/p99 of transports: one hop = ping-pong round trip / 2 between two processes; the \
             sender writes every payload byte, the receiver checks one byte in {} in place \
             (iceoryx2), in the copy zenoh hands over (zenoh) or after reading the whole message into a \
             buffer (socket).",
            self.touch_stride_bytes
        );
        let _ = writeln!(
            s,
            "- throughput of transports: one-way stream until the receiver acknowledged the last \
             message (MB = 1e6 bytes); bus topics queue {} frames, the socket uses the kernel's \
             default buffers.",
            self.topic_buffer
        );
        if let Some(z) = &self.zenoh {
            let _ = writeln!(
                s,
                "- {}: the driver's zenoh session listens on {}, the zenoh partner's connects to {}{}; \
                 zenoh copies each payload into its buffers on send and out of them on receive, \
                 and acknowledges on a second key.",
                z.label(),
                z.listen,
                z.connect,
                z.partner_netns.as_deref().map_or_else(
                    || " (same network namespace)".to_owned(),
                    |ns| format!(" from network namespace `{ns}`")
                )
            );
        }
        let _ = writeln!(
            s,
            "- in-process rows: one operation timed at a time (clock reads included); throughput = \
             operations / wall time of the timed loop."
        );
        let _ = writeln!(
            s,
            "- after the run: removed {} iceoryx2 file(s) of the run's prefix: {:?}",
            self.removed_after_run.len(),
            self.removed_after_run
        );
        s
    }
}

fn size_label(bytes: usize) -> String {
    if bytes >= 1 << 20 && bytes.is_multiple_of(1 << 20) {
        format!("{} MiB", bytes >> 20)
    } else if bytes >= 1 << 10 && bytes.is_multiple_of(1 << 10) {
        format!("{} KiB", bytes >> 10)
    } else {
        format!("{bytes} B")
    }
}
