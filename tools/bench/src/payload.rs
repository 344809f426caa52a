//! The benchmark payload: a counter pattern that the sender writes in full and the receiver
//! spot-checks in place.
//!
//! Byte `i` of a message with seed `s` is `(s + i) mod 256`. Writing it costs the same as
//! producing real data of that size (every byte is stored); checking one byte in every
//! [`DEFAULT_TOUCH_STRIDE`] makes the receiver pull every cache line of the message without
//! turning the benchmark into a checksum benchmark.

use std::num::NonZeroUsize;

use gprflow::msg::PayloadWriter;

/// By default the receiver reads one byte in 64: one per cache line.
pub const DEFAULT_TOUCH_STRIDE: NonZeroUsize = NonZeroUsize::new(64).expect("64 is not zero");

/// Writes the pattern with `seed` into every byte left in `out` (loaned shared memory).
pub fn fill_writer(out: &mut PayloadWriter<'_>, seed: u8) {
    out.fill_rest(|i| seed.wrapping_add(i as u8));
}

/// Writes the pattern with `seed` into every byte of `buf`.
pub fn fill(buf: &mut [u8], seed: u8) {
    for (i, b) in buf.iter_mut().enumerate() {
        *b = seed.wrapping_add(i as u8);
    }
}

/// Checks bytes 0, `stride`, 2 `stride`, ... of `buf` against the pattern with `seed` (a
/// stride of 0 counts as 1).
///
/// # Errors
/// The offset of the first byte that differs.
pub fn verify(buf: &[u8], seed: u8, stride: usize) -> Result<(), usize> {
    let stride = stride.max(1);
    for (k, b) in buf.iter().step_by(stride).enumerate() {
        let offset = k * stride;
        if *b != seed.wrapping_add(offset as u8) {
            return Err(offset);
        }
    }
    Ok(())
}

/// Seed of the pattern of message `seq` (pings and stream messages).
pub fn seed_of(seq: u64) -> u8 {
    seq as u8
}

/// Seed of the reply to message `seq` (differs from the request so that an echoed request is
/// not mistaken for a reply).
pub fn reply_seed_of(seq: u64) -> u8 {
    (seq as u8) ^ 0xA5
}

#[cfg(test)]
mod tests {
    use super::*;

    const STRIDE: usize = DEFAULT_TOUCH_STRIDE.get();

    #[test]
    fn filled_buffers_verify_and_corruption_is_found() {
        let mut buf = vec![0_u8; 4096];
        fill(&mut buf, 7);
        assert_eq!(verify(&buf, 7, STRIDE), Ok(()));
        assert_eq!(verify(&buf, 8, STRIDE), Err(0));
        if let Some(b) = buf.get_mut(3 * STRIDE) {
            *b ^= 1;
        }
        assert_eq!(verify(&buf, 7, STRIDE), Err(3 * STRIDE));
        assert_eq!(verify(&buf, 7, buf.len()), Ok(()));
        assert_eq!(verify(&buf, 7, 1), Err(3 * STRIDE));
    }
}
