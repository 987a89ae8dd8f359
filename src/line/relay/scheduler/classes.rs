//! Priority classes (docs/masters.md "Priority"): each master's class, and the class
//! a request goes as, the highest of the masters it serves. Which class goes next is
//! the scheduler's `next` (`LOWER_EVERY`).

use super::{Queued, Scheduler};
use crate::line::relay::ConnId;

impl<R: Queued> Scheduler<R> {
    /// `conn`'s priority class from now on (0, the lowest, unless set).
    pub(in crate::line::relay) fn set_class(&mut self, conn: ConnId, class: u8) {
        if class == 0 {
            self.classes.remove(&conn);
        } else {
            self.classes.insert(conn, class);
        }
    }

    /// The class `req` goes as: the highest of the masters it serves.
    pub(in crate::line::relay) fn class_of(&self, req: &R) -> u8 {
        if self.classes.is_empty() {
            return 0;
        }
        self.classes_of(req).1
    }

    /// The lowest and the highest class of the masters `req` serves.
    pub(super) fn classes_of(&self, req: &R) -> (u8, u8) {
        let each = req
            .masters()
            .map(|c| self.classes.get(&c).copied().unwrap_or(0));
        each.fold((u8::MAX, 0), |(lo, hi), c| (lo.min(c), hi.max(c)))
    }
}
