//! Tests of tools::client::transport.

use super::*;

#[test]
fn transaction_ids_skip_zero() {
    let mut m = Master::new(ClientTransport::tcp("127.0.0.1"), Duration::from_secs(1));
    assert_eq!(m.next_tid(), 1);
    assert_eq!(m.next_tid(), 2);
    m.next_tid = 0xFFFF;
    assert_eq!(m.next_tid(), 0xFFFF);
    assert_eq!(m.next_tid(), 1);
}

#[test]
fn judge_takes_only_the_answer_to_its_request() {
    let req = Adu::build(7, 1, &[3, 0, 0, 0, 1]);
    let mut d = crate::frame::Resync::new();
    // A late answer (tid 6), another unit's, a wrong shape, then ours.
    for f in [
        Adu::build(6, 1, &[3, 2, 0, 1]),
        Adu::build(7, 2, &[3, 2, 0, 2]),
        Adu::build(7, 1, &[3, 4, 0, 3, 0, 3]),
        Adu::build(7, 1, &[3, 2, 0, 0xFF]),
    ] {
        d.push(f.as_bytes());
    }
    let got = d.next_frame(&ReplyTo(&req), false).unwrap();
    assert_eq!(got.pdu(), &[3, 2, 0, 0xFF]);
}
