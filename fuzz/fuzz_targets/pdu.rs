//! Function-code knowledge (docs/protocol.md §1) on arbitrary PDUs: request checks, reply
//! shapes and reply decoding never panic and agree with each other.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::frame::pdu;
use mbgate::frame::request::decode_reply;

fuzz_target!(|input: (Vec<u8>, Vec<u8>)| {
    let (request, reply) = input;
    if pdu::check_request(&request).is_ok() && !request.is_empty() {
        assert!(
            pdu::request_well_formed(&request),
            "a request within limits has its shape"
        );
    }
    let matches = pdu::reply_matches(&request, &reply);
    if matches && reply.first().is_some_and(|&c| c < 0x80) {
        assert!(
            pdu::reply_well_formed(&reply),
            "a matching reply is well formed"
        );
    }
    assert_eq!(
        decode_reply(&request, &reply).is_ok(),
        matches && !request.is_empty()
    );
});
