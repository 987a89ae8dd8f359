//! What the scheduler asks of a request it queues (`Queued`), and what makes two reads
//! the same read (`ReadKey`): the relay's requests and the tests' answer it.

use super::super::ConnId;

/// What makes two reads the same read: the unit and the PDU (function code 01-04,
/// address, count). Two requests with the same key get the same reply from the device
/// if nothing acted on it in between.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(in crate::line::relay) struct ReadKey {
    pub(in crate::line::relay) unit: u8,
    pub(in crate::line::relay) pdu: [u8; 5],
}

impl std::hash::Hash for ReadKey {
    /// As one word: one step of the hasher, not one for each field and byte.
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        let [f, a0, a1, c0, c1] = self.pdu;
        state.write_u64(u64::from_le_bytes([self.unit, f, a0, a1, c0, c1, 0, 0]));
    }
}

/// What the scheduler needs to know of a request.
pub(in crate::line::relay) trait Queued: Sized {
    /// The master that sent it (the first of the masters it serves).
    fn conn(&self) -> ConnId;
    /// The unit it is for.
    fn unit(&self) -> u8;
    /// A read (FC 01-04 of one unit) that an identical read may join; `None` for
    /// anything else.
    fn read_key(&self) -> Option<ReadKey>;
    /// May it act on its unit (anything but a read)? It ends the chance for reads
    /// queued before it to be joined by reads that come after it; to unit 0, for every
    /// unit (a broadcast on a bus).
    fn acts(&self) -> bool;
    /// The masters it serves, once for each of their requests it answers, in the
    /// order they asked.
    fn masters(&self) -> impl Iterator<Item = ConnId> + '_;
    /// `other`, an identical read, is answered with this one.
    fn join(&mut self, other: Self);
    /// Takes out the requests of `conn` as a request of their own, leaving the others';
    /// `None` when it serves no other master (then the whole request is `conn`'s) or
    /// does not serve `conn`.
    fn leave(&mut self, conn: ConnId) -> Option<Self>;
    /// Takes out the newest request of `conn` alone, as [`Queued::leave`] does all of
    /// them; `None` when it is the only request this one answers.
    fn leave_one(&mut self, conn: ConnId) -> Option<Self>;
    /// The turn that last put it on the line (`set_turn`): a resend is checked
    /// against it.
    fn turn(&self) -> u64;
    fn set_turn(&mut self, turn: u64);

    /// How many masters' requests it answers.
    fn served(&self) -> usize {
        self.masters().count()
    }
}
