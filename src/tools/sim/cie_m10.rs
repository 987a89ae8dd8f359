//! The `cie-m10` profile: the Sollae ezTCP CIE-M10/H10 as docs/protocol.md §3 describes it.
//!
//! Eight input ports read at the input port address, eight output ports driven at the
//! output port address, one word each with port 0 in the least significant bit. Only
//! FC 03 and FC 16; exception 01 for any other function code and 02 for any other
//! reference. A write to the outputs can be wired back to the inputs (loopback), and a
//! change of the inputs can be notified unsolicited, as an FC 03 response.

use super::{exception_pdu, Answer};
use crate::frame::function::{ExceptionCode as Ex, FunctionCode as Fc};

/// The device's settings and port state.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CieM10 {
    pub(crate) unit: u8,
    pub(crate) input_address: u16,
    pub(crate) output_address: u16,
    /// Input ports 0..7, port 0 in bit 0.
    pub(crate) inputs: u8,
    /// Output ports 0..7, port 0 in bit 0.
    pub(crate) outputs: u8,
    /// The inputs follow the outputs, as if each output were wired to its input.
    pub(crate) loopback: bool,
    /// Input port change notification (docs/protocol.md §3, default off on the device).
    pub(crate) notify: bool,
}

impl Default for CieM10 {
    /// The device's defaults in serial Modbus/TCP mode (docs/protocol.md §3).
    fn default() -> Self {
        Self {
            unit: 1,
            input_address: 0,
            output_address: 8,
            inputs: 0,
            outputs: 0,
            loopback: false,
            notify: false,
        }
    }
}

fn word(pdu: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([pdu[at], pdu[at + 1]])
}

impl CieM10 {
    /// Answers one request PDU addressed to `unit`; any other unit gets silence.
    pub(crate) fn answer(&mut self, unit: u8, pdu: &[u8]) -> Answer {
        if unit != self.unit {
            return Answer::silent();
        }
        let code = Fc::new(pdu[0]);
        let reply = match code {
            Fc::READ_HOLDING_REGISTERS if pdu.len() == 5 => {
                let (address, quantity) = (word(pdu, 1), word(pdu, 3));
                if quantity != 1 {
                    exception_pdu(code, Ex::ILLEGAL_DATA_ADDRESS)
                } else if address == self.input_address {
                    vec![code.get(), 2, 0, self.inputs]
                } else if address == self.output_address {
                    vec![code.get(), 2, 0, self.outputs]
                } else {
                    exception_pdu(code, Ex::ILLEGAL_DATA_ADDRESS)
                }
            }
            Fc::WRITE_MULTIPLE_REGISTERS if pdu.len() == 8 && pdu[5] == 2 => {
                let (address, quantity) = (word(pdu, 1), word(pdu, 3));
                if address != self.output_address || quantity != 1 {
                    exception_pdu(code, Ex::ILLEGAL_DATA_ADDRESS)
                } else {
                    self.outputs = pdu[7];
                    let echo = pdu[..5].to_vec();
                    let changed = self.loopback && self.set_inputs(self.outputs);
                    return Answer {
                        reply: Some(echo),
                        notification: changed.then(|| self.notification()).flatten(),
                        delay: None,
                    };
                }
            }
            Fc::WRITE_MULTIPLE_REGISTERS => exception_pdu(code, Ex::ILLEGAL_DATA_ADDRESS),
            _ => exception_pdu(code.base(), Ex::ILLEGAL_FUNCTION),
        };
        Answer::reply(reply)
    }

    /// Sets the inputs; `true` if any changed.
    pub(crate) fn set_inputs(&mut self, inputs: u8) -> bool {
        let changed = self.inputs != inputs;
        self.inputs = inputs;
        changed
    }

    /// The unsolicited frame's PDU for the current inputs, if notification is on: it
    /// looks like the FC 03 response to a read of the input port (docs/protocol.md §3).
    pub(crate) fn notification(&self) -> Option<Vec<u8>> {
        self.notify
            .then(|| vec![Fc::READ_HOLDING_REGISTERS.get(), 2, 0, self.inputs])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;

    /// The byte-exact examples of docs/protocol.md §3, as PDUs (the MBAP header is the
    /// caller's; the end-to-end tests check the whole frames).
    #[test]
    fn protocol_examples() {
        let mut d = CieM10 {
            inputs: 0xFF,
            ..CieM10::default()
        };
        assert_eq!(
            d.answer(1, &bytes("03 00 00 00 01")).reply,
            Some(bytes("03 02 00 FF"))
        );
        let a = d.answer(1, &bytes("10 00 08 00 01 02 00 11"));
        assert_eq!(a.reply, Some(bytes("10 00 08 00 01")));
        assert_eq!(d.outputs, 0x11);
        assert_eq!(
            d.answer(1, &bytes("03 00 08 00 01")).reply,
            Some(bytes("03 02 00 11")),
            "FC 03 on the output address reads back the outputs"
        );
        assert_eq!(
            d.answer(1, &bytes("03 00 05 00 01")).reply,
            Some(bytes("83 02"))
        );
        assert_eq!(
            d.answer(1, &bytes("03 00 00 00 02")).reply,
            Some(bytes("83 02"))
        );
        assert_eq!(
            d.answer(1, &bytes("10 00 00 00 01 02 00 11")).reply,
            Some(bytes("90 02")),
            "inputs cannot be written"
        );
        assert_eq!(
            d.answer(1, &bytes("04 00 00 00 01")).reply,
            Some(bytes("84 01"))
        );
        assert_eq!(
            d.answer(1, &bytes("06 00 08 00 11")).reply,
            Some(bytes("86 01"))
        );
        assert_eq!(d.answer(2, &bytes("03 00 00 00 01")), Answer::silent());
    }

    #[test]
    fn addresses_are_configurable() {
        let mut d = CieM10 {
            input_address: 100,
            output_address: 200,
            inputs: 0x0F,
            ..CieM10::default()
        };
        assert_eq!(
            d.answer(1, &bytes("03 00 64 00 01")).reply,
            Some(bytes("03 02 00 0F"))
        );
        assert_eq!(
            d.answer(1, &bytes("03 00 00 00 01")).reply,
            Some(bytes("83 02"))
        );
        assert_eq!(
            d.answer(1, &bytes("10 00 C8 00 01 02 00 01")).reply,
            Some(bytes("10 00 C8 00 01"))
        );
    }

    #[test]
    fn loopback_and_notification() {
        let mut d = CieM10 {
            loopback: true,
            notify: true,
            ..CieM10::default()
        };
        let a = d.answer(1, &bytes("10 00 08 00 01 02 00 11"));
        assert_eq!(d.inputs, 0x11);
        assert_eq!(a.notification, Some(bytes("03 02 00 11")));
        // The same outputs again change nothing: no notification.
        let a = d.answer(1, &bytes("10 00 08 00 01 02 00 11"));
        assert_eq!(a.notification, None);
        d.notify = false;
        let a = d.answer(1, &bytes("10 00 08 00 01 02 00 22"));
        assert_eq!((d.inputs, a.notification), (0x22, None));
    }
}
