//! [`Endpoint`] over a bus [`Transport`]: the sender fills the transport's buffer in place
//! (`Publisher::send_with`), the receiver checks the frame where the transport hands it over.
//!
//! Over iceoryx2 that buffer is loaned shared memory and the receiver reads the sample where
//! the sender wrote it; over zenoh the payload is copied into zenoh's buffers on the way out
//! and out of them on the way in (see `gprflow::bus::zenoh`).

use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, ensure};
use gprflow::bus::{self, FrameHeader, Publisher, Subscriber, Transport};

use crate::hop::Endpoint;
use crate::payload;
use crate::plan::{Patience, Phase, SPINS_PER_CHECK, WaitMode};

/// Longest single `Subscriber::wait` before the patience is checked again.
const WAIT_SLICE: Duration = Duration::from_millis(50);

/// How long a publisher waits for the other process's subscriber to appear.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// One process's publisher and subscriber of a phase.
pub struct BusEndpoint {
    publisher: Box<dyn Publisher>,
    subscriber: Box<dyn Subscriber>,
    /// The subscriber's topic, for error messages.
    sub_topic: String,
    mode: WaitMode,
    touch_stride: usize,
    patience: Patience,
}

impl std::fmt::Debug for BusEndpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BusEndpoint")
            .field("publishes", &self.publisher.topic())
            .field("subscribes", &self.subscriber.topic())
            .field("mode", &self.mode)
            .finish_non_exhaustive()
    }
}

/// Which end of a phase a process holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// Publishes the forward topic, subscribes to the backward one.
    Driver,
    /// Subscribes to the forward topic, publishes the backward one.
    Partner,
}

impl BusEndpoint {
    /// Opens this side's ports of `phase` (both processes derive the same topic settings
    /// from the phase); [`BusEndpoint::handshake`] connects them.
    ///
    /// # Errors
    /// The transport's errors.
    pub fn open(transport: &dyn Transport, phase: &Phase, side: Side, patience: Patience) -> Result<Self> {
        let (pub_topic, sub_topic) = match side {
            Side::Driver => (phase.forward_topic(), phase.backward_topic()),
            Side::Partner => (phase.backward_topic(), phase.forward_topic()),
        };
        let subscriber = transport.subscriber(&sub_topic)?;
        let publisher = transport.publisher(&pub_topic)?;
        Ok(Self {
            publisher,
            subscriber,
            sub_topic: sub_topic.name,
            mode: phase.mode,
            touch_stride: phase.touch_stride,
            patience,
        })
    }

    /// Attaches this side's subscriber to the other process's publisher, then waits until
    /// the other process's subscriber has attached to this side's publisher, so that nothing
    /// sent afterwards is lost. Both processes call it at the same time.
    ///
    /// # Errors
    /// Handshake timeout or shutdown.
    pub fn handshake(&mut self) -> Result<()> {
        let patience = &self.patience;
        let stopped = || patience.stopped();
        self.subscriber
            .attach(HANDSHAKE_TIMEOUT, &stopped)
            .context("waiting for the other process's publisher")?;
        bus::wait_for_subscribers(self.publisher.as_ref(), 1, HANDSHAKE_TIMEOUT, &stopped)
            .context("waiting for the other process to subscribe")
    }
}

impl Endpoint for BusEndpoint {
    fn send(&mut self, seq: u64, len: usize, seed: u8) -> Result<()> {
        let reached = self
            .publisher
            .send_with(FrameHeader::data(seq, 0), len, &mut |mut out| {
                payload::fill_writer(&mut out, seed);
                out.finish()
            })
            .with_context(|| format!("seq {seq}: send"))?;
        ensure!(
            reached == 1,
            "topic `{}` seq {seq}: reached {reached} subscribers instead of 1 (the other process is gone)",
            self.publisher.topic()
        );
        Ok(())
    }

    fn receive(&mut self, seq: u64, len: usize, seed: u8) -> Result<()> {
        let topic = &self.sub_topic;
        let mut spins: u32 = 0;
        let mut since: Option<Instant> = None;
        let frame = loop {
            if let Some(frame) = self.subscriber.try_receive()? {
                break frame;
            }
            match self.mode {
                WaitMode::Event => self.subscriber.wait(WAIT_SLICE)?,
                WaitMode::Spin => {
                    std::hint::spin_loop();
                    spins = spins.wrapping_add(1);
                    if !spins.is_multiple_of(SPINS_PER_CHECK) {
                        continue;
                    }
                }
            }
            self.patience.check(*since.get_or_insert_with(Instant::now), || {
                format!("topic `{topic}` seq {seq}")
            })?;
        };
        ensure!(
            frame.header.seq == seq && frame.payload().len() == len,
            "topic `{topic}`: expected seq {seq} with {len} bytes, got seq {} with {} bytes",
            frame.header.seq,
            frame.payload().len()
        );
        payload::verify(frame.payload(), seed, self.touch_stride)
            .map_err(|offset| anyhow!("topic `{topic}` seq {seq}: byte {offset} differs from the pattern"))
    }
}
