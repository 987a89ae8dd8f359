//! What the function codes mean (docs/protocol.md §1): which requests are well formed, what
//! shape their replies must have, and which replies could exist at all.
//!
//! All functions take a PDU: the function code followed by its data.

/// Function codes (docs/protocol.md §1 table).
pub mod fc {
    pub const READ_COILS: u8 = 0x01;
    pub const READ_DISCRETE_INPUTS: u8 = 0x02;
    pub const READ_HOLDING_REGISTERS: u8 = 0x03;
    pub const READ_INPUT_REGISTERS: u8 = 0x04;
    pub const WRITE_SINGLE_COIL: u8 = 0x05;
    pub const WRITE_SINGLE_REGISTER: u8 = 0x06;
    pub const READ_EXCEPTION_STATUS: u8 = 0x07;
    pub const DIAGNOSTICS: u8 = 0x08;
    pub const GET_COMM_EVENT_COUNTER: u8 = 0x0B;
    pub const GET_COMM_EVENT_LOG: u8 = 0x0C;
    pub const WRITE_MULTIPLE_COILS: u8 = 0x0F;
    pub const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
    pub const REPORT_SERVER_ID: u8 = 0x11;
    pub const READ_FILE_RECORD: u8 = 0x14;
    pub const WRITE_FILE_RECORD: u8 = 0x15;
    pub const MASK_WRITE_REGISTER: u8 = 0x16;
    pub const READ_WRITE_MULTIPLE_REGISTERS: u8 = 0x17;
    pub const READ_FIFO_QUEUE: u8 = 0x18;
    pub const ENCAPSULATED_INTERFACE: u8 = 0x2B;
}

/// Exception codes (docs/protocol.md §1).
pub mod exception {
    pub const ILLEGAL_FUNCTION: u8 = 0x01;
    pub const ILLEGAL_DATA_ADDRESS: u8 = 0x02;
    pub const ILLEGAL_DATA_VALUE: u8 = 0x03;
    pub const SERVER_DEVICE_FAILURE: u8 = 0x04;
    pub const ACKNOWLEDGE: u8 = 0x05;
    pub const SERVER_DEVICE_BUSY: u8 = 0x06;
    pub const MEMORY_PARITY_ERROR: u8 = 0x08;
    /// The gateway cannot route the request: no serial port, or shutting down.
    pub const GATEWAY_PATH_UNAVAILABLE: u8 = 0x0A;
    /// The device did not answer in time.
    pub const GATEWAY_TARGET_FAILED: u8 = 0x0B;
}

use fc::*;

/// Every public function code of the Modbus application protocol.
pub fn is_public_function(code: u8) -> bool {
    matches!(
        code,
        READ_COILS
            | READ_DISCRETE_INPUTS
            | READ_HOLDING_REGISTERS
            | READ_INPUT_REGISTERS
            | WRITE_SINGLE_COIL
            | WRITE_SINGLE_REGISTER
            | READ_EXCEPTION_STATUS
            | DIAGNOSTICS
            | GET_COMM_EVENT_COUNTER
            | GET_COMM_EVENT_LOG
            | WRITE_MULTIPLE_COILS
            | WRITE_MULTIPLE_REGISTERS
            | REPORT_SERVER_ID
            | READ_FILE_RECORD
            | WRITE_FILE_RECORD
            | MASK_WRITE_REGISTER
            | READ_WRITE_MULTIPLE_REGISTERS
            | READ_FIFO_QUEUE
            | ENCAPSULATED_INTERFACE
    )
}

/// A function code a device could send back: a public one, or its exception form.
pub fn is_reply_function(code: u8) -> bool {
    is_public_function(code & 0x7F)
}

/// Exception codes a device may answer with.
pub fn is_exception_code(code: u8) -> bool {
    matches!(code, 0x01..=0x06 | 0x08 | 0x0A | 0x0B)
}

