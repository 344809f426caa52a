//! Latency percentiles and throughput figures.

use std::time::Duration;

use serde::Serialize;

/// Percentiles of a set of latency samples, in microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Number of samples.
    pub samples: usize,
    /// Smallest sample.
    pub min_us: f64,
    /// Median (nearest rank).
    pub p50_us: f64,
    /// 99th percentile (nearest rank).
    pub p99_us: f64,
    /// Largest sample.
    pub max_us: f64,
    /// Arithmetic mean.
    pub mean_us: f64,
}

impl LatencySummary {
    /// Summarises `samples_ns`, dividing every sample by `divisor` first (2 turns round trips
    /// into one-hop times). `None` when there are no samples.
    pub fn from_ns(samples_ns: &mut [u64], divisor: f64) -> Option<Self> {
        samples_ns.sort_unstable();
        let us = |ns: u64| ns as f64 / 1e3 / divisor;
        let min = *samples_ns.first()?;
        let max = *samples_ns.last()?;
        let sum: u128 = samples_ns.iter().map(|&s| u128::from(s)).sum();
        Some(Self {
            samples: samples_ns.len(),
            min_us: us(min),
            p50_us: us(nearest_rank(samples_ns, 0.50)?),
            p99_us: us(nearest_rank(samples_ns, 0.99)?),
            max_us: us(max),
            mean_us: sum as f64 / samples_ns.len() as f64 / 1e3 / divisor,
        })
    }
}

/// The nearest-rank percentile `p` (0..=1) of sorted `samples`.
fn nearest_rank(sorted: &[u64], p: f64) -> Option<u64> {
    let rank = (p * sorted.len() as f64).ceil() as usize;
    sorted.get(rank.clamp(1, sorted.len()) - 1).copied()
}

/// Messages moved in a measured time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Throughput {
    /// Messages counted.
    pub messages: usize,
    /// Bytes of payload per message.
    pub message_bytes: usize,
    /// Time they took, in seconds.
    pub elapsed_s: f64,
    /// Messages per second.
    pub msgs_per_s: f64,
    /// Payload gigabytes (1e9 bytes) per second.
    pub gb_per_s: f64,
}

impl Throughput {
    /// `messages` of `message_bytes` each in `elapsed`.
    pub fn new(messages: usize, message_bytes: usize, elapsed: Duration) -> Self {
        let elapsed_s = elapsed.as_secs_f64().max(f64::MIN_POSITIVE);
        let msgs_per_s = messages as f64 / elapsed_s;
        Self {
            messages,
            message_bytes,
            elapsed_s,
            msgs_per_s,
            gb_per_s: msgs_per_s * message_bytes as f64 / 1e9,
        }
    }
}

/// Nanoseconds of `d`, saturating.
pub fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOLERANCE: f64 = 1e-9;

    #[test]
    fn percentiles_use_nearest_rank() {
        let mut samples: Vec<u64> = (1..=100).rev().map(|v| v * 1000).collect();
        let s = LatencySummary::from_ns(&mut samples, 1.0);
        let Some(s) = s else {
            panic!("no summary");
        };
        assert_eq!(s.samples, 100);
        assert!((s.p50_us - 50.0).abs() < TOLERANCE);
        assert!((s.p99_us - 99.0).abs() < TOLERANCE);
        assert!((s.min_us - 1.0).abs() < TOLERANCE);
        assert!((s.max_us - 100.0).abs() < TOLERANCE);
        assert!((s.mean_us - 50.5).abs() < TOLERANCE);
    }

    #[test]
    fn round_trips_halve() {
        let mut samples = vec![10_000_u64];
        let s = LatencySummary::from_ns(&mut samples, 2.0).map(|s| s.p50_us);
        assert_eq!(s, Some(5.0));
        assert_eq!(LatencySummary::from_ns(&mut [], 2.0), None);
    }

    #[test]
    fn throughput_in_gigabytes() {
        let t = Throughput::new(1000, 1_000_000, Duration::from_secs(1));
        assert!((t.msgs_per_s - 1000.0).abs() < TOLERANCE);
        assert!((t.gb_per_s - 1.0).abs() < TOLERANCE);
    }
}
