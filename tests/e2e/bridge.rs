//! End to end against pymodbus: the real binary, a socat pty pair, pymodbus'
//! `ModbusSerialServer` with the socket framer as the device.

use crate::common;
use common::*;
use std::io::Write;
use std::thread;

struct Bench {
    _dir: tempfile::TempDir,
    _socat: Socat,
    _device: Py,
    gw: Gateway,
}

/// socat, pymodbus' stock serial server on one end, mbgate on the other.
fn bench(extra: impl FnOnce(Cfg) -> Cfg) -> Bench {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let device = Py::start("stock_server.py", &["--port", socat.dev.to_str().unwrap()]);
    let gw = Gateway::start(&extra(Cfg::new(&socat.gw).pty_line()), dir.path());
    Bench {
        _dir: dir,
        _socat: socat,
        _device: device,
        gw,
    }
}

/// Every byte-exact example of docs/protocol.md §3, from a raw TCP client.
#[test]
fn cie_m10_examples_byte_exact() {
    let b = bench(|c| c.log("traffic = true"));
    let mut m = b.gw.connect();
    // Read inputs 0..7 (all ON on this device).
    assert_eq!(
        transact(&mut m, &hex("00 00 00 00 00 06 01 03 00 00 00 01")),
        hex("00 00 00 00 00 05 01 03 02 00 FF")
    );
    // Write outputs 0 and 4 at address 8.
    assert_eq!(
        transact(&mut m, &hex("00 00 00 00 00 09 01 10 00 08 00 01 02 00 11")),
        hex("00 00 00 00 00 06 01 10 00 08 00 01")
    );
    // Read the outputs back, with a transaction id of the master's own.
    assert_eq!(
        transact(&mut m, &hex("BE EF 00 00 00 06 01 03 00 08 00 01")),
        hex("BE EF 00 00 00 05 01 03 02 00 11")
    );
    // Exceptions: bad reference number on read (83 02) and write (90 02).
    assert_eq!(
        transact(&mut m, &hex("12 34 00 00 00 06 01 03 27 10 00 01")),
        hex("12 34 00 00 00 03 01 83 02")
    );
    assert_eq!(
        transact(&mut m, &hex("43 21 00 00 00 09 01 10 27 10 00 01 02 00 11")),
        hex("43 21 00 00 00 03 01 90 02")
    );
    // log.traffic: every frame in both directions, as hex, with its direction. The
    // serial-side id is the gateway's own (not sequential: docs/reliability.md), the
    // same in the request and its reply, and the master's comes back.
    let sent = " 00 00 00 09 01 10 00 08 00 01 02 00 11 dir=\"gw->serial\" conn=1";
    b.gw.wait_log(sent, std::time::Duration::from_secs(2));
    let log = b.gw.log();
    let line = log
        .lines()
        .find(|l| l.contains(sent))
        .expect("the write on the line");
    let hexes = line.split("traffic: ").nth(1).expect("traffic line");
    let serial_id = &hexes[..5];
    assert_ne!(serial_id, "00 00", "never 0x0000 on the line: {line}");
    for line in [
        "00 00 00 00 00 09 01 10 00 08 00 01 02 00 11 dir=\"master->gw\" conn=1".to_string(),
        format!("{serial_id} 00 00 00 06 01 10 00 08 00 01 dir=\"serial->gw\""),
        "BE EF 00 00 00 05 01 03 02 00 11 dir=\"gw->master\" conn=1".to_string(),
    ] {
        b.gw.wait_log(&line, std::time::Duration::from_secs(2));
    }
}

/// Eight masters at once, all using transaction id 0 like CIE-M10 clients: each reads
/// back only what it wrote.
#[test]
fn eight_masters_same_transaction_id_no_crossover() {
    let b = bench(|c| c);
    let addr = b.gw.addr;
    let masters: Vec<_> = (0..8u16)
        .map(|i| {
            thread::spawn(move || {
                let mut m = std::net::TcpStream::connect(addr).unwrap();
                m.set_read_timeout(Some(std::time::Duration::from_secs(10)))
                    .unwrap();
                let reg = 100 + i;
                for round in 0..25u16 {
                    let value = i * 1000 + round;
                    assert_eq!(
                        transact(&mut m, &write_req(0, 1, reg, &[value])),
                        hex(&format!("00 00 00 00 00 06 01 10 00 {reg:02X} 00 01")),
                        "master {i} write"
                    );
                    assert_eq!(
                        transact(&mut m, &read_req(0, 1, reg, 1)),
                        read_reply(0, 1, &[value]),
                        "master {i} round {round} read its own value back"
                    );
                }
            })
        })
        .collect();
    for m in masters {
        m.join().expect("a master saw a wrong reply");
    }
}

/// One master pipelines 16 requests in one write: 16 replies, each with its own id.
#[test]
fn sixteen_pipelined_requests() {
    let b = bench(|c| c);
    let mut m = b.gw.connect();
    let mut burst = Vec::new();
    for i in 0..16u16 {
        burst.extend(read_req(0x0100 + i, 1, 1 + i, 1));
    }
    m.write_all(&burst).unwrap();
    let mut got: Vec<Vec<u8>> = (0..16).map(|_| read_frame(&mut m)).collect();
    got.sort();
    let want: Vec<Vec<u8>> = (0..16u16)
        .map(|i| read_reply(0x0100 + i, 1, &[1000 + 1 + i]))
        .collect();
    assert_eq!(got, want);
}

/// The ordinary user's client: pymodbus AsyncModbusTcpClient through the gateway.
#[test]
fn pymodbus_tcp_client_through_the_gateway() {
    let b = bench(|c| c);
    let (status, out) = Py::run(
        "tcp_client.py",
        &[
            "--host",
            "127.0.0.1",
            "--port",
            &b.gw.addr.port().to_string(),
        ],
    );
    assert!(status.success(), "tcp_client.py failed: {out}");
    assert!(out.contains("\"ok\": true"), "{out}");
}
