//! Tests of tools::client.

use super::*;
use std::time::UNIX_EPOCH;

#[test]
fn value_lines_format() {
    assert_eq!(
        value_lines(&Reply::Registers {
            addr: 0,
            values: vec![0xFF, 1001]
        }),
        ["0: 255 (0x00FF)", "1: 1001 (0x03E9)"]
    );
    assert_eq!(
        value_lines(&Reply::Bits {
            addr: 20,
            values: vec![true, false]
        }),
        ["20: 1", "21: 0"]
    );
    let wrote = |addr, qty, coils| value_lines(&Reply::WroteMany { addr, qty, coils });
    assert_eq!(wrote(20, 3, false), ["wrote 3 registers at 20..=22"]);
    assert_eq!(wrote(8, 1, false), ["wrote 1 register at 8"]);
    assert_eq!(wrote(0, 10, true), ["wrote 10 coils at 0..=9"]);
}

#[test]
fn timestamps() {
    assert_eq!(utc_stamp(UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
    // 2024-02-29T12:34:56.789Z
    let t = UNIX_EPOCH + Duration::from_millis(1_709_210_096_789);
    assert_eq!(utc_stamp(t), "2024-02-29T12:34:56.789Z");
}