/// Requests that only read, and so may be resent after a timeout (docs/design.md §4
/// `retries`). Everything else may act on the device and is resent only with
/// `retry_writes`.
pub fn is_read(function: u8) -> bool {
    matches!(
        function,
        READ_COILS
            | READ_DISCRETE_INPUTS
            | READ_HOLDING_REGISTERS
            | READ_INPUT_REGISTERS
            | READ_EXCEPTION_STATUS
            | GET_COMM_EVENT_COUNTER
            | GET_COMM_EVENT_LOG
            | REPORT_SERVER_ID
            | READ_FILE_RECORD
            | READ_FIFO_QUEUE
    )
}

fn word(pdu: &[u8], at: usize) -> usize {
    usize::from(u16::from_be_bytes([pdu[at], pdu[at + 1]]))
}

/// Checks a master's request PDU against the limits of docs/protocol.md §1. `Err` carries
/// the exception code a device would answer: 01 for a function code that cannot be a
/// request, 03 for a quantity or size out of range. Unknown (vendor) function codes
/// pass: the device decides.
pub fn check_request(pdu: &[u8]) -> Result<(), u8> {
    use super::pdu::exception::{ILLEGAL_DATA_VALUE as BAD, ILLEGAL_FUNCTION};
    let Some(&code) = pdu.first() else {
        return Err(ILLEGAL_FUNCTION);
    };
    if code == 0 || code >= 0x80 {
        return Err(ILLEGAL_FUNCTION);
    }
    let n = pdu.len();
    let ok = match code {
        READ_COILS | READ_DISCRETE_INPUTS => n == 5 && (1..=2000).contains(&word(pdu, 3)),
        READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
            n == 5 && (1..=125).contains(&word(pdu, 3))
        }
        WRITE_SINGLE_COIL => n == 5 && matches!(word(pdu, 3), 0xFF00 | 0x0000),
        WRITE_SINGLE_REGISTER => n == 5,
        WRITE_MULTIPLE_COILS => {
            n >= 6 && {
                let qty = word(pdu, 3);
                let count = usize::from(pdu[5]);
                (1..=1968).contains(&qty) && count == qty.div_ceil(8) && n == 6 + count
            }
        }
        WRITE_MULTIPLE_REGISTERS => {
            n >= 6 && {
                let qty = word(pdu, 3);
                let count = usize::from(pdu[5]);
                (1..=123).contains(&qty) && count == 2 * qty && n == 6 + count
            }
        }
        MASK_WRITE_REGISTER => n == 7,
        READ_WRITE_MULTIPLE_REGISTERS => {
            n >= 10 && {
                let read = word(pdu, 3);
                let write = word(pdu, 7);
                let count = usize::from(pdu[9]);
                (1..=125).contains(&read)
                    && (1..=121).contains(&write)
                    && count == 2 * write
                    && n == 10 + count
            }
        }
        READ_EXCEPTION_STATUS | GET_COMM_EVENT_COUNTER | GET_COMM_EVENT_LOG | REPORT_SERVER_ID => {
            n == 1
        }
        _ => true,
    };
    if ok {
        Ok(())
    } else {
        Err(BAD)
    }
}

