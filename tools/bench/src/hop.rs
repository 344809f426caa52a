//! The two measurements, written once for every transport: ping-pong and one-way streaming.
//!
//! Each side holds an [`Endpoint`]: something that can send a pattern-filled message and
//! receive-and-spot-check one. The driver (the process that prints the report) times; its
//! partner answers.

use std::time::{Duration, Instant};

use anyhow::{Result, ensure};

use crate::payload::{reply_seed_of, seed_of};
use crate::plan::{ACK_BYTES, Phase, Test};
use crate::stats::nanos;

/// One process's end of a two-way link.
pub trait Endpoint {
    /// Sends message `seq` of `len` payload bytes, writing the pattern with `seed` into every
    /// byte of it on the way (the cost of producing the data is part of the hop).
    ///
    /// # Errors
    /// Transport errors; the other side is gone.
    fn send(&mut self, seq: u64, len: usize, seed: u8) -> Result<()>;

    /// Waits for the next message, checks that it is `seq` with `len` payload bytes, reads
    /// one byte per [`Phase::touch_stride`] in place against the pattern with `seed`, and
    /// releases it.
    ///
    /// # Errors
    /// Transport errors, a wrong message, or the wait gave up (see [`crate::plan::Patience`]).
    fn receive(&mut self, seq: u64, len: usize, seed: u8) -> Result<()>;
}

/// Driver side of a ping-pong: `phase.warmup + phase.count` round trips, each a `size`-byte
/// request answered by a `size`-byte reply. Returns the round-trip times of the last
/// `phase.count`, in nanoseconds, timed from before the request is filled until the reply
/// was checked.
///
/// # Errors
/// As [`Endpoint`].
pub fn ping_pong_driver(end: &mut impl Endpoint, phase: &Phase) -> Result<Vec<u64>> {
    let mut round_trips_ns = Vec::with_capacity(phase.count);
    for seq in 0..total(phase) {
        let start = Instant::now();
        end.send(seq, phase.size, seed_of(seq))?;
        end.receive(seq, phase.size, reply_seed_of(seq))?;
        let elapsed = start.elapsed();
        if seq >= phase.warmup as u64 {
            round_trips_ns.push(nanos(elapsed));
        }
    }
    Ok(round_trips_ns)
}

/// Partner side of a ping-pong: answers every request with a reply of the same size.
///
/// # Errors
/// As [`Endpoint`].
pub fn ping_pong_partner(end: &mut impl Endpoint, phase: &Phase) -> Result<()> {
    for seq in 0..total(phase) {
        end.receive(seq, phase.size, seed_of(seq))?;
        end.send(seq, phase.size, reply_seed_of(seq))?;
    }
    Ok(())
}

/// Driver side of a stream: sends `phase.warmup` messages, waits for their acknowledgement,
/// then times `phase.count` messages from the first send until the partner acknowledged the
/// last one. The sender is held back only by the transport's back-pressure.
///
/// # Errors
/// As [`Endpoint`].
pub fn stream_driver(end: &mut impl Endpoint, phase: &Phase) -> Result<Duration> {
    ensure!(phase.warmup > 0, "a stream needs at least one warm-up message");
    let warmup = phase.warmup as u64;
    let total = total(phase);
    for seq in 0..warmup {
        end.send(seq, phase.size, seed_of(seq))?;
    }
    end.receive(warmup, ACK_BYTES, reply_seed_of(warmup))?;
    let start = Instant::now();
    for seq in warmup..total {
        end.send(seq, phase.size, seed_of(seq))?;
    }
    end.receive(total, ACK_BYTES, reply_seed_of(total))?;
    Ok(start.elapsed())
}

/// Partner side of a stream: receives and checks every message, acknowledges after the
/// warm-up and after the last one.
///
/// # Errors
/// As [`Endpoint`].
pub fn stream_partner(end: &mut impl Endpoint, phase: &Phase) -> Result<()> {
    let warmup = phase.warmup as u64;
    let total = total(phase);
    for seq in 0..total {
        end.receive(seq, phase.size, seed_of(seq))?;
        let received = seq + 1;
        if received == warmup || received == total {
            end.send(received, ACK_BYTES, reply_seed_of(received))?;
        }
    }
    Ok(())
}

fn total(phase: &Phase) -> u64 {
    (phase.warmup + phase.count) as u64
}

/// What the driver measured in one phase.
#[derive(Debug, Clone)]
pub enum Outcome {
    /// Round-trip times of a ping-pong, ns.
    RoundTrips(Vec<u64>),
    /// Time of a stream's recorded messages.
    Stream(Duration),
}

/// Runs the driver side of `phase`.
///
/// # Errors
/// As [`Endpoint`].
pub fn drive(end: &mut impl Endpoint, phase: &Phase) -> Result<Outcome> {
    Ok(match phase.test {
        Test::PingPong => Outcome::RoundTrips(ping_pong_driver(end, phase)?),
        Test::Stream => Outcome::Stream(stream_driver(end, phase)?),
    })
}

/// Runs the partner side of `phase`.
///
/// # Errors
/// As [`Endpoint`].
pub fn answer(end: &mut impl Endpoint, phase: &Phase) -> Result<()> {
    match phase.test {
        Test::PingPong => ping_pong_partner(end, phase),
        Test::Stream => stream_partner(end, phase),
    }
}
