//! Forged UDP datagrams, for the hostile peers of a Modbus/UDP listener
//! (tests/e2e/udp_hostile.rs): raw IPv4 packets with any source address and port, as an
//! attacker on a network that lets spoofed sources through writes them. A raw socket of
//! protocol IPPROTO_RAW (which implies IP_HDRINCL) needs root or CAP_NET_RAW; without
//! it the test skips, saying so.

use socket2::{Domain, Protocol, SockAddr, Socket, Type};
use std::net::{SocketAddr, SocketAddrV4};

/// Writes UDP datagrams from any source.
pub(crate) struct Forger(Socket);

impl Forger {
    /// A raw socket; `None` when this process may not open one (the calling test is
    /// to return at once: it has said it skips).
    pub(crate) fn open() -> Option<Forger> {
        let raw = Protocol::from(libc::IPPROTO_RAW);
        match Socket::new(Domain::IPV4, Type::RAW, Some(raw)) {
            Ok(s) => Some(Forger(s)),
            Err(e) => {
                super::skipped(&format!(
                    "needs a raw socket to forge UDP sources (root or CAP_NET_RAW): {e}"
                ));
                None
            }
        }
    }

    /// One UDP datagram of `payload` from `from` to `to`, as if `from` had sent it.
    pub(crate) fn send(&self, from: SocketAddr, to: SocketAddr, payload: &[u8]) {
        let (SocketAddr::V4(from), SocketAddr::V4(to)) = (from, to) else {
            panic!("IPv4 only: {from} to {to}");
        };
        let packet = packet(from, to, payload);
        let sent = self
            .0
            .send_to(&packet, &SockAddr::from(to))
            .unwrap_or_else(|e| panic!("a forged datagram from {from} to {to}: {e}"));
        assert_eq!(sent, packet.len());
    }
}

/// The IPv4 packet: the kernel fills in the header's checksum and id (IP_HDRINCL);
/// no UDP checksum (0, which IPv4 allows).
fn packet(from: SocketAddrV4, to: SocketAddrV4, payload: &[u8]) -> Vec<u8> {
    let udp = 8 + payload.len();
    let total = 20 + udp;
    let mut p = Vec::with_capacity(total);
    p.extend_from_slice(&[0x45, 0]);
    p.extend_from_slice(&(total as u16).to_be_bytes());
    // id (the kernel's), don't fragment, TTL 64, UDP, checksum (the kernel's)
    p.extend_from_slice(&[0, 0, 0x40, 0, 64, 17, 0, 0]);
    p.extend_from_slice(&from.ip().octets());
    p.extend_from_slice(&to.ip().octets());
    p.extend_from_slice(&from.port().to_be_bytes());
    p.extend_from_slice(&to.port().to_be_bytes());
    p.extend_from_slice(&(udp as u16).to_be_bytes());
    p.extend_from_slice(&[0, 0]);
    p.extend_from_slice(payload);
    p
}
