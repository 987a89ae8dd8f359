//! The turnaround of an RS-485 transmitter the gateway switches itself
//! (`serial.direction`, docs/rs485.md), as plain data with the time passed in: on
//! before a request's first byte is written (and `direction_delay_before_us` before
//! it), off once its last stop bit has left the UART (and `direction_delay_after_us`
//! after), so the device's reply, which may begin 3.5 character times after the
//! request (Modbus over Serial Line V1.02 §2.5.1.1), finds the bus free. The loop
//! does what [`Act`] says and tells what happened.
//!
//! When the last stop bit has left: looked at (TIOCSERGETLSR, "transmitter empty")
//! from the earliest instant it can have, the frame's time on the wire after it was
//! written, and again every quarter of a character until it has, each look on the
//! relay's microsecond timer, never by spinning; where the port cannot tell, when the
//! drain (`tcdrain`) returns, but never before that earliest instant: a drain may
//! return while bytes are still on their way (a pseudo-terminal's at once, a USB
//! adapter's while its own FIFO still holds them), and a transmitter switched off
//! then cuts the request's tail.

use std::time::Duration;
use tokio::time::Instant;

/// What the loop must do now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Act {
    /// Switch the transmitter on.
    On,
    /// Switch the transmitter off.
    Off,
    /// Ask the port whether its transmitter is empty, and tell [`Turnaround::looked`].
    Look,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// The transmitter is off.
    Receive,
    /// On; bytes may be written from `ready_at`.
    Sending { ready_at: Instant },
    /// Every byte of the frame handed to the port: looked at from `look_at`; `None`
    /// where the port cannot tell, then the drain's end says it; `drained`: it has
    /// returned.
    Emptying {
        look_at: Option<Instant>,
        drained: bool,
    },
    /// The last stop bit has left: off at `off_at`.
    Trailing { off_at: Instant },
}

/// The transmitter's state and its timing.
#[derive(Debug)]
pub(super) struct Turnaround {
    before: Duration,
    after: Duration,
    /// How long between looks while the last character is still leaving.
    poll: Duration,
    /// The port can say whether its transmitter is empty (until a look says it cannot).
    looks: bool,
    phase: Phase,
    /// The earliest the last stop bit could leave: the turnaround counts from it.
    earliest: Option<Instant>,
}

impl Turnaround {
    /// `before` and `after` the delays; `char_time` one character on the wire.
    pub(super) fn new(before: Duration, after: Duration, char_time: Duration) -> Turnaround {
        Turnaround {
            before,
            after,
            poll: (char_time / 4).max(Duration::from_micros(10)),
            looks: true,
            phase: Phase::Receive,
            earliest: None,
        }
    }

    /// Bytes wait to be written: switched on unless it is (the loop calls this only
    /// when no request on the line awaits its reply, one at a time on RTU/ASCII).
    pub(super) fn begin(&mut self, now: Instant) -> Option<Act> {
        match self.phase {
            Phase::Receive => {
                self.phase = Phase::Sending {
                    ready_at: now + self.before,
                };
                self.earliest = None;
                Some(Act::On)
            }
            _ => None,
        }
    }

    /// The switch asked for by [`Turnaround::begin`] returned at `at`: the delay
    /// before the first byte counts from then, not from the instant the loop decided
    /// (the switch itself, an ioctl or a GPIO write, takes time of its own).
    pub(super) fn switched_on(&mut self, at: Instant) {
        if let Phase::Sending { ready_at } = &mut self.phase {
            *ready_at = at + self.before;
        }
    }

    /// May bytes be written now: on, and the delay before them passed.
    pub(super) fn may_write(&self, now: Instant) -> bool {
        matches!(self.phase, Phase::Sending { ready_at } if now >= ready_at)
    }

    /// The frame's last byte was handed to the port; its last stop bit can leave at
    /// `earliest` at the soonest.
    pub(super) fn written(&mut self, earliest: Instant) {
        if let Phase::Sending { .. } = self.phase {
            self.earliest = Some(earliest);
            self.phase = Phase::Emptying {
                look_at: self.looks.then_some(earliest),
                drained: false,
            };
        }
    }

    /// The drain has returned: everything written has left the driver's buffer.
    pub(super) fn drained(&mut self, now: Instant) {
        if let Phase::Emptying { .. } = self.phase {
            let at = self.not_before_earliest(now);
            if self.looks {
                // Its shift register may still hold the last character: look now,
                // or once it can have left.
                self.phase = Phase::Emptying {
                    look_at: Some(at),
                    drained: true,
                };
            } else {
                self.emptied(at);
            }
        }
    }

