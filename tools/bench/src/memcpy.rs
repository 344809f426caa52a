//! In-process baselines: a plain copy between two preallocated buffers, and the cost of
//! writing the payload pattern alone (what every sender above pays per message).

use std::hint::black_box;
use std::time::{Duration, Instant};

use crate::payload;
use crate::stats::nanos;

/// Per-operation times (ns) of `iterations` timed operations after `warmup` untimed ones,
/// and the wall time of the timed loop (including the clock reads).
#[derive(Debug, Clone)]
pub struct Timed {
    /// Nanoseconds of each timed operation.
    pub samples_ns: Vec<u64>,
    /// Wall time of all timed operations.
    pub elapsed: Duration,
}

fn time_each(warmup: usize, iterations: usize, mut op: impl FnMut(usize)) -> Timed {
    for i in 0..warmup {
        op(i);
    }
    let mut samples_ns = Vec::with_capacity(iterations);
    let loop_start = Instant::now();
    for i in 0..iterations {
        let start = Instant::now();
        op(i);
        samples_ns.push(nanos(start.elapsed()));
    }
    Timed {
        samples_ns,
        elapsed: loop_start.elapsed(),
    }
}

/// `dst.copy_from_slice(&src)` with `size`-byte buffers, timed one copy at a time.
pub fn copy(size: usize, warmup: usize, iterations: usize) -> Timed {
    let mut src = vec![0_u8; size];
    payload::fill(&mut src, 1);
    let mut dst = vec![0_u8; size];
    time_each(warmup, iterations, |_| {
        dst.copy_from_slice(black_box(&src));
        black_box(&mut dst);
    })
}

/// Writing the payload pattern into a `size`-byte buffer, timed one fill at a time.
pub fn fill(size: usize, warmup: usize, iterations: usize) -> Timed {
    let mut buf = vec![0_u8; size];
    time_each(warmup, iterations, |i| {
        payload::fill(black_box(&mut buf), i as u8);
        black_box(&mut buf);
    })
}
