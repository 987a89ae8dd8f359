//! The always-on capture (`[capture] file`, docs/capture.md "Always on"): every packet
//! into a ring of files, as tcpdump's `-C` and `-W` keep one. The current file is
//! `file`; when the next packet would take it past `file_size_kb`, it becomes
//! `file.1`, the older ones move up one (`file.1` to `file.2`, ...), the oldest beyond
//! `files` is deleted, and a new `file` begins. Each file is a whole pcapng file.
//!
//! Files are written on a thread of their own, so a slow disk never holds up the
//! runtime; packets the thread cannot take in time are dropped and counted, as for
//! any capture. A write that fails (a full disk) ends the ring, with one error in the
//! log: the gateway goes on.

use super::hub::{Hub, Subscription, GATHER};
use super::pcapng;
use super::request::CaptureRequest;
use crate::config::CaptureConfig;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use tracing::{error, info, warn};

/// The ring's files: `file`, then `file.1` (newest) to `file.N-1` (oldest).
fn nth(file: &Path, n: u32) -> PathBuf {
    if n == 0 {
        return file.to_owned();
    }
    let mut name = file.as_os_str().to_owned();
    name.push(format!(".{n}"));
    PathBuf::from(name)
}

/// Moves each file of the ring up one, deleting the oldest: `file` is free again.
/// Only regular files move (a ring pointed at a device is written in place).
fn rotate(file: &Path, files: u32) -> std::io::Result<()> {
    if !std::fs::metadata(file).is_ok_and(|m| m.is_file()) {
        return Ok(());
    }
    let _ = std::fs::remove_file(nth(file, files - 1));
    for n in (0..files - 1).rev() {
        let from = nth(file, n);
        if from.exists() {
            std::fs::rename(&from, nth(file, n + 1))?;
        }
    }
    Ok(())
}

struct Ring {
    file: PathBuf,
    files: u32,
    limit: u64,
    head: Vec<u8>,
    out: Option<BufWriter<File>>,
    size: u64,
    packets: u64,
}

impl Ring {
    /// A new current file, the previous one (if any) moved up the ring.
    fn begin(&mut self) -> std::io::Result<()> {
        if let Some(mut out) = self.out.take() {
            out.flush()?;
        }
        rotate(&self.file, self.files)?;
        let mut out = BufWriter::with_capacity(64 * 1024, File::create(&self.file)?);
        out.write_all(&self.head)?;
        self.size = self.head.len() as u64;
        self.out = Some(out);
        Ok(())
    }

    fn write(&mut self, block: &[u8]) -> std::io::Result<()> {
        if self.size + block.len() as u64 > self.limit {
            self.begin()?;
        }
        self.out.as_mut().expect("begun").write_all(block)?;
        self.size += block.len() as u64;
        self.packets += 1;
        Ok(())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match &mut self.out {
            Some(out) => out.flush(),
            None => Ok(()),
        }
    }
}

/// Starts the ring of `cfg` (if it has a file) on a thread of its own; the thread
/// ends when the hub closes, its files flushed.
pub(crate) fn start(cfg: &CaptureConfig, hub: &Hub) -> Option<std::thread::JoinHandle<()>> {
    if cfg.file.trim().is_empty() {
        return None;
    }
    let sub = match hub.subscribe(CaptureRequest::default()) {
        Ok(s) => s,
        Err(e) => {
            warn!("capture.file: {e}");
            return None;
        }
    };
    let mut head = pcapng::section_header(&format!("mbgate {}", env!("CARGO_PKG_VERSION")));
    for i in hub.interfaces() {
        head.extend(pcapng::interface(&i.name, &i.description));
    }
    let ring = Ring {
        file: PathBuf::from(&cfg.file),
        files: cfg.files,
        limit: cfg.file_size_kb * 1024,
        head,
        out: None,
        size: 0,
        packets: 0,
    };
    let spawned = std::thread::Builder::new()
        .name("capture-ring".into())
        .spawn(move || run(ring, sub));
    match spawned {
        Ok(t) => Some(t),
        Err(e) => {
            warn!("capture.file: no thread for it ({e})");
            None
        }
    }
}

fn run(mut ring: Ring, mut sub: Subscription) {
    let shown = ring.file.display().to_string();
    if let Err(e) = ring.begin() {
        error!("capture.file: cannot write {shown}: {e}; no capture ring (the gateway goes on)");
        return;
    }
    info!(
        "capture ring: {shown} and {} older files of {} kB",
        ring.files - 1,
        ring.limit / 1024
    );
    let result = (|| -> std::io::Result<()> {
        while let Some(p) = sub.rx.blocking_recv() {
            ring.write(&p.block(u32::from(p.iface)))?;
            // What came meanwhile, then to the disk in one go.
            while let Ok(p) = sub.rx.try_recv() {
                ring.write(&p.block(u32::from(p.iface)))?;
            }
            ring.flush()?;
            // Packets gather meanwhile: one wake and one write for many.
            std::thread::sleep(GATHER);
        }
        ring.flush()
    })();
    let dropped: u64 = sub.dropped().iter().sum();
    match result {
        Ok(()) => info!(
            packets = ring.packets,
            dropped, "capture ring stopped: {shown}"
        ),
        Err(e) => error!(
            packets = ring.packets,
            dropped,
            "capture.file: cannot write {shown}: {e}; the capture ring stopped (the gateway goes on)"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ring_moves_each_file_up_and_deletes_the_oldest() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("cap.pcapng");
        let mut ring = Ring {
            file: file.clone(),
            files: 3,
            limit: 100,
            head: vec![b'H'; 20],
            out: None,
            size: 0,
            packets: 0,
        };
        ring.begin().unwrap();
        for i in 0..9u8 {
            ring.write(&[b'0' + i; 40]).unwrap();
        }
        ring.flush().unwrap();
        let read = |n| std::fs::read(nth(&file, n)).unwrap();
        // 20 + 2 x 40 fit in 100: files of two packets each; 9 packets make five
        // files, of which the last three are kept.
        assert_eq!(read(0), [&[b'H'; 20][..], &[b'8'; 40]].concat());
        assert_eq!(
            read(1),
            [&[b'H'; 20][..], &[b'6'; 40], &[b'7'; 40]].concat()
        );
        assert_eq!(
            read(2),
            [&[b'H'; 20][..], &[b'4'; 40], &[b'5'; 40]].concat()
        );
        assert!(!nth(&file, 3).exists());
        // A new run keeps the last one's current file as the newest old one.
        ring.out = None;
        ring.begin().unwrap();
        ring.flush().unwrap();
        assert_eq!(read(1)[20], b'8');
        assert_eq!(read(0).len(), 20);
    }
}