    /// What the port said when looked at: empty, not yet, or `None`: it cannot tell
    /// (then the drain's end stands for it, at this open and after).
    pub(super) fn looked(&mut self, empty: Option<bool>, now: Instant) {
        if let Phase::Emptying { drained, .. } = self.phase {
            match empty {
                Some(true) => self.emptied(now),
                Some(false) => {
                    self.phase = Phase::Emptying {
                        look_at: Some(now + self.poll),
                        drained,
                    }
                }
                None => {
                    self.looks = false;
                    if drained {
                        self.emptied(self.not_before_earliest(now));
                    } else {
                        self.phase = Phase::Emptying {
                            look_at: None,
                            drained,
                        };
                    }
                }
            }
        }
    }

    /// The transmitter emptied at `at` (now, or the earliest instant the last stop bit
    /// can leave, if later): off once the delay after has passed.
    fn emptied(&mut self, at: Instant) {
        self.phase = Phase::Trailing {
            off_at: at + self.after,
        };
    }

    /// `now`, or the earliest instant the frame's last stop bit can leave if that is
    /// later: no drain nor look can have seen it leave sooner.
    fn not_before_earliest(&self, now: Instant) -> Instant {
        self.earliest.map_or(now, |e| e.max(now))
    }

    /// What is due at `now`: a look, or switching off.
    pub(super) fn due(&mut self, now: Instant) -> Option<Act> {
        match self.phase {
            Phase::Emptying {
                look_at: Some(at), ..
            } if now >= at => Some(Act::Look),
            Phase::Trailing { off_at } if now >= off_at => {
                self.phase = Phase::Receive;
                Some(Act::Off)
            }
            _ => None,
        }
    }

    /// When the loop must come back after `now`: the end of the delay before, the
    /// next look, the end of the delay after. Never `now` or before: a wake that has
    /// passed would wake the loop at once, again and again (a write held back by flow
    /// control leaves the delay before passed for as long as it is held).
    pub(super) fn wake(&self, now: Instant) -> Option<Instant> {
        let at = match self.phase {
            Phase::Receive => None,
            Phase::Sending { ready_at } => Some(ready_at),
            Phase::Emptying { look_at, .. } => look_at,
            Phase::Trailing { off_at } => Some(off_at),
        };
        at.filter(|&at| at > now)
    }

    /// On, with no byte of the frame handed to the port yet.
    pub(super) fn sending(&self) -> bool {
        matches!(self.phase, Phase::Sending { .. })
    }

    /// The frame is abandoned (the port lost, the request timed out while its bytes
    /// were held back): off now if on.
    pub(super) fn abort(&mut self) -> Option<Act> {
        match std::mem::replace(&mut self.phase, Phase::Receive) {
            Phase::Receive => None,
            _ => Some(Act::Off),
        }
    }

    /// The port was opened afresh: its switch was taken off, and whether it can tell
    /// its transmitter empty is to be learnt again.
    pub(super) fn reset(&mut self) {
        self.phase = Phase::Receive;
        self.looks = true;
        self.earliest = None;
    }

