//! Tests of line::outbox.

use super::*;
use std::time::Duration;

fn adu(tid: u16) -> Adu {
    Adu::build(tid, 1, &[0x03, 0x02, 0x00, tid as u8])
}

async fn next_tid(inbox: &mut Inbox) -> u16 {
    let out = tokio::time::timeout(Duration::from_secs(1), inbox.next())
        .await
        .expect("a frame")
        .expect("open");
    out.adu().tid()
}

#[tokio::test]
async fn replies_go_out_in_request_order_and_notifications_at_once() {
    let (mut outbox, mut inbox) = Outbox::new(4);
    let (t0, t1, t2, t3) = (
        outbox.ticket().await,
        outbox.ticket().await,
        outbox.ticket().await,
        outbox.ticket().await,
    );
    assert!(outbox.owed());
    // Answered last to first; the second has no reply at all.
    t3.answer(adu(3));
    drop(t1);
    t2.answer(adu(2));
    assert!(outbox.notifier().notify(adu(0x99)));
    assert_eq!(
        next_tid(&mut inbox).await,
        0x99,
        "a notification waits for nothing"
    );
    t0.answer(adu(0));
    assert_eq!(next_tid(&mut inbox).await, 0);
    assert_eq!(next_tid(&mut inbox).await, 2);
    assert_eq!(next_tid(&mut inbox).await, 3);
    assert!(!outbox.owed(), "every slot free once written");
    tokio::time::timeout(Duration::from_secs(1), outbox.settled())
        .await
        .expect("settled");
}

#[tokio::test]
async fn a_slot_is_free_only_once_its_reply_is_written() {
    let (mut outbox, mut inbox) = Outbox::new(1);
    let t = outbox.ticket().await;
    t.answer(adu(1));
    // Answered, not yet written: the master may not send another yet.
    let waiting = tokio::time::timeout(Duration::from_millis(50), outbox.ticket()).await;
    assert!(waiting.is_err());
    let before = outbox.last_settled();
    let out = inbox.next().await.unwrap();
    assert!(outbox.owed());
    drop(out);
    assert!(!outbox.owed());
    assert!(outbox.last_settled() >= before);
    let _t = tokio::time::timeout(Duration::from_millis(50), outbox.ticket())
        .await
        .expect("a slot again");
}

#[tokio::test]
async fn the_writer_ends_once_nothing_can_send_and_a_waiting_ticket_wakes() {
    let (mut outbox, mut inbox) = Outbox::new(1);
    let notifier = outbox.notifier();
    let t = outbox.ticket().await;
    // A second ticket waits for the one slot, in a task of its own, and gets it
    // once the first reply is written.
    let second = tokio::spawn(async move {
        let t2 = outbox.ticket().await;
        t2.answer(adu(2));
        outbox
    });
    tokio::task::yield_now().await;
    assert!(!second.is_finished(), "one slot, in use");
    t.answer(adu(1));
    assert_eq!(next_tid(&mut inbox).await, 1);
    assert_eq!(next_tid(&mut inbox).await, 2);
    let outbox = tokio::time::timeout(Duration::from_secs(1), second)
        .await
        .expect("the waiting ticket was woken")
        .unwrap();
    // The outbox and the notifier gone, nothing can come: the writer ends.
    drop(outbox);
    let pending = tokio::time::timeout(Duration::from_millis(50), inbox.next()).await;
    assert!(pending.is_err(), "the notifier can still send");
    drop(notifier);
    let end = tokio::time::timeout(Duration::from_secs(1), inbox.next()).await;
    assert!(end.expect("woken").is_none());
}

#[tokio::test]
async fn answers_after_the_writer_is_gone_free_their_slots() {
    let (mut outbox, inbox) = Outbox::new(2);
    let notifier = outbox.notifier();
    let (a, b) = (outbox.ticket().await, outbox.ticket().await);
    a.answer(adu(1));
    drop(inbox);
    assert!(outbox.owed(), "b is still owed");
    b.answer(adu(2));
    assert!(!outbox.owed(), "both slots free");
    assert!(!notifier.notify(adu(3)), "nobody to notify");
    tokio::time::timeout(Duration::from_secs(1), outbox.settled())
        .await
        .expect("settled");
}

