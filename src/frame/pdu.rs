//! What the function codes mean (docs/protocol.md §1): which requests are well formed, what
//! shape their replies must have, and which replies could exist at all.
//!
//! All functions take a PDU: the function code followed by its data. What they know of
//! each code comes from the one table, `super::function::TABLE`.

use super::function::{Echo, ExceptionCode, FunctionCode, Item, Spec};

/// Exception codes a device may answer with.
pub(crate) fn is_exception_code(code: u8) -> bool {
    ExceptionCode::new(code).is_known()
}

fn word(pdu: &[u8], at: usize) -> usize {
    usize::from(u16::from_be_bytes([pdu[at], pdu[at + 1]]))
}

/// The row of a request's function code, and whether the request has its shape;
/// `None` for a code that cannot be a request.
fn request_row(pdu: &[u8]) -> Option<(Option<&'static Spec>, bool)> {
    let code = FunctionCode::new(*pdu.first()?);
    if !code.can_be_request() {
        return None;
    }
    Some((code.spec(), code.request_shape().fits(pdu)))
}

/// Checks a master's request PDU against the limits of docs/protocol.md §1. `Err` carries
/// the exception code a device would answer: 01 for a function code that cannot be a
/// request, 03 for a size, quantity or value out of range. Unknown (vendor) function
/// codes pass: the device decides.
pub fn check_request(pdu: &[u8]) -> Result<(), ExceptionCode> {
    let Some((spec, fits)) = request_row(pdu) else {
        return Err(ExceptionCode::ILLEGAL_FUNCTION);
    };
    if let Some(fits) = super::function::mei_request_fits(pdu) {
        return if fits {
            Ok(())
        } else {
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        };
    }
    let Some(spec) = spec else {
        return Ok(());
    };
    let read_ok = spec
        .read
        .is_none_or(|q| q.of(pdu).is_some_and(|n| q.allows(n)));
    let write_ok = spec.write.is_none_or(|q| {
        let count = pdu.get(q.at + 2).map(|&c| usize::from(c));
        q.of(pdu)
            .is_some_and(|n| q.allows(n) && count == Some(q.item.bytes(n)))
    });
    let value_ok = !spec.coil_value || pdu.len() < 5 || matches!(word(pdu, 3), 0xFF00 | 0x0000);
    if fits && read_ok && write_ok && value_ok {
        Ok(())
    } else {
        Err(ExceptionCode::ILLEGAL_DATA_VALUE)
    }
}

/// Is this request PDU consistent with itself: the size its function code calls for,
/// and byte-count fields that cover the rest (docs/protocol.md §1 table)? Values are not
/// checked (a device answers 03 for those), and unknown function codes pass (a device
/// answers 01). The simulator's decoder uses this to delimit requests on a lossy line.
pub fn request_well_formed(pdu: &[u8]) -> bool {
    request_row(pdu).is_some_and(|(_, fits)| fits)
}

/// What a frame that came where a request belongs is, when it cannot be one: an answer
/// of some device or gateway. Answering an answer is how two peers that answer
/// everything loop for ever (docs/security.md "Threat model"), so the masters' side
/// never answers one: it drops it and counts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NotRequest {
    /// Its function code has the high bit set: an exception reply (V1.1b3 §7).
    Exception,
    /// It has the shape of its function code's normal reply and not of its request
    /// (`03 02 00 FF`: a byte count and 2N data bytes).
    ReplyShape,
}

/// `None` for a PDU that may be a request (well formed or not: a malformed request is
/// answered 0x01 or 0x03 by [`check_request`]); else what it is. A PDU that has the
/// shape of both its request and its reply (`01 03 CD 6B 05`, five bytes of FC 01)
/// may be a request; and so may one of a code whose reply repeats its request (FC 05,
/// 06, 08, 22: only the time it comes can tell those apart, docs/dialing.md "Modbus
/// over UDP") or whose shape is unknown.
pub fn not_a_request(pdu: &[u8]) -> Option<NotRequest> {
    let code = FunctionCode::new(*pdu.first()?);
    if code.is_exception() {
        return Some(NotRequest::Exception);
    }
    let spec = code.spec()?;
    (!spec.request.fits(pdu) && reply_well_formed(pdu)).then_some(NotRequest::ReplyShape)
}