    /// How long after the earliest instant the last stop bit could leave the
    /// transmitter was switched off at `now` (the figure docs/rs485.md asks for).
    pub(super) fn late_by(&self, now: Instant) -> Option<Duration> {
        self.earliest.map(|e| now.saturating_duration_since(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn us(n: u64) -> Duration {
        Duration::from_micros(n)
    }

    /// A port whose transmitter empties at `empty_at`, with or without an LSR, driven
    /// the way the relay's loop drives the turnaround; returns the switch's history.
    struct Bench {
        t: Turnaround,
        now: Instant,
        on: bool,
        /// (when, on) for every switch.
        history: Vec<(Instant, bool)>,
        /// When bytes were written, and whether the switch was on then.
        writes: Vec<(Instant, bool)>,
        lsr: bool,
        empty_at: Option<Instant>,
    }

    impl Bench {
        fn new(before: u64, after: u64, lsr: bool) -> Bench {
            Bench {
                t: Turnaround::new(us(before), us(after), us(87)),
                now: Instant::now(),
                on: false,
                history: Vec::new(),
                writes: Vec::new(),
                lsr,
                empty_at: None,
            }
        }

        /// One turn of the loop: begin if `want`, then whatever is due.
        fn turn(&mut self, want: bool) {
            let mut act = if want { self.t.begin(self.now) } else { None };
            while let Some(a) = act.take().or_else(|| self.t.due(self.now)) {
                match a {
                    Act::On | Act::Off => {
                        let on = a == Act::On;
                        assert_ne!(self.on, on, "switched {on} twice");
                        self.on = on;
                        self.history.push((self.now, on));
                    }
                    Act::Look => {
                        let empty = self
                            .lsr
                            .then(|| self.empty_at.is_some_and(|at| self.now >= at));
                        self.t.looked(empty, self.now);
                    }
                }
            }
        }

        fn write(&mut self) -> bool {
            if self.t.may_write(self.now) {
                self.writes.push((self.now, self.on));
                true
            } else {
                false
            }
        }
    }

    /// A switch that takes time: the delay before counts from its return.
    #[test]
    fn the_delay_before_counts_from_the_switch_done() {
        let mut t = Turnaround::new(us(300), us(200), us(87));
        let t0 = Instant::now();
        assert_eq!(t.begin(t0), Some(Act::On));
        t.switched_on(t0 + us(40));
        assert!(!t.may_write(t0 + us(300)), "300 µs after the decision only");
        assert!(!t.may_write(t0 + us(339)));
        assert!(t.may_write(t0 + us(340)));
        assert_eq!(t.wake(t0), Some(t0 + us(340)));
    }

    /// One request: on, the delay before, written, off only once the transmitter is
    /// empty and the delay after has passed; with an LSR, the drain's end is not
    /// waited for.
    #[test]
    fn on_before_the_first_byte_off_after_the_last_stop_bit() {
        for lsr in [true, false] {
            let mut b = Bench::new(100, 50, lsr);
            let t0 = b.now;
            b.turn(true);
            assert_eq!(b.history, [(t0, true)]);
            assert!(!b.write(), "not before the delay before");
            assert_eq!(b.t.wake(b.now), Some(t0 + us(100)));
            b.now = t0 + us(100);
            assert!(b.write());
            // 8 characters: their last stop bit leaves 700 µs later at the soonest,
            // and in fact at 760 µs.
            let earliest = b.now + us(700);
            b.t.written(earliest);
            b.empty_at = Some(b.now + us(760));
            b.now = earliest;
            b.turn(false);
            assert!(b.on, "not empty yet");
            if lsr {
                // Looked at every quarter character until it is empty.
                let mut looks = 0;
                while b.history.len() == 1 {
                    b.now = b.t.wake(b.now).expect("a look or the off is due");
                    b.turn(false);
                    looks += 1;
                    assert!(looks < 10, "looked too often");
                }
                let off = b.history[1];
                assert!(!off.1);
                let empty = t0 + us(100) + us(760);
                assert!(off.0 >= empty + us(50), "off before the delay after");
                assert!(off.0 <= empty + us(50) + us(22), "off a look late at most");
            } else {
                assert_eq!(b.t.wake(b.now), None, "waits for the drain");
                b.now = t0 + us(2000);
                b.t.drained(b.now);
                b.turn(false);
                assert!(b.on, "the delay after");
                b.now += us(50);
                b.turn(false);
                assert_eq!(b.history[1], (b.now, false));
            }
        }
    }

    /// A port that cannot say its transmitter is empty learns it at the first look and
    /// waits for the drain from then on.
    #[test]
    fn without_an_lsr_the_drain_decides() {
        let mut b = Bench::new(0, 0, false);
        b.turn(true);
        assert!(b.write());
        b.t.written(b.now);
        b.turn(false);
        assert!(b.on && !b.t.looks, "looked once, learnt");
        b.t.drained(b.now);
        b.turn(false);
        assert!(!b.on);
        b.turn(true);
        b.t.written(b.now);
        assert_eq!(b.t.wake(b.now), None, "no look this time");
    }

    /// A drain that returns while the bytes are still on their way (a pseudo-terminal's
    /// returns at once) does not switch off before their time on the wire has passed,
    /// with or without an LSR.
    #[test]
    fn an_early_drain_waits_for_the_wire() {
        for lsr in [true, false] {
            let mut b = Bench::new(0, 30, lsr);
            let t0 = b.now;
            b.turn(true);
            assert!(b.write());
            let earliest = t0 + us(700);
            b.t.written(earliest);
            b.empty_at = Some(t0);
            b.now = t0 + us(10);
            b.t.drained(b.now);
            b.turn(false);
            assert!(b.on, "not off while the bytes are on the wire");
            assert_eq!(b.t.wake(b.now), Some(earliest));
            b.now = earliest;
            b.turn(false);
            assert!(b.on, "the delay after");
            b.now = b.t.wake(b.now).expect("the off is due");
            b.turn(false);
            assert_eq!(b.history[1], (earliest + us(30), false));
        }
    }

    /// Abandoned while on: off at once; a fresh open starts off, learning again.
    #[test]
    fn abort_switches_off() {
        let mut t = Turnaround::new(Duration::ZERO, Duration::ZERO, us(87));
        let now = Instant::now();
        assert_eq!(t.abort(), None, "off already");
        assert_eq!(t.begin(now), Some(Act::On));
        assert_eq!(t.begin(now), None, "on already");
        assert_eq!(t.abort(), Some(Act::Off));
        t.looks = false;
        t.reset();
        assert!(t.looks && t.phase == Phase::Receive);
    }

    #[derive(Debug, Clone)]
    enum Step {
        /// Time passes.
        Wait(u64),
        /// The loop turns, with bytes to write or not.
        Turn(bool),
        /// A write, if allowed; then the frame is whole or not.
        Write(bool),
        /// The drain returns.
        Drained,
        /// The port is lost or the request abandoned.
        Abort,
    }

    fn step() -> impl Strategy<Value = Step> {
        prop_oneof![
            (0u64..400).prop_map(Step::Wait),
            any::<bool>().prop_map(Step::Turn),
            any::<bool>().prop_map(Step::Write),
            Just(Step::Drained),
            Just(Step::Abort),
        ]
    }

    proptest! {
        /// Whatever happens in whatever order: the switch alternates on and off; every
        /// byte is written while it is on, and no sooner than the delay before after it
        /// went on; it goes off only once the frame is whole, the transmitter said
        /// empty (or, with no LSR, the drain returned) and the delay after passed, or
        /// when the frame is abandoned; and once off, it stays off until bytes are
        /// waiting again, so it is never on while a reply can come.
        #[test]
        fn the_order_holds(
            before in 0u64..300,
            after in 0u64..300,
            lsr in any::<bool>(),
            empties in 0u64..500,
            wire in 0u64..800,
            steps in proptest::collection::vec(step(), 1..80),
        ) {
            let mut b = Bench::new(before, after, lsr);
            let mut on_at = None;
            // The frame is whole, and when its transmitter emptied (LSR) or drained.
            let mut whole = false;
            let mut emptied: Option<Instant> = None;
            let mut aborted = false;
            // The earliest the frame's last stop bit can leave (its time on the wire).
            let mut earliest = b.now;
            for s in steps {
                let switched = b.history.len();
                let wants = matches!(s, Step::Turn(true));
                match s {
                    Step::Wait(n) => b.now += us(n),
                    Step::Turn(want) => b.turn(want),
                    Step::Write(last) => {
                        if !whole && b.write() {
                            prop_assert!(b.on, "a byte written while off");
                            let on = on_at.expect("on");
                            prop_assert!(b.now >= on + us(before), "written within the delay before");
                            if last {
                                whole = true;
                                earliest = b.now + us(wire);
                                b.t.written(earliest);
                                b.empty_at = Some(b.now + us(empties));
                            }
                        }
                    }
                    Step::Drained => {
                        if whole && !lsr {
                            emptied.get_or_insert(b.now);
                        }
                        b.t.drained(b.now);
                    }
                    Step::Abort => {
                        if b.t.abort().is_some() {
                            b.on = false;
                            b.history.push((b.now, false));
                            aborted = true;
                        }
                    }
                }
                for &(at, on) in &b.history[switched..] {
                    if on {
                        // Only when bytes wait: between a frame and the next, the bus
                        // is the device's.
                        prop_assert!(wants, "on with nothing to send");
                        on_at = Some(at);
                        whole = false;
                        emptied = None;
                        aborted = false;
                        b.empty_at = None;
                    } else if !aborted {
                        prop_assert!(whole, "off before the frame was whole");
                        let empty = if lsr { b.empty_at.expect("written") } else { emptied.expect("drained") };
                        prop_assert!(at >= empty + us(after), "off before the last stop bit and the delay after");
                        // Whatever the port or the drain says, never before the
                        // frame's time on the wire has passed.
                        prop_assert!(at >= earliest + us(after), "off before the bytes can have left");
                    }
                }
                if !b.on {
                    prop_assert!(!b.t.may_write(b.now), "may write while off");
                }
                if let Some(w) = b.t.wake(b.now) {
                    prop_assert!(w > b.now, "a wake that has passed");
                }
            }
        }
    }
}
