//! [`Endpoint`] over a Unix stream socket: length-prefixed frames. The sender fills a
//! preallocated frame buffer and writes it; the receiver reads the whole message into a
//! preallocated buffer (the kernel copies it twice: into the socket, out of it) and checks it.
//!
//! Event mode uses blocking reads and writes; spin mode sets the socket non-blocking and
//! retries `WouldBlock` in a loop.

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::UnixStream;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail, ensure};

use crate::hop::Endpoint;
use crate::payload;
use crate::plan::{Patience, Phase, SPINS_PER_CHECK, WaitMode};

/// Frame header: payload length and sequence number, both u64 little endian.
const HEADER_BYTES: usize = 16;

/// Timeout of one blocking read or write of the driver (the partner blocks without one and
/// learns of the driver's end from end of file).
pub const IO_TIMEOUT: Duration = Duration::from_secs(10);

/// One process's end of the socket during a phase.
#[derive(Debug)]
pub struct UdsEndpoint<'s> {
    stream: &'s mut UnixStream,
    mode: WaitMode,
    touch_stride: usize,
    patience: Patience,
    /// Header and payload of the frame being sent.
    send_buf: Vec<u8>,
    /// Payload of the frame being received.
    recv_buf: Vec<u8>,
}

impl<'s> UdsEndpoint<'s> {
    /// Sets `stream` up for `phase` (blocking or not) with buffers for its largest message.
    ///
    /// # Errors
    /// When the socket mode cannot be set.
    pub fn open(stream: &'s mut UnixStream, phase: &Phase, patience: Patience) -> Result<Self> {
        stream
            .set_nonblocking(phase.mode == WaitMode::Spin)
            .context("setting the socket (non-)blocking")?;
        let max_len = phase.size.max(crate::plan::ACK_BYTES);
        Ok(Self {
            stream,
            mode: phase.mode,
            touch_stride: phase.touch_stride,
            patience,
            send_buf: vec![0; HEADER_BYTES + max_len],
            recv_buf: vec![0; max_len],
        })
    }
}

impl Endpoint for UdsEndpoint<'_> {
    fn send(&mut self, seq: u64, len: usize, seed: u8) -> Result<()> {
        let frame = self
            .send_buf
            .get_mut(..HEADER_BYTES + len)
            .ok_or_else(|| anyhow!("socket: message of {len} bytes exceeds the buffer"))?;
        let (header, body) = frame.split_at_mut(HEADER_BYTES);
        let (len_field, seq_field) = header.split_at_mut(8);
        len_field.copy_from_slice(&(len as u64).to_le_bytes());
        seq_field.copy_from_slice(&seq.to_le_bytes());
        payload::fill(body, seed);
        write_full(self.stream, frame, self.mode, &self.patience).with_context(|| format!("socket seq {seq}: send"))
    }

    fn receive(&mut self, seq: u64, len: usize, seed: u8) -> Result<()> {
        let mut header = [0_u8; HEADER_BYTES];
        read_full(self.stream, &mut header, self.mode, &self.patience)
            .with_context(|| format!("socket seq {seq}: header"))?;
        let (len_field, seq_field) = header.split_at(8);
        let got_len = u64::from_le_bytes(len_field.try_into()?);
        let got_seq = u64::from_le_bytes(seq_field.try_into()?);
        ensure!(
            got_seq == seq && got_len == len as u64,
            "socket: expected seq {seq} with {len} bytes, got seq {got_seq} with {got_len} bytes"
        );
        let body = self
            .recv_buf
            .get_mut(..len)
            .ok_or_else(|| anyhow!("socket: message of {len} bytes exceeds the buffer"))?;
        read_full(self.stream, body, self.mode, &self.patience)
            .with_context(|| format!("socket seq {seq}: payload"))?;
        payload::verify(body, seed, self.touch_stride)
            .map_err(|offset| anyhow!("socket seq {seq}: byte {offset} differs from the pattern"))
    }
}

/// Reads exactly `buf.len()` bytes.
fn read_full(stream: &mut UnixStream, buf: &mut [u8], mode: WaitMode, patience: &Patience) -> Result<()> {
    let mut done = 0;
    let mut retry = Retry::default();
    while let Some(rest) = buf.get_mut(done..).filter(|rest| !rest.is_empty()) {
        match stream.read(rest) {
            Ok(0) => bail!("the other process closed the socket"),
            Ok(n) => done += n,
            Err(e) => retry.after(e, mode, patience)?,
        }
    }
    Ok(())
}

/// Writes all of `buf`.
fn write_full(stream: &mut UnixStream, buf: &[u8], mode: WaitMode, patience: &Patience) -> Result<()> {
    let mut done = 0;
    let mut retry = Retry::default();
    while let Some(rest) = buf.get(done..).filter(|rest| !rest.is_empty()) {
        match stream.write(rest) {
            Ok(0) => bail!("the socket accepts no more data"),
            Ok(n) => done += n,
            Err(e) => retry.after(e, mode, patience)?,
        }
    }
    Ok(())
}

/// What to do after a failed read or write: spin on `WouldBlock` in spin mode, retry after a
/// signal, give up otherwise (in event mode `WouldBlock` is the blocking call's timeout).
#[derive(Debug, Default)]
struct Retry {
    spins: u32,
    since: Option<Instant>,
}

impl Retry {
    fn after(&mut self, error: std::io::Error, mode: WaitMode, patience: &Patience) -> Result<()> {
        match error.kind() {
            ErrorKind::WouldBlock if mode == WaitMode::Spin => {
                std::hint::spin_loop();
                self.spins = self.spins.wrapping_add(1);
                if !self.spins.is_multiple_of(SPINS_PER_CHECK) {
                    return Ok(());
                }
            }
            ErrorKind::Interrupted => {}
            ErrorKind::WouldBlock | ErrorKind::TimedOut => {
                bail!("no progress on the socket for {IO_TIMEOUT:?} (the other process is gone or stuck)")
            }
            _ => return Err(error).context("socket I/O"),
        }
        patience.check(*self.since.get_or_insert_with(Instant::now), || "socket".to_owned())
    }
}