/// A reply whose byte-count field is its second byte and covers the rest.
fn counted(reply: &[u8]) -> Option<usize> {
    let count = usize::from(*reply.get(1)?);
    (reply.len() == 2 + count).then_some(count)
}

/// Is this reply PDU consistent with itself, whatever was asked (docs/design.md §2: the
/// shape check for frames that answer no outstanding request)? Unknown function codes
/// pass: nothing is known of their shape.
pub fn reply_well_formed(reply: &[u8]) -> bool {
    let Some(&code) = reply.first() else {
        return false;
    };
    let code = FunctionCode::new(code);
    if code.is_exception() {
        return code.is_reply() && reply.len() == 2 && is_exception_code(reply[1]);
    }
    let Some(spec) = code.spec() else {
        return true;
    };
    spec.reply.fits(reply) && (!spec.coil_value || matches!(word(reply, 3), 0xFF00 | 0x0000))
}

/// Is `reply` an answer to `request` (docs/design.md §1 step 4): the same function code or
/// its exception, and the shape the request calls for (an FC 03 reply for N registers
/// carries 2N bytes; a write echoes what it wrote; the bits of an FC 01 or 02 reply
/// past the quantity asked are zero, as the Modbus Application Protocol V1.1b3 §6.1
/// and §6.2 require, so an echo of the request rarely passes).
pub fn reply_matches(request: &[u8], reply: &[u8]) -> bool {
    let (Some(&asked), Some(&got)) = (request.first(), reply.first()) else {
        return false;
    };
    // A request without its own shape has no answer (and its fields may be missing).
    if !request_well_formed(request) {
        return false;
    }
    let (asked, got) = (FunctionCode::new(asked), FunctionCode::new(got));
    if got == asked.exception() {
        return reply.len() == 2 && is_exception_code(reply[1]);
    }
    if got != asked || !reply_well_formed(reply) {
        return false;
    }
    let Some(spec) = asked.spec() else {
        return true;
    };
    let read_ok = spec.read.is_none_or(|q| {
        let qty = word(request, q.at);
        let bits_padded = match q.item {
            Item::Bits => qty.is_multiple_of(8) || reply[reply.len() - 1] >> (qty % 8) == 0,
            Item::Registers => true,
        };
        counted(reply) == Some(q.item.bytes(qty)) && bits_padded
    });
    let echo_ok = match spec.echo {
        Echo::No => true,
        Echo::Whole => reply == request,
        Echo::Prefix(n) => reply.get(..n) == request.get(..n),
    };
    read_ok && echo_ok
}

