//! Where the references' pixels live. A run keeps a reference every `reference_spacing_m`
//! (0.3 m by default) and a 3 m submap's pixels are about 200 KB, so holding them all would
//! grow the stage by some 0.6 GB per kilometre. The loop closer holds only what the method
//! needs ([`super::Matcher::reference_needs_pixels`]): the learned model matches on the
//! features it encoded once, the oracle and the zeroth-order model on no pixels at all. For a
//! method that correlates pixels (the engineered one) the newest references stay in memory
//! and older ones move to an unnamed temporary file (removed by the system when the process
//! ends, however it ends), read back when a query finds one of them as a loop candidate. The
//! read gives the same `f32` values that were written, so a match does not depend on where its
//! reference was.

use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;

use crate::{Error, Result};

/// An append-only file of `f32` pixels (little-endian).
#[derive(Debug, Default)]
pub struct PixelSpill {
    file: Option<File>,
    bytes: u64,
}

impl PixelSpill {
    /// Appends `pixels`; returns where they start, in bytes.
    ///
    /// # Errors
    /// [`Error::Spill`] when the temporary file cannot be made or written.
    pub fn put(&mut self, pixels: &[f32]) -> Result<u64> {
        let file = match &mut self.file {
            Some(f) => f,
            None => self
                .file
                .insert(tempfile::tempfile().map_err(|e| Error::Spill(format!("cannot make it: {e}")))?),
        };
        let mut buf = Vec::with_capacity(pixels.len() * 4);
        for p in pixels {
            buf.extend_from_slice(&p.to_le_bytes());
        }
        file.write_all(&buf)
            .map_err(|e| Error::Spill(format!("cannot write {} bytes: {e}", buf.len())))?;
        let at = self.bytes;
        self.bytes += buf.len() as u64;
        Ok(at)
    }

    /// Reads `count` pixels written at `offset` into `out` (replacing its contents).
    ///
    /// # Errors
    /// [`Error::Spill`] when they cannot be read back.
    pub fn get(&self, offset: u64, count: usize, out: &mut Vec<f32>) -> Result<()> {
        let file = self
            .file
            .as_ref()
            .ok_or_else(|| Error::Spill("read before any write".into()))?;
        let mut buf = vec![0u8; count * 4];
        file.read_exact_at(&mut buf, offset)
            .map_err(|e| Error::Spill(format!("cannot read {count} pixels at byte {offset}: {e}")))?;
        out.clear();
        out.extend(
            buf.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        );
        Ok(())
    }

    /// Bytes written.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_read_back_bit_for_bit_wherever_they_were_written() {
        let mut spill = PixelSpill::default();
        let a: Vec<f32> = (0..1000).map(|i| (i as f32).sin() * 1e-3).collect();
        let b = vec![f32::MIN_POSITIVE, -0.0, f32::MAX, 1.5];
        let (oa, ob) = (spill.put(&a).expect("put"), spill.put(&b).expect("put"));
        assert_eq!((oa, ob, spill.bytes()), (0, 4000, 4016));
        let mut out = Vec::new();
        spill.get(ob, b.len(), &mut out).expect("get");
        assert_eq!(
            out.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        spill.get(oa, a.len(), &mut out).expect("get");
        assert_eq!(out, a);
        let e = spill.get(ob, 100, &mut out).expect_err("past the end").to_string();
        assert!(e.contains("cannot read 100 pixels at byte 4000"), "{e}");
    }
}
