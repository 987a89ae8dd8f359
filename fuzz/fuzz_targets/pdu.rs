//! Function-code knowledge (docs/protocol.md §1) on arbitrary PDUs: request checks, reply
//! shapes, reply decoding and the rule that tells an answer from a request (the one
//! every listener and dial drops answers by, docs/security.md "Threat model") never
//! panic and agree with each other.
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
    // An answer is never a request within the limits, and never well formed as one;
    // a PDU whose code has the high bit set is always an answer.
    for p in [&request, &reply] {
        let answer = pdu::not_a_request(p);
        if answer.is_some() {
            assert!(pdu::check_request(p).is_err(), "an answer passed the request checks");
            assert!(!pdu::request_well_formed(p), "an answer has a request's shape");
        }
        if p.first().is_some_and(|&c| c >= 0x80) {
            assert_eq!(answer, Some(pdu::NotRequest::Exception));
        }
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
