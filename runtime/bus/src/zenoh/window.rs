//! The publisher's go-back-N window, as plain state: what was sent and not yet acknowledged,
//! what the subscriber has received and consumed, and when to resend. Every method takes the
//! time as an argument, so the resend rules are tested on a made-up clock.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::RESEND_AFTER;
use super::envelope::{ACK_BYE, ACK_GAP};
use crate::FrameKind;

/// One frame sent and not yet acknowledged as received.
#[derive(Debug)]
struct Pending<B> {
    link: u64,
    seq: u64,
    kind: FrameKind,
    bytes: B,
}

/// The sending side of one topic; `B` is the frame's bytes as sent (zenoh's `ZBytes`).
#[derive(Debug)]
pub(super) struct SendWindow<B> {
    window: VecDeque<Pending<B>>,
    next_link: u64,
    /// The subscriber has every frame below this link seq.
    received: u64,
    /// Its consumer has taken every frame below this link seq.
    consumed: u64,
    attached: bool,
    gone: bool,
    last_heard: Option<Instant>,
    last_progress: Option<Instant>,
    resend_now: bool,
}

impl<B> Default for SendWindow<B> {
    fn default() -> Self {
        Self {
            window: VecDeque::new(),
            next_link: 0,
            received: 0,
            consumed: 0,
            attached: false,
            gone: false,
            last_heard: None,
            last_progress: None,
            resend_now: false,
        }
    }
}

impl<B: Clone> SendWindow<B> {
    /// The link seq the next frame gets.
    pub(super) fn next_link(&self) -> u64 {
        self.next_link
    }

    /// Frames sent and not yet taken by the subscriber's consumer.
    pub(super) fn unconsumed(&self) -> u64 {
        self.next_link - self.consumed
    }

    /// Whether every frame sent was taken by the consumer.
    pub(super) fn all_consumed(&self) -> bool {
        self.consumed >= self.next_link
    }

    /// Whether a subscriber has answered at all.
    pub(super) fn attached(&self) -> bool {
        self.attached
    }

    /// Whether the subscriber said goodbye.
    pub(super) fn gone(&self) -> bool {
        self.gone
    }

    /// When the subscriber was last heard from.
    pub(super) fn last_heard(&self) -> Option<Instant> {
        self.last_heard
    }

    /// Takes the next link seq for a frame; a lossless one (`keep`) stays in the window
    /// until the subscriber acknowledges it.
    pub(super) fn send(&mut self, seq: u64, kind: FrameKind, bytes: B, keep: bool, now: Instant) -> u64 {
        let link = self.next_link;
        self.next_link += 1;
        if keep {
            if self.window.is_empty() {
                self.last_progress = Some(now);
            }
            self.window.push_back(Pending { link, seq, kind, bytes });
        }
        link
    }

    /// An acknowledgement of `kind`: the subscriber has `received` and its consumer has
    /// taken `consumed` (link seqs, one past the last).
    pub(super) fn on_ack(&mut self, kind: u8, received: u64, consumed: u64, now: Instant) {
        if kind == ACK_BYE {
            self.gone = true;
            return;
        }
        self.attached = true;
        self.last_heard = Some(now);
        if received > self.received {
            self.received = received.min(self.next_link);
            self.last_progress = Some(now);
            while self.window.front().is_some_and(|p| p.link < self.received) {
                self.window.pop_front();
            }
        }
        self.consumed = self.consumed.max(consumed.min(self.received));
        if kind == ACK_GAP {
            self.resend_now = true;
        }
    }

    /// The frames to send again now: every one not yet received, when the subscriber
    /// reported a gap or nothing advanced for [`RESEND_AFTER`]; none for a subscriber that
    /// left. A latest-only topic resends its control frames only.
    pub(super) fn due(&mut self, now: Instant, latest_only: bool) -> Vec<B> {
        let stalled = self.last_progress.is_none_or(|t| now.duration_since(t) > RESEND_AFTER);
        let outstanding = self.window.iter().any(|p| p.link >= self.received);
        if !outstanding || self.gone || !(self.resend_now || stalled) {
            return Vec::new();
        }
        self.resend_now = false;
        self.last_progress = Some(now);
        self.window
            .iter()
            .filter(|p| p.link >= self.received && (!latest_only || p.kind != FrameKind::Data))
            .map(|p| p.bytes.clone())
            .collect()
    }