/// Is this request PDU consistent with itself: the size its function code calls for,
/// and byte-count fields that cover the rest (docs/protocol.md §1 table)? Values are not
/// checked (a device answers 03 for those), and unknown function codes pass (a device
/// answers 01). The simulator's decoder uses this to delimit requests on a lossy line.
pub fn request_well_formed(pdu: &[u8]) -> bool {
    let Some(&code) = pdu.first() else {
        return false;
    };
    let n = pdu.len();
    match code {
        0 | 0x80..=0xFF => false,
        READ_COILS
        | READ_DISCRETE_INPUTS
        | READ_HOLDING_REGISTERS
        | READ_INPUT_REGISTERS
        | WRITE_SINGLE_COIL
        | WRITE_SINGLE_REGISTER => n == 5,
        WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => n >= 6 && n == 6 + usize::from(pdu[5]),
        MASK_WRITE_REGISTER => n == 7,
        READ_WRITE_MULTIPLE_REGISTERS => n >= 10 && n == 10 + usize::from(pdu[9]),
        READ_EXCEPTION_STATUS | GET_COMM_EVENT_COUNTER | GET_COMM_EVENT_LOG | REPORT_SERVER_ID => {
            n == 1
        }
        _ => true,
    }
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
    if code & 0x80 != 0 {
        return is_public_function(code & 0x7F) && reply.len() == 2 && is_exception_code(reply[1]);
    }
    match code {
        READ_COILS | READ_DISCRETE_INPUTS => counted(reply).is_some_and(|c| c >= 1),
        READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS | READ_WRITE_MULTIPLE_REGISTERS => {
            counted(reply).is_some_and(|c| c >= 2 && c % 2 == 0)
        }
        WRITE_SINGLE_COIL => reply.len() == 5 && matches!(word(reply, 3), 0xFF00 | 0x0000),
        WRITE_SINGLE_REGISTER | WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => reply.len() == 5,
        MASK_WRITE_REGISTER => reply.len() == 7,
        READ_EXCEPTION_STATUS => reply.len() == 2,
        GET_COMM_EVENT_COUNTER => reply.len() == 5,
        GET_COMM_EVENT_LOG | REPORT_SERVER_ID | READ_FILE_RECORD | WRITE_FILE_RECORD => {
            counted(reply).is_some()
        }
        READ_FIFO_QUEUE => reply.len() >= 5 && word(reply, 1) + 3 == reply.len(),
        DIAGNOSTICS => reply.len() >= 5,
        _ => true,
    }
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
    if got == asked | 0x80 {
        return reply.len() == 2 && is_exception_code(reply[1]);
    }
    if got != asked || !reply_well_formed(reply) {
        return false;
    }
    match asked {
        READ_COILS | READ_DISCRETE_INPUTS => {
            let qty = word(request, 3);
            let used = qty % 8;
            counted(reply) == Some(qty.div_ceil(8))
                && (used == 0 || reply[reply.len() - 1] >> used == 0)
        }
        READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS | READ_WRITE_MULTIPLE_REGISTERS => {
            counted(reply) == Some(2 * word(request, 3))
        }
        WRITE_SINGLE_COIL | WRITE_SINGLE_REGISTER | MASK_WRITE_REGISTER => reply == request,
        WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => reply[..5] == request[..5],
        _ => true,
    }
}

/// The answer a device gives to a write request, made from the request itself: FC 05,
/// 06 and 16 echo it whole; 0F and 10 echo address and quantity. Other requests are
/// echoed whole. (What a master gets for a broadcast with `broadcast_reply = "echo"`.)
pub fn write_echo(request: &[u8]) -> Vec<u8> {
    match request.first() {
        Some(&(WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS)) if request.len() >= 5 => {
            request[..5].to_vec()
        }
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
        assert_eq!(check_request(&[3, 0, 0, 0, 126]), Err(3));
        assert_eq!(check_request(&[3, 0, 0, 0, 0]), Err(3));
        assert_eq!(check_request(&[3, 0, 0, 0]), Err(3));
        assert_eq!(check_request(&[1, 0, 0, 0x07, 0xD0]), Ok(()));
        assert_eq!(check_request(&[1, 0, 0, 0x07, 0xD1]), Err(3));
        assert_eq!(check_request(&[5, 0, 1, 0xFF, 0x00]), Ok(()));
        assert_eq!(check_request(&[5, 0, 1, 0x12, 0x34]), Err(3));
        // The CIE-M10 write of docs/protocol.md §3.
        assert_eq!(check_request(&[0x10, 0, 8, 0, 1, 2, 0, 0x11]), Ok(()));
        assert_eq!(check_request(&[0x10, 0, 8, 0, 1, 4, 0, 0x11, 0, 0]), Err(3));
        assert_eq!(check_request(&[0x0F, 0, 20, 0, 10, 2, 0xCD, 0x01]), Ok(()));
        assert_eq!(check_request(&[0x0F, 0, 20, 0, 10, 1, 0xCD]), Err(3));
        assert_eq!(
            check_request(&[0x17, 0, 0, 0, 2, 0, 5, 0, 1, 2, 0, 9]),
            Ok(())
        );
        assert_eq!(check_request(&[0x80, 0]), Err(1));
        assert_eq!(check_request(&[0x00]), Err(1));
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
