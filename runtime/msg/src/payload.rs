//! Writing a loaned, uninitialised payload buffer without unsafe code, and a proof that it
//! was written in full.
//!
//! A transport loans `len` bytes (shared memory with iceoryx2, the spare capacity of a
//! vector elsewhere), hands them to a fill step as a [`PayloadWriter`], and may treat the
//! bytes as initialised only when the fill step returns the [`Written`] token of that very
//! buffer. Only [`PayloadWriter::finish`] makes a token, and only after every byte was
//! written, so safe code cannot make a transport send uninitialised memory: a fill step that
//! writes nothing has no token to return, and a token of another buffer is refused by
//! [`fill_payload`]. Both of these fail to compile:
//!
//! ```compile_fail
//! use std::mem::MaybeUninit;
//! let mut buf = [MaybeUninit::<u8>::uninit(); 100];
//! // a fill step that writes nothing and claims success
//! gprflow_msg::fill_payload(&mut buf, |_w| Ok(())).unwrap();
//! ```
//!
//! ```compile_fail
//! // a token made up by hand
//! let token = gprflow_msg::Written { addr: 0, len: 100 };
//! ```

use std::mem::MaybeUninit;

use super::{MsgError, Result};

/// Proof that a whole payload buffer was written: made only by [`PayloadWriter::finish`].
///
/// It names the buffer (address and length), so a token of one buffer does not vouch for
/// another.
#[derive(Debug, PartialEq, Eq)]
#[must_use = "a transport sends the payload only with its token"]
pub struct Written {
    addr: usize,
    len: usize,
}

impl Written {
    /// Whether this token vouches for `buf`: made by a writer over exactly these bytes.
    pub fn covers(&self, buf: &[MaybeUninit<u8>]) -> bool {
        self.addr == buf.as_ptr() as usize && self.len == buf.len()
    }
}

/// Writes a payload buffer front to back; [`finish`](Self::finish) gives the [`Written`]
/// token once every byte is written.
#[derive(Debug)]
pub struct PayloadWriter<'a> {
    buf: &'a mut [MaybeUninit<u8>],
    pos: usize,
}

impl<'a> PayloadWriter<'a> {
    /// A writer at the start of `buf`.
    pub fn new(buf: &'a mut [MaybeUninit<u8>]) -> Self {
        Self { buf, pos: 0 }
    }

    /// The buffer's whole length.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether the buffer holds no byte at all.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Bytes written so far.
    pub fn written(&self) -> usize {
        self.pos
    }

    /// Bytes still to write.
    pub fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Appends `data`.
    ///
    /// # Errors
    /// [`MsgError::BufferSize`] when `data` does not fit (nothing is written then).
    pub fn put(&mut self, data: &[u8]) -> Result<()> {
        if data.len() > self.remaining() {
            return Err(MsgError::BufferSize {
                expected: self.pos + data.len(),
                actual: self.buf.len(),
            });
        }
        let dst = &mut self.buf[self.pos..self.pos + data.len()];
        // SAFETY: `MaybeUninit<u8>` has the layout of `u8`; `dst` and `data` have the same
        // length and cannot overlap (one is borrowed mutably, the other shared).
        unsafe {
            std::ptr::copy_nonoverlapping(data.as_ptr(), dst.as_mut_ptr().cast::<u8>(), data.len());
        }
        self.pos += data.len();
        Ok(())
    }

    /// Appends `count` zero bytes (alignment padding), or as many as fit.
    ///
    /// # Errors
    /// [`MsgError::BufferSize`] when they do not all fit.
    pub fn zeros(&mut self, count: usize) -> Result<()> {
        if count > self.remaining() {
            return Err(MsgError::BufferSize {
                expected: self.pos + count,
                actual: self.buf.len(),
            });
        }
        for slot in &mut self.buf[self.pos..self.pos + count] {
            slot.write(0);
        }
        self.pos += count;
        Ok(())
    }

    /// Writes every remaining byte as `byte(i)`, `i` its offset in the buffer.
    pub fn fill_rest(&mut self, mut byte: impl FnMut(usize) -> u8) {
        let start = self.pos;
        for (k, slot) in self.buf[start..].iter_mut().enumerate() {
            slot.write(byte(start + k));
        }
        self.pos = self.buf.len();
    }

    /// The token for this buffer.
    ///
    /// # Errors
    /// [`MsgError::BufferSize`] when fewer bytes were written than the buffer holds.
    pub fn finish(self) -> Result<Written> {
        if self.pos != self.buf.len() {
            return Err(MsgError::BufferSize {
                expected: self.buf.len(),
                actual: self.pos,
            });
        }
        Ok(Written {
            addr: self.buf.as_ptr() as usize,
            len: self.buf.len(),
        })
    }
}

/// Runs a fill step over `buf` and checks the token it returns: on `Ok`, every byte of
/// `buf` is initialised.
///
/// # Errors
/// The fill step's error, or [`MsgError::ForeignToken`] when it returned a token of another
/// buffer.
pub fn fill_payload(
    buf: &mut [MaybeUninit<u8>],
    fill: impl FnOnce(PayloadWriter<'_>) -> Result<Written>,
) -> Result<()> {
    let written = fill(PayloadWriter::new(buf))?;
    if written.covers(buf) {
        Ok(())
    } else {
        Err(MsgError::ForeignToken)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_writer_that_stops_short_gives_no_token() {
        let mut buf = [MaybeUninit::<u8>::uninit(); 8];
        let mut w = PayloadWriter::new(&mut buf);
        w.put(&[1, 2, 3]).expect("fits");
        assert_eq!(w.finish(), Err(MsgError::BufferSize { expected: 8, actual: 3 }));
    }

    #[test]
    fn writing_past_the_end_is_refused_and_writes_nothing() {
        let mut buf = [MaybeUninit::<u8>::uninit(); 4];
        let mut w = PayloadWriter::new(&mut buf);
        w.put(&[9, 9]).expect("fits");
        assert!(w.put(&[1, 2, 3]).is_err());
        assert!(w.zeros(3).is_err());
        assert_eq!(w.written(), 2);
    }

    #[test]
    fn a_full_buffer_gives_its_token_and_its_bytes() {
        let mut buf = [MaybeUninit::<u8>::uninit(); 6];
        fill_payload(&mut buf, |mut w| {
            w.put(&[7, 8])?;
            w.zeros(1)?;
            w.fill_rest(|i| i as u8);
            w.finish()
        })
        .expect("filled");
        // SAFETY: `fill_payload` returned Ok, so every byte was written.
        let bytes: Vec<u8> = buf.iter().map(|b| unsafe { b.assume_init() }).collect();
        assert_eq!(bytes, [7, 8, 0, 3, 4, 5]);
    }

    #[test]
    fn a_token_of_another_buffer_is_refused() {
        let mut other = [MaybeUninit::<u8>::uninit(); 4];
        let mut w = PayloadWriter::new(&mut other);
        w.fill_rest(|_| 1);
        let foreign = w.finish().expect("full");
        let mut buf = [MaybeUninit::<u8>::uninit(); 4];
        assert_eq!(fill_payload(&mut buf, |_w| Ok(foreign)), Err(MsgError::ForeignToken));
    }

    #[test]
    fn an_empty_buffer_needs_no_byte() {
        let mut buf: [MaybeUninit<u8>; 0] = [];
        assert_eq!(fill_payload(&mut buf, |out| out.finish()), Ok(()));
    }
}