#[tokio::test]
async fn notifications_use_only_spare_room() {
    let (mut outbox, mut inbox) = Outbox::new(2);
    let notifier = outbox.notifier();
    let sent = (0..100).filter(|i| notifier.notify(adu(*i))).count();
    assert_eq!(
        sent,
        NOTIFICATION_SLACK + 2,
        "a master not reading misses the rest"
    );
    // The writer catches up; replies still find their room.
    for _ in 0..sent {
        inbox.next().await.unwrap();
    }
    let a = outbox.ticket().await;
    let b = outbox.ticket().await;
    let flood = (0..100).filter(|i| notifier.notify(adu(*i))).count();
    assert_eq!(flood, NOTIFICATION_SLACK, "the tickets' room is theirs");
    b.answer(adu(0xB));
    a.answer(adu(0xA));
    for _ in 0..flood {
        assert!(next_tid(&mut inbox).await < 100);
    }
    assert_eq!(next_tid(&mut inbox).await, 0xA);
    assert_eq!(next_tid(&mut inbox).await, 0xB);
}

#[tokio::test]
async fn every_refusal_answers_its_code_and_counts_it_once() {
    use std::sync::atomic::Ordering;
    let request = Adu::build(0x1234, 7, &[0x03, 0, 0, 0, 1]);
    let cases = [
        (Refusal::BadRequest(ExceptionCode::ILLEGAL_DATA_VALUE), 0x03),
        (Refusal::BadRequest(ExceptionCode::ILLEGAL_FUNCTION), 0x01),
        (Refusal::Unavailable, 0x0A),
        (Refusal::Busy, 0x06),
        (Refusal::TargetFailed, 0x0B),
        (Refusal::BackedOff, 0x0B),
        (Refusal::Denied, 0x01),
    ];
    for (why, code) in cases {
        let stats = Stats::default();
        let (mut outbox, mut inbox) = Outbox::new(1);
        outbox.ticket().await.refuse(&request, why, &stats);
        let out = inbox.next().await.expect("the answer");
        assert_eq!(
            out.adu().as_bytes(),
            Adu::build(0x1234, 7, &[0x83, code]).as_bytes()
        );
        let counted = [
            &stats.bad_requests,
            &stats.unavailable,
            &stats.busy,
            &stats.timeouts,
            &stats.backed_off,
            &stats.denied,
        ]
        .map(|c| c.load(Ordering::Relaxed));
        assert_eq!(counted.iter().sum::<u64>(), 1, "{why:?}: {stats}");
        assert_eq!(why.counter(&stats).load(Ordering::Relaxed), 1, "{why:?}");
    }
    assert_eq!(stats_name(Refusal::BackedOff), "backed_off=1");
    assert_eq!(stats_name(Refusal::TargetFailed), "timeouts=1");
}

/// The one counter `why` adds to, as the stats line shows it.
fn stats_name(why: Refusal) -> String {
    let stats = Stats::default();
    stats.add(why.counter(&stats), 1);
    stats
        .to_string()
        .split(' ')
        .find(|f| f.ends_with("=1"))
        .expect("one counter")
        .to_string()
}

#[tokio::test]
async fn idle_only_while_nothing_is_owed() {
    let idle = Duration::from_secs(5);
    let (mut outbox, mut inbox) = Outbox::new(2);
    let start = Instant::now();
    let later = start + Duration::from_secs(60);
    assert_eq!(
        outbox.idle_at(later, idle),
        Some(later + idle),
        "from the last byte"
    );
    let t = outbox.ticket().await;
    assert_eq!(outbox.idle_at(later, idle), None, "owed a reply");
    t.answer(adu(1));
    assert_eq!(
        outbox.idle_at(later, idle),
        None,
        "its reply not yet written"
    );
    let out = inbox.next().await.unwrap();
    drop(out);
    let settled = outbox.last_settled();
    assert!(settled >= start);
    // From the last reply when it came after the last byte.
    assert_eq!(outbox.idle_at(start, idle), Some(settled + idle));
}
