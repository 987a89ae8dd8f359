//! The write buffer between the relay and the port: frames in order, the front one
//! possibly part written, and a frame not yet begun withdrawn when flow control held
//! it back past its deadline. Plain data: the loop writes what `pending` gives.

use std::collections::VecDeque;

/// Frames waiting to be written to the port, in order. A frame not yet begun can be
/// withdrawn; one partly written is finished, so the device's parser stays in step.
/// Their bytes are encoded straight into a buffer kept from frame to frame: no
/// allocation a request (docs/performance.md "A transaction on a quiet line").
#[derive(Debug, Default)]
pub(super) struct Outgoing {
    /// Each frame's request id and length, in order.
    frames: VecDeque<(u16, usize)>,
    /// Their bytes, back to back, the front frame's from `front`.
    bytes: Vec<u8>,
    front: usize,
    /// Bytes of the front frame already written.
    written: usize,
}

impl Outgoing {
    /// Queues the frame `encode` appends to the buffer, for request `tid`; its bytes.
    pub(super) fn push_with(&mut self, tid: u16, encode: impl FnOnce(&mut Vec<u8>)) -> &[u8] {
        let start = self.bytes.len();
        encode(&mut self.bytes);
        self.frames.push_back((tid, self.bytes.len() - start));
        &self.bytes[start..]
    }

    pub(super) fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Bytes still to write.
    pub(super) fn len(&self) -> usize {
        self.bytes.len() - self.front - self.written
    }

    /// The unwritten rest of the front frame.
    pub(super) fn pending(&self) -> &[u8] {
        self.frames.front().map_or(&[][..], |&(_, len)| {
            &self.bytes[self.front + self.written..self.front + len]
        })
    }

    pub(super) fn advance(&mut self, n: usize) {
        self.written += n;
        if let Some(&(_, len)) = self.frames.front() {
            if self.written >= len {
                self.frames.pop_front();
                self.front += len;
                self.written = 0;
            }
        }
        if self.frames.is_empty() {
            self.clear();
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
        let at = self.front
            + self
                .frames
                .iter()
                .take(i)
                .map(|&(_, len)| len)
                .sum::<usize>();
        let (_, len) = self.frames.remove(i).expect("index found above");
        self.bytes.drain(at..at + len);
        if self.frames.is_empty() {
            self.clear();
        }
        true
    }

    pub(super) fn clear(&mut self) {
        self.frames.clear();
        self.bytes.clear();
        self.front = 0;
        self.written = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::Outgoing;

    #[test]
    fn outgoing_writes_in_order_and_withdraws_only_unstarted_frames() {
        let mut o = Outgoing::default();
        let mut push = |tid, bytes: &[u8]| {
            assert_eq!(o.push_with(tid, |b| b.extend_from_slice(bytes)), bytes);
        };
        push(1, b"abc");
        push(2, b"de");
        push(3, b"f");
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
        // The buffer starts again from its beginning, its room kept.
        assert_eq!(o.push_with(4, |b| b.extend_from_slice(b"gh")), b"gh");
        assert!(o.withdraw(4) && o.is_empty() && o.pending().is_empty());
    }
}
