//! The pcapng reader (src/ops/capture/pcapng_read.rs) on arbitrary files: it never panics,
//! stops at damage inside the file, and every packet it gives lies within the file and
//! names an interface it gave.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::ops::capture::pcapng_read::{exported, read};

fuzz_target!(|file: &[u8]| {
    match read(file) {
        Err(d) => assert_eq!(d.offset, 0, "refused only at its start"),
        Ok(r) => {
            if let Some(d) = &r.damage {
                assert!(d.offset < file.len());
            }
            for p in &r.packets {
                assert!(p.interface < r.interfaces.len());
                assert!(p.data.len() <= file.len());
                if let Some(e) = exported(p.data) {
                    assert!(e.payload.len() <= p.data.len());
                }
            }
        }
    }
});