/// The answer a device gives to a write request, made from the request itself: FC 05,
/// 06 and 16 echo it whole; 0F and 10 echo address and quantity. Other requests are
/// echoed whole. (What a master gets for a broadcast with `broadcast_reply = "echo"`.)
pub(crate) fn write_echo(request: &[u8]) -> Vec<u8> {
    let echo = request
        .first()
        .and_then(|&c| FunctionCode::new(c).spec())
        .map(|s| s.echo);
    match echo {
        Some(Echo::Prefix(n)) if request.len() >= n => request[..n].to_vec(),
        _ => request.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_limits() {
        assert_eq!(check_request(&[3, 0, 0, 0, 1]), Ok(()));
        assert_eq!(check_request(&[3, 0, 0, 0, 125]), Ok(()));
        assert_eq!(
            check_request(&[3, 0, 0, 0, 126]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(
            check_request(&[3, 0, 0, 0, 0]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(
            check_request(&[3, 0, 0, 0]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(check_request(&[1, 0, 0, 0x07, 0xD0]), Ok(()));
        assert_eq!(
            check_request(&[1, 0, 0, 0x07, 0xD1]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(check_request(&[5, 0, 1, 0xFF, 0x00]), Ok(()));
        assert_eq!(
            check_request(&[5, 0, 1, 0x12, 0x34]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        // The CIE-M10 write of docs/protocol.md §3.
        assert_eq!(check_request(&[0x10, 0, 8, 0, 1, 2, 0, 0x11]), Ok(()));
        assert_eq!(
            check_request(&[0x10, 0, 8, 0, 1, 4, 0, 0x11, 0, 0]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(check_request(&[0x0F, 0, 20, 0, 10, 2, 0xCD, 0x01]), Ok(()));
        assert_eq!(
            check_request(&[0x0F, 0, 20, 0, 10, 1, 0xCD]),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE)
        );
        assert_eq!(
            check_request(&[0x17, 0, 0, 0, 2, 0, 5, 0, 1, 2, 0, 9]),
            Ok(())
        );
        assert_eq!(
            check_request(&[0x80, 0]),
            Err(ExceptionCode::ILLEGAL_FUNCTION)
        );
        assert_eq!(check_request(&[0x00]), Err(ExceptionCode::ILLEGAL_FUNCTION));
        assert_eq!(check_request(&[0x41, 1, 2, 3]), Ok(()));
    }

    #[test]
    fn replies_match_their_requests() {
        // docs/protocol.md §3: read of 1 word at 0 answered `03 02 00 FF`.
        assert!(reply_matches(&[3, 0, 0, 0, 1], &[3, 2, 0, 0xFF]));
        assert!(!reply_matches(&[3, 0, 0, 0, 2], &[3, 2, 0, 0xFF]));
        assert!(!reply_matches(&[4, 0, 0, 0, 1], &[3, 2, 0, 0xFF]));
        assert!(reply_matches(&[3, 0, 0, 0, 1], &[0x83, 0x02]));
        assert!(!reply_matches(&[3, 0, 0, 0, 1], &[0x83, 0x09]));
        assert!(!reply_matches(&[3, 0, 0, 0, 1], &[0x84, 0x02]));
        // Write response echoes address and quantity.
        let write = [0x10, 0, 8, 0, 1, 2, 0, 0x11];
        assert!(reply_matches(&write, &[0x10, 0, 8, 0, 1]));
        assert!(!reply_matches(&write, &[0x10, 0, 9, 0, 1]));
        assert!(reply_matches(&write, &[0x90, 0x01]));
        // Seed 004: coils 20..38 read as CD 6B 05.
        assert!(reply_matches(&[1, 0, 19, 0, 19], &[1, 3, 0xCD, 0x6B, 0x05]));
        assert!(!reply_matches(&[1, 0, 19, 0, 19], &[1, 2, 0xCD, 0x6B]));
        // The bits past coil 38 pad the last byte with zeros: 0x05 uses 3 bits.
        assert!(!reply_matches(
            &[1, 0, 19, 0, 19],
            &[1, 3, 0xCD, 0x6B, 0x0D]
        ));
        assert!(!reply_matches(
            &[2, 0, 19, 0, 19],
            &[2, 3, 0xCD, 0x6B, 0x85]
        ));
        assert!(reply_matches(&[2, 0, 0, 0, 16], &[2, 2, 0xFF, 0xFF]));
        // An echo of an FC 01 read passes the byte count at address 0x03xx; for 17 to
        // 20 coils the padding gives it away.
        for qty in 17..=20u8 {
            let read = [1, 3, 0x10, 0, qty];
            assert!(!reply_matches(&read, &read), "{qty} coils");
        }
        assert!(reply_matches(&[6, 0, 1, 0, 3], &[6, 0, 1, 0, 3]));
        assert!(!reply_matches(&[6, 0, 1, 0, 3], &[6, 0, 1, 0, 4]));
        // Found by fuzzing: a request too short for its function code panicked.
        assert!(!reply_matches(&[1], &[1, 1, 0]));
        assert!(!reply_matches(&[0x10, 0, 1], &[0x10, 0, 1, 0, 1]));
        assert!(!reply_matches(&[3, 0], &[0x83, 2]));
    }

    #[test]
    fn write_echoes() {
        assert_eq!(write_echo(&[6, 0, 1, 0, 3]), [6, 0, 1, 0, 3]);
        let write = [0x10, 0, 8, 0, 1, 2, 0, 0x11];
        assert_eq!(write_echo(&write), [0x10, 0, 8, 0, 1]);
        assert!(reply_matches(&write, &write_echo(&write)));
    }

    #[test]
    fn well_formed_requests() {
        assert!(request_well_formed(&[3, 0, 0, 0, 1]));
        assert!(
            request_well_formed(&[3, 0, 0, 0, 0]),
            "values are the device's business"
        );
        assert!(!request_well_formed(&[3, 0, 0, 0]));
        assert!(request_well_formed(&[0x10, 0, 8, 0, 1, 2, 0, 0x11]));
        assert!(!request_well_formed(&[0x10, 0, 8, 0, 1, 2, 0]));
        assert!(request_well_formed(&[0x10, 0, 8, 0, 9, 2, 0, 0x11]));
        assert!(request_well_formed(&[
            0x17, 0, 0, 0, 2, 0, 5, 0, 1, 2, 0, 9
        ]));
        assert!(!request_well_formed(&[
            0x17, 0, 0, 0, 2, 0, 5, 0, 1, 4, 0, 9
        ]));
        assert!(request_well_formed(&[0x41, 1, 2, 3]));
        assert!(!request_well_formed(&[0x83, 2]));
        assert!(!request_well_formed(&[]));
    }

    /// Exceptions and replies of a shape no request has are not requests; a request,
    /// malformed or not, and a PDU of both shapes are left to the request checks.
    #[test]
    fn answers_are_not_requests() {
        use NotRequest::{Exception, ReplyShape};
        for (pdu, want) in [
            (&[0x83, 0x02][..], Some(Exception)),
            (&[0x80, 0x01], Some(Exception)),
            (&[0xFF], Some(Exception)),
            (&[0x83], Some(Exception)),
            (&[3, 2, 0, 0xFF], Some(ReplyShape)),
            (&[3, 4, 0, 1, 0, 2], Some(ReplyShape)),
            (&[4, 2, 0, 0x0A], Some(ReplyShape)),
            (&[1, 1, 5], Some(ReplyShape)),
            (&[0x10, 0, 8, 0, 1], Some(ReplyShape)),
            (&[0x0F, 0, 0x13, 0, 0x0A], Some(ReplyShape)),
            (&[7, 0x6D], Some(ReplyShape)),
            (&[0x11, 3, 0x2A, 0xFF, 1], Some(ReplyShape)),
            (&[0x17, 2, 0, 0xFE], Some(ReplyShape)),
            (&[3, 0, 1, 0, 2], None),
            // Of both shapes (an FC 01 request for coils at 0x03CD): a request.
            (&[1, 3, 0xCD, 0x6B, 0x05], None),
            // A reply that repeats its request.
            (&[6, 0, 1, 0, 3], None),
            (&[5, 0, 0xAC, 0xFF, 0], None),
            (&[8, 0, 0, 0xA5, 0x37], None),
            (&[0x16, 0, 4, 0, 0xF2, 0, 0x25], None),
            // Malformed, but no reply either: answered 0x03 by the request checks.
            (&[3, 0], None),
            (&[3, 2, 0], None),
            (&[0x10, 0, 8, 0], None),
            (&[0], None),
            (&[0x41, 1, 2], None),
            (&[0x2B, 0x0E, 1, 0], None),
            (&[], None),
        ] {
            assert_eq!(not_a_request(pdu), want, "{pdu:02X?}");
        }
    }

    #[test]
    fn well_formed_replies() {
        assert!(reply_well_formed(&[3, 2, 0, 0xFF]));
        assert!(!reply_well_formed(&[3, 3, 0, 0xFF, 1]));
        assert!(!reply_well_formed(&[3, 2, 0]));
        assert!(!reply_well_formed(&[3, 0]));
        assert!(reply_well_formed(&[0x90, 0x02]));
        assert!(!reply_well_formed(&[0x90, 0x02, 0x00]));
        assert!(!reply_well_formed(&[0xC1, 0x02]));
        assert!(!reply_well_formed(&[]));
        assert!(reply_well_formed(&[0x41, 9, 9]));
    }
}
