//! The timer floor (reported with `rtu-limit`): how late this machine wakes a thread
//! sleeping on the gateway's own timer.

use super::report::{spread, Spread};
use std::time::Duration;

/// How late this machine wakes a thread sleeping on a timer: the gateway's own timer
/// ([`mbgate::line::port::serial::PreciseTimer`], a timerfd on tokio's reactor) set 1750 µs ahead
/// (t3.5 above 19 200 baud) 1000 times, on an otherwise idle runtime. A gateway keeps
/// the gap with one such wake more than a master talking straight to the device, so
/// this is the least it can add to a transaction without spinning.
pub(super) fn timer_floor() -> Spread {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a runtime");
    rt.block_on(async {
        let mut timer = mbgate::line::port::serial::PreciseTimer::new().expect("a timerfd");
        let mut late = Vec::new();
        for _ in 0..1000 {
            let at = tokio::time::Instant::now() + Duration::from_micros(1750);
            timer.until(at).await.expect("the timer");
            late.push(tokio::time::Instant::now() - at);
        }
        spread(&late)
    })
}