    /// The data seqs of the frames not yet received, as `first..last` (one past).
    pub(super) fn undelivered(&self) -> (u64, u64) {
        let data = self.window.iter().filter(|p| p.link >= self.received);
        let first = data.clone().map(|p| p.seq).min().unwrap_or(0);
        let last = data
            .map(|p| p.seq + u64::from(p.kind == FrameKind::Data))
            .max()
            .unwrap_or(first);
        (first, last)
    }

    /// Whether the subscriber has been silent for longer than `timeout` (never heard: not
    /// silent, it may not be up yet).
    pub(super) fn silent_for(&self, now: Instant, timeout: Duration) -> Option<Instant> {
        self.last_heard.filter(|heard| now.duration_since(*heard) > timeout)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::zenoh::envelope::ACK;

    const MS: Duration = Duration::from_millis(1);

    /// A window with data frames seq 0..n sent at `t0`.
    fn sent(n: u64, t0: Instant) -> SendWindow<u64> {
        let mut w = SendWindow::default();
        for seq in 0..n {
            w.send(seq, FrameKind::Data, seq, true, t0);
        }
        w
    }

    #[test]
    fn nothing_is_resent_while_acks_advance_and_all_is_after_a_stall() {
        let t0 = Instant::now();
        let mut w = sent(4, t0);
        w.on_ack(ACK, 2, 1, t0 + 100 * MS);
        assert!(w.due(t0 + 300 * MS, false).is_empty(), "progress 200 ms ago");
        assert_eq!(
            w.due(t0 + 401 * MS, false),
            [2, 3],
            "stalled past RESEND_AFTER: from the first unreceived"
        );
        assert!(w.due(t0 + 500 * MS, false).is_empty(), "the resend counts as progress");
    }

    #[test]
    fn a_gap_report_resends_at_once() {
        let t0 = Instant::now();
        let mut w = sent(3, t0);
        w.on_ack(ACK_GAP, 1, 0, t0 + MS);
        assert_eq!(w.due(t0 + 2 * MS, false), [1, 2]);
        assert!(w.due(t0 + 3 * MS, false).is_empty(), "one resend per report");
    }

    #[test]
    fn acknowledged_frames_leave_the_window_and_counts_never_go_back() {
        let t0 = Instant::now();
        let mut w = sent(5, t0);
        w.on_ack(ACK, 3, 2, t0);
        w.on_ack(ACK, 1, 1, t0 + MS); // a late, older ack
        assert_eq!((w.unconsumed(), w.undelivered()), (3, (3, 5)));
        w.on_ack(ACK, 99, 99, t0 + 2 * MS); // more than was sent
        assert!(w.all_consumed());
        assert!(w.due(t0 + Duration::from_secs(1), false).is_empty());
    }

    #[test]
    fn latest_only_topics_resend_control_frames_only() {
        let t0 = Instant::now();
        let mut w = SendWindow::default();
        w.send(0, FrameKind::Data, 10u64, true, t0);
        w.send(1, FrameKind::Watermark, 11, true, t0);
        w.send(1, FrameKind::EndOfStream, 12, true, t0);
        w.on_ack(ACK_GAP, 0, 0, t0);
        assert_eq!(w.due(t0 + MS, true), [11, 12]);
    }

    #[test]
    fn a_subscriber_that_left_gets_nothing_and_silence_is_timed_from_its_last_word() {
        let t0 = Instant::now();
        let mut w = sent(2, t0);
        assert_eq!(
            w.silent_for(t0 + Duration::from_secs(100), Duration::from_secs(1)),
            None
        );
        w.on_ack(ACK, 0, 0, t0);
        assert_eq!(w.silent_for(t0 + 900 * MS, Duration::from_secs(1)), None);
        assert_eq!(w.silent_for(t0 + 1001 * MS, Duration::from_secs(1)), Some(t0));
        w.on_ack(ACK_BYE, 0, 0, t0 + MS);
        assert!(w.gone() && w.due(t0 + Duration::from_secs(5), false).is_empty());
    }

    #[test]
    fn frames_not_kept_take_a_link_seq_but_are_never_resent() {
        let t0 = Instant::now();
        let mut w = SendWindow::default();
        assert_eq!(w.send(0, FrameKind::Data, 1u64, false, t0), 0);
        assert_eq!(w.send(1, FrameKind::Data, 2, true, t0), 1);
        assert_eq!(w.due(t0 + Duration::from_secs(1), false), [2]);
        assert_eq!(w.next_link(), 2);
    }
}
