//! Tests of tools::scan.

use super::report::slow_units;
use super::*;

fn unit(id: u8, ms: &[u64]) -> Found {
    Found {
        unit: id,
        serial: None,
        answered: String::new(),
        device_id: Err(probe::NoIdentity::NotAsked),
        server_id: Err(probe::NoIdentity::NotAsked),
        replies: ms.iter().map(|&m| Duration::from_millis(m)).collect(),
        after: Duration::ZERO,
    }
}

#[test]
fn a_unit_much_slower_than_the_rest_gets_a_timeout_of_its_own() {
    let (a, b, c) = (
        unit(1, &[10, 12, 9]),
        unit(2, &[11, 14]),
        unit(3, &[200, 260]),
    );
    assert_eq!(
        c.reply_time(),
        Some((Duration::from_millis(260), Duration::from_millis(260)))
    );
    let slow = slow_units(&[&a, &b, &c]);
    assert_eq!(slow.len(), 1);
    assert_eq!((slow[0].0.unit, slow[0].1), (3, 520));
    // A lone unit is named only when the default timeout would cut it short.
    assert!(slow_units(&[&c]).is_empty());
    let lone = unit(4, &[600]);
    assert_eq!(slow_units(&[&lone])[0].1, 1200);
    // None without reply times.
    assert!(slow_units(&[&unit(5, &[])]).is_empty());
    assert_eq!(unit(5, &[]).reply_time(), None);
}
