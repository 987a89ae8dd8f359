//! The write buffer between the relay and the port: frames in order, the front one
//! possibly part written, and a frame not yet begun withdrawn when flow control held
//! it back past its deadline. Plain data: the loop writes what `pending` gives.

use bytes::Bytes;
use std::collections::VecDeque;

/// Frames waiting to be written to the port, in order. A frame not yet begun can be
/// withdrawn; one partly written is finished, so the device's parser stays in step.
#[derive(Debug, Default)]
pub(super) struct Outgoing {
    frames: VecDeque<(u16, Bytes)>,
    /// Bytes of the front frame already written.
    written: usize,
    len: usize,
}

impl Outgoing {
    pub(super) fn push(&mut self, tid: u16, frame: Bytes) {
        self.len += frame.len();
        self.frames.push_back((tid, frame));
    }

    pub(super) fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Bytes still to write.
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// The unwritten rest of the front frame.
    pub(super) fn pending(&self) -> &[u8] {
        self.frames
            .front()
            .map_or(&[][..], |(_, f)| &f[self.written..])
    }

    pub(super) fn advance(&mut self, n: usize) {
        self.written += n;
        self.len -= n;
        if let Some((_, f)) = self.frames.front() {
            if self.written >= f.len() {
                self.frames.pop_front();
                self.written = 0;
            }
        }
    }

    /// Removes the frame for `tid` if none of it has been written.
    pub(super) fn withdraw(&mut self, tid: u16) -> bool {
        let Some(i) = self.frames.iter().position(|(t, _)| *t == tid) else {
            return false;
        };
        if i == 0 && self.written > 0 {
            return false;
        }
        let (_, f) = self.frames.remove(i).expect("index found above");
        self.len -= f.len();
        true
    }

    pub(super) fn clear(&mut self) {
        self.frames.clear();
        self.written = 0;
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::Outgoing;
    use bytes::Bytes;

    #[test]
    fn outgoing_writes_in_order_and_withdraws_only_unstarted_frames() {
        let mut o = Outgoing::default();
        o.push(1, Bytes::from_static(b"abc"));
        o.push(2, Bytes::from_static(b"de"));
        o.push(3, Bytes::from_static(b"f"));
        assert_eq!(o.len(), 6);
        o.advance(2);
        assert_eq!(o.pending(), b"c");
        assert!(!o.withdraw(1), "partly written: finished, not withdrawn");
        assert!(o.withdraw(2));
        assert_eq!(o.len(), 2);
        o.advance(1);
        assert_eq!(o.pending(), b"f");
        o.advance(1);
        assert!(o.is_empty());
        assert_eq!(o.len(), 0);
        assert!(!o.withdraw(3));
    }
}
