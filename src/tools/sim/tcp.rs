//! The simulated device as a Modbus/TCP slave that several masters reach at once
//! (`mbgate sim --listen ADDR --connections N`): the profile answers MBAP requests on
//! up to N connections, with the same console. The slave a master line reaches in
//! `mbgate demo --master` (where the user's own reads reach it too). One connection at
//! a time, in any framing, is `serve/tcp.rs`.

use super::packets::PacketDirection;
use super::serve::ConsoleRequest;
use super::Device;
use crate::frame::hex::Hex;
use crate::frame::mbap::decode_strict;
use crate::frame::Adu;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

/// Binds `addr`; the address bound (port 0 becomes a real port) is logged as
/// `serving Modbus/TCP on ADDR`.
pub(crate) async fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    let l = TcpListener::bind(addr).await?;
    info!("serving Modbus/TCP on {}", l.local_addr()?);
    Ok(l)
}

/// Serves the device on `listener`, at most `connections` at once (a connection
/// beyond them is closed at once), until `shutdown`.
pub(crate) async fn run(
    device: Device,
    listener: TcpListener,
    connections: usize,
    mut commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
) -> std::io::Result<()> {
    let mut device = device;
    super::replay::announce(&mut device);
    let device = Arc::new(Mutex::new(device));
    let room = Arc::new(tokio::sync::Semaphore::new(connections));
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            r = listener.accept() => {
                let (stream, from) = r?;
                let Ok(permit) = room.clone().try_acquire_owned() else {
                    info!("a connection from {from} closed: {connections} served already");
                    continue;
                };
                debug!("master connected from {from}");
                let (device, shutdown) = (device.clone(), shutdown.clone());
                tokio::spawn(async move {
                    connection(stream, device, shutdown).await;
                    drop(permit);
                });
            }
            Some(req) = commands.recv() => {
                let outcome = device.lock().expect("not poisoned").execute(req.command);
                // No unsolicited frames on TCP here: notification is the serial line's.
                let _ = req.reply.send(outcome.text);
            }
        }
    }
}

async fn connection(stream: TcpStream, device: Arc<Mutex<Device>>, shutdown: CancellationToken) {
    let _ = stream.set_nodelay(true);
    let (mut rd, mut wr) = stream.into_split();
    let mut buf = bytes::BytesMut::with_capacity(512);
    let mut timer = crate::line::port::serial::PreciseTimer::new().ok();
    loop {
        let n = tokio::select! {
            _ = shutdown.cancelled() => return,
            r = rd.read_buf(&mut buf) => r,
        };
        // A replayed device's delay counts from here, the request's last byte in.
        let arrived = tokio::time::Instant::now();
        if !matches!(n, Ok(n) if n > 0) {
            return;
        }
        while let Ok(Some(req)) = decode_strict(&mut buf) {
            let answer = {
                let mut d = device.lock().expect("not poisoned");
                d.log.record(PacketDirection::Rx, req.as_bytes(), "request");
                d.answer(req.unit(), req.pdu())
            };
            info!(target: "mbgate::tools::sim::packets", "rx {} (request)", Hex(req.as_bytes()));
            let Some(pdu) = answer.reply else {
                continue;
            };
            if let Some(delay) = answer.delay {
                // A replayed device's own reply time (`--replay`), to the microsecond:
                // tokio's timer would round it up to the next millisecond.
                super::serve::until_precisely(timer.as_mut(), arrived + delay).await;
            }
            let reply = Adu::build(req.tid(), req.unit(), &pdu);
            info!(target: "mbgate::tools::sim::packets", "tx {} (reply)", Hex(reply.as_bytes()));
            device.lock().expect("not poisoned").log.record(
                PacketDirection::Tx,
                reply.as_bytes(),
                "reply",
            );
            if wr.write_all(reply.as_bytes()).await.is_err() {
                return;
            }
        }
    }
}
