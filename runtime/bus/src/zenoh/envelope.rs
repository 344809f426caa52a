//! The bytes on the wire: the envelope before every frame (link seq and frame header) and
//! the acknowledgements the subscriber sends back.

use crate::FrameHeader;

/// Envelope: link seq (8 bytes), then the frame header (24 bytes), then the payload.
pub(super) const ENVELOPE: usize = 32;
/// Link seq of a publisher heartbeat (the header's `seq` field carries the next link seq).
pub(super) const PUBLISHER_HEARTBEAT: u64 = u64::MAX;

/// Acknowledgement kinds (first byte of an ack).
pub(super) const ACK: u8 = 0;
pub(super) const ACK_GAP: u8 = 1;
pub(super) const ACK_BYE: u8 = 2;
pub(super) const ACK_LEN: usize = 24;

pub(super) fn write_header(out: &mut [u8], link: u64, header: &FrameHeader) {
    out[0..8].copy_from_slice(&link.to_le_bytes());
    out[8..16].copy_from_slice(&header.seq.to_le_bytes());
    out[16..24].copy_from_slice(&header.stamp_ns.to_le_bytes());
    out[24..28].copy_from_slice(&header.kind.to_le_bytes());
    out[28..32].copy_from_slice(&header.reserved.to_le_bytes());
}

pub(super) fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(w)
}

pub(super) fn read_header(b: &[u8]) -> Option<(u64, FrameHeader)> {
    if b.len() < ENVELOPE {
        return None;
    }
    let mut kind = [0u8; 4];
    kind.copy_from_slice(&b[24..28]);
    let mut reserved = [0u8; 4];
    reserved.copy_from_slice(&b[28..32]);
    Some((
        u64_at(b, 0),
        FrameHeader {
            seq: u64_at(b, 8),
            stamp_ns: u64_at(b, 16) as i64,
            kind: u32::from_le_bytes(kind),
            reserved: u32::from_le_bytes(reserved),
        },
    ))
}

pub(super) fn ack_bytes(kind: u8, received: u64, consumed: u64) -> Vec<u8> {
    let mut b = vec![0u8; ACK_LEN];
    b[0] = kind;
    b[8..16].copy_from_slice(&received.to_le_bytes());
    b[16..24].copy_from_slice(&consumed.to_le_bytes());
    b
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::FrameKind;

    #[test]
    fn an_envelope_reads_back_what_was_written() {
        let header = FrameHeader::control(FrameKind::Watermark, 7, -42);
        let mut out = vec![0u8; ENVELOPE + 3];
        write_header(&mut out, 1234, &header);
        assert_eq!(read_header(&out), Some((1234, header)));
        assert_eq!(read_header(&out[..ENVELOPE - 1]), None, "a short envelope is refused");
    }

    #[test]
    fn an_ack_carries_its_kind_and_counts() {
        let b = ack_bytes(ACK_GAP, 5, 3);
        assert_eq!((b.len(), b[0], u64_at(&b, 8), u64_at(&b, 16)), (ACK_LEN, ACK_GAP, 5, 3));
    }
}
