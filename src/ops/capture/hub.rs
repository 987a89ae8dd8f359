//! Where captured packets go (docs/capture.md "Never in the line's way"): the relays,
//! the connections and the master line hand each packet to a [`Tap`], which, under
//! one short lock, keeps each interface's times from going back, keeps the last
//! [`RECENT`] of each line for the status page while it is open, and hands each
//! subscriber (a `mbgate capture`, the capture ring) what its filter keeps with
//! `try_send` (never waiting: a full channel drops the packet and counts it).
//!
//! No task stands between a line and a subscriber: a task in between cost a wake of
//! its own for each packet (docs/performance.md "What a capture costs"). The hub's
//! task only ends every subscription when the hub closes.
//!
//! With no subscriber and the status page closed, a tap is two atomic loads and no
//! clock: the relay builds no packet. With only the page open, a packet is filled in
//! place of the line's oldest (docs/performance.md "What the status page costs,
//! counted").

use super::packet::{Dir, Packet, Part, Proto};
use super::request::CaptureRequest;
use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, SystemTime};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

/// Packets waiting for one subscriber.
pub(crate) const PER_SUBSCRIBER: usize = 4096;
/// How long a subscriber lets packets gather after taking some: one wake and one
/// write for a few hundred packets at full speed, where each packet woke it (docs/
/// performance.md "What a capture costs"), and well within what its channel holds.
pub(crate) const GATHER: Duration = Duration::from_millis(10);
/// Packets of each line the status page shows.
pub(crate) const RECENT: usize = 50;
/// Disconnected masters whose addresses are kept for the page: enough for every frame
/// of the last [`RECENT`] of a few lines to have come from a different one.
const GONE: usize = 256;
/// How long the status page counts as open after its last poll.
const PAGE_OPEN_FOR: Duration = Duration::from_secs(10);

/// The one clock of every packet: the monotonic clock, anchored once to the wall
/// clock, so times on every interface compare and never go back.
fn anchor() -> (Instant, u64) {
    static ANCHOR: OnceLock<(Instant, u64)> = OnceLock::new();
    *ANCHOR.get_or_init(|| {
        let wall = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap_or_default();
        (Instant::now(), wall.as_micros() as u64)
    })
}

/// `at` in microseconds since the Unix epoch, on the capture's clock.
pub(crate) fn unix_us(at: Instant) -> u64 {
    let (base, base_us) = anchor();
    match at.checked_duration_since(base) {
        Some(d) => base_us + d.as_micros() as u64,
        None => base_us.saturating_sub(base.duration_since(at).as_micros() as u64),
    }
}

/// One pcapng interface: the TCP side, or a line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Interface {
    /// `if_name`: `tcp`, or the line's name (its serial port, or host:port).
    pub(crate) name: String,
    /// `if_description`: what it is, in words.
    pub(crate) description: String,
}

/// A line's last packets, for the status page.
#[derive(Debug, Default, Clone)]
pub(crate) struct Recent {
    pub(crate) kept: VecDeque<Arc<Packet>>,
    /// Packets recorded in all while the page was open.
    pub(crate) total: u64,
    /// The time of the last packet of this interface handed on, kept or not: one
    /// interface's times never go back.
    last_us: u64,
}

impl Recent {
    /// `p`'s time, never before the last packet's of this interface: a packet handed
    /// on later than one stamped after it (a reply held for its confirmation while the
    /// next request went out) takes that one's time.
    fn stamp(&mut self, p: &mut Packet) {
        p.at_us = p.at_us.max(self.last_us);
        self.last_us = p.at_us;
    }

    /// Keeps `p`, the oldest making room, its time never before the last one's.
    fn record(&mut self, mut p: Packet) {
        self.stamp(&mut p);
        self.keep(Arc::new(p));
    }

    /// Keeps the packet `build` makes (see [`Tap::send_with`]) on interface `iface`
    /// at `at_us`, in the place of the oldest when there is no room, and in its
    /// memory when nothing else holds it (a page being written may).
    fn record_with(
        &mut self,
        iface: u16,
        at_us: u64,
        (dir, part): (Dir, Part),
        build: impl FnOnce(&mut Packet),
    ) {
        let oldest = if self.kept.len() == RECENT {
            self.kept.pop_front()
        } else {
            None
        };
        let fresh = || Arc::new(Packet::new(dir, part, Proto::Data, Vec::new()));
        let mut slot = oldest.unwrap_or_else(fresh);
        if Arc::get_mut(&mut slot).is_none() {
            slot = fresh();
        }
        let p = Arc::get_mut(&mut slot).expect("made here, held here only");
        p.clear(dir, part);
        build(p);
        (p.iface, p.at_us) = (iface, at_us);
        self.stamp(p);
        self.keep(slot);
    }

    fn keep(&mut self, p: Arc<Packet>) {
        if self.kept.len() == RECENT {
            self.kept.pop_front();
        }
        self.kept.push_back(p);
        self.total += 1;
    }
}

struct Sub {
    id: u64,
    request: CaptureRequest,
    keep: Vec<bool>,
    tx: mpsc::Sender<Arc<Packet>>,
    /// Packets this subscriber's full channel dropped, by interface.
    dropped: Arc<[AtomicU64]>,
}

struct HubState {
    interfaces: Vec<Interface>,
    /// Subscribers now: a tap builds packets only while there is one (or the page).
    active: AtomicUsize,
    /// Until when (on the capture's clock) the status page counts as open.
    page_until_us: AtomicU64,
    subs: Mutex<Vec<Sub>>,
    /// Packets any subscriber lost because its channel was full, in all.
    lost: AtomicU64,
    /// Subscriptions not yet dropped, and the news that one was.
    alive: AtomicUsize,
    ended: tokio::sync::Notify,
    next_id: AtomicU64,
    /// The master behind each connection id, for the master filter and the page.
    conns: Mutex<HashMap<u64, SocketAddr>>,
    /// The last [`GONE`] masters that disconnected, oldest first: the page still names
    /// the master of a frame kept from before it went.
    gone: Mutex<VecDeque<(u64, SocketAddr)>>,
    recent: Mutex<Vec<Recent>>,
    closed: CancellationToken,
}

/// The capture's centre: made once at start with its interfaces; cheap to clone.
#[derive(Clone)]
pub(crate) struct Hub(Arc<HubState>);

/// Where one source (a line, the TCP side) hands its packets: cheap to clone.
#[derive(Clone, Default)]
pub(crate) struct Tap {
    hub: Option<Arc<HubState>>,
    iface: u16,
}

/// Why a capture is not started.
#[derive(Debug, thiserror::Error)]
pub(crate) enum CaptureRefusal {
    /// It names a line that is not there.
    #[error(transparent)]
    Request(#[from] super::request::BadRequest),
    /// The gateway is stopping.
    #[error("the gateway is stopping")]
    Stopping,
}

impl Hub {
    /// A hub for these interfaces (0: the TCP side, then each line), and its task.
    pub(crate) fn new(interfaces: Vec<Interface>) -> (Hub, impl std::future::Future<Output = ()>) {
        anchor();
        let n = interfaces.len();
        let shared = Arc::new(HubState {
            recent: Mutex::new(vec![Recent::default(); n]),
            interfaces,
            active: AtomicUsize::new(0),
            page_until_us: AtomicU64::new(0),
            lost: AtomicU64::new(0),
            alive: AtomicUsize::new(0),
            ended: tokio::sync::Notify::new(),
            subs: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(1),
            conns: Mutex::new(HashMap::new()),
            gone: Mutex::new(VecDeque::new()),
            closed: CancellationToken::new(),
        });
        let task = run(shared.clone());
        (Hub(shared), task)
    }

    pub(crate) fn interfaces(&self) -> &[Interface] {
        &self.0.interfaces
    }

    /// The tap of interface `iface`.
    pub(crate) fn tap(&self, iface: u16) -> Tap {
        Tap {
            hub: Some(self.0.clone()),
            iface,
        }
    }

    /// Master connection `conn` is at `peer` (until [`Hub::forget`]).
    pub(crate) fn connected(&self, conn: u64, peer: SocketAddr) {
        self.0
            .conns
            .lock()
            .expect("not poisoned")
            .insert(conn, peer);
    }

    pub(crate) fn forget(&self, conn: u64) {
        let Some(peer) = self.0.conns.lock().expect("not poisoned").remove(&conn) else {
            return;
        };
        let mut gone = self.0.gone.lock().expect("not poisoned");
        if gone.len() == GONE {
            gone.pop_front();
        }
        gone.push_back((conn, peer));
    }

    /// Packets of every interface from now on that `request` keeps (it names only
    /// interfaces there are: see [`CaptureRequest::interfaces`]).
    pub(crate) fn subscribe(
        &self,
        request: CaptureRequest,
    ) -> Result<Subscription, CaptureRefusal> {
        let names: Vec<String> = self.0.interfaces.iter().map(|i| i.name.clone()).collect();
        let keep = request.interfaces(&names)?;
        let (tx, rx) = mpsc::channel(PER_SUBSCRIBER);
        let id = self.0.next_id.fetch_add(1, Ordering::Relaxed);
        let dropped: Arc<[AtomicU64]> = (0..names.len()).map(|_| AtomicU64::new(0)).collect();
        let mut subs = self.0.subs.lock().expect("not poisoned");
        if self.0.closed.is_cancelled() {
            return Err(CaptureRefusal::Stopping);
        }
        subs.push(Sub {
            id,
            request,
            keep,
            tx,
            dropped: dropped.clone(),
        });
        self.0.active.fetch_add(1, Ordering::Relaxed);
        self.0.alive.fetch_add(1, Ordering::Relaxed);
        Ok(Subscription {
            rx,
            id,
            hub: self.0.clone(),
            dropped,
        })
    }

    /// The status page was asked for now: the lines' last packets are kept for a
    /// while. Returns each interface's last packets as kept so far.
    pub(crate) fn page(&self) -> Vec<Recent> {
        let until = unix_us(Instant::now() + PAGE_OPEN_FOR);
        self.0.page_until_us.store(until, Ordering::Relaxed);
        self.0.recent.lock().expect("not poisoned").clone()
    }

    /// The master at connection `conn`, if known: connected, or among the last
    /// [`GONE`] that disconnected.
    pub(crate) fn master(&self, conn: u64) -> Option<SocketAddr> {
        let now = self
            .0
            .conns
            .lock()
            .expect("not poisoned")
            .get(&conn)
            .copied();
        now.or_else(|| {
            let gone = self.0.gone.lock().expect("not poisoned");
            gone.iter().rev().find(|(c, _)| *c == conn).map(|(_, p)| *p)
        })
    }

    /// Packets every capture lost because it was behind, in all.
    pub(crate) fn dropped(&self) -> u64 {
        self.0.lost.load(Ordering::Relaxed)
    }

    /// No more packets: the hub's task ends every subscription (each sees its
    /// channel close once it has taken what was handed to it).
    pub(crate) fn close(&self) {
        self.0.closed.cancel();
    }

    /// Done once [`Hub::close`] was called: a subscriber letting packets gather
    /// stops waiting.
    pub(crate) async fn closed(&self) {
        self.0.closed.cancelled().await;
    }

    /// Once every subscription has been dropped (each capture has written its end),
    /// or `within` has passed: false then.
    pub(crate) async fn ended(&self, within: Duration) -> bool {
        let all = async {
            loop {
                let notified = self.0.ended.notified();
                if self.0.alive.load(Ordering::Acquire) == 0 {
                    return;
                }
                notified.await;
            }
        };
        tokio::time::timeout(within, all).await.is_ok()
    }
}

impl std::fmt::Debug for Hub {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hub")
            .field("interfaces", &self.0.interfaces)
            .field("active", &self.0.active.load(Ordering::Relaxed))
            .finish()
    }
}

impl Tap {
    /// A tap that goes nowhere (no capture configured, tests).
    pub(crate) fn off() -> Tap {
        Tap::default()
    }

    /// Is anyone capturing, or is the status page open? One or two atomic loads, and
    /// no clock: the page's window is closed by the first packet made after it
    /// ended (see [`Tap::send`]), so one packet is made for nothing then.
    pub(crate) fn on(&self) -> bool {
        let Some(h) = &self.hub else {
            return false;
        };
        h.active.load(Ordering::Relaxed) > 0 || h.page_until_us.load(Ordering::Relaxed) != 0
    }

    /// Hands `p` on, stamped with this tap's interface and the time `at`; never
    /// waits: a subscriber that is behind loses the packet, counted. With no
    /// capture running (only the status page open) the packet goes straight into its
    /// interface's last packets, so watching the page costs the line one short lock a
    /// frame (docs/performance.md "What a transaction costs").
    pub(crate) fn send(&self, mut p: Packet, at: Instant) {
        let Some(h) = &self.hub else {
            return;
        };
        p.iface = self.iface;
        p.at_us = unix_us(at);
        if h.active.load(Ordering::Relaxed) == 0 {
            if !page_open(h, p.at_us) {
                return;
            }
            let mut recent = h.recent.lock().expect("not poisoned");
            if let Some(r) = recent.get_mut(usize::from(self.iface)) {
                r.record(p);
            }
            return;
        }
        hand_on(h, p);
    }

    /// As [`Tap::send`], the packet made by `build` from one emptied by
    /// [`Packet::clear`] (`dir`, `part` set). With only the status page open, `build`
    /// fills the oldest of the line's last packets in place where no page holds it
    /// any more: no allocation a frame (docs/performance.md "What the status page
    /// costs, counted").
    pub(crate) fn send_with(
        &self,
        (dir, part): (Dir, Part),
        at: Instant,
        build: impl FnOnce(&mut Packet),
    ) {
        let Some(h) = &self.hub else {
            return;
        };
        if h.active.load(Ordering::Relaxed) > 0 {
            let mut p = Packet::new(dir, part, Proto::Data, Vec::new());
            build(&mut p);
            self.send(p, at);
            return;
        }
        let at_us = unix_us(at);
        if !page_open(h, at_us) {
            return;
        }
        let mut recent = h.recent.lock().expect("not poisoned");
        if let Some(r) = recent.get_mut(usize::from(self.iface)) {
            r.record_with(self.iface, at_us, (dir, part), build);
        }
    }
}

/// Is the status page open at `at_us`? Past its window, closes it (unless the page
/// was asked for again meanwhile), so that [`Tap::on`] needs no clock.
fn page_open(h: &HubState, at_us: u64) -> bool {
    let until = h.page_until_us.load(Ordering::Relaxed);
    if until == 0 {
        return false;
    }
    if until <= at_us {
        let _ = h
            .page_until_us
            .compare_exchange(until, 0, Ordering::Relaxed, Ordering::Relaxed);
        return false;
    }
    true
}

/// One subscriber's packets, until it is dropped (or the hub closes).
pub(crate) struct Subscription {
    pub(crate) rx: mpsc::Receiver<Arc<Packet>>,
    id: u64,
    hub: Arc<HubState>,
    dropped: Arc<[AtomicU64]>,
}

impl Subscription {
    /// Packets this subscription lost because its channel was full, by interface.
    pub(crate) fn dropped(&self) -> Vec<u64> {
        self.dropped
            .iter()
            .map(|d| d.load(Ordering::Relaxed))
            .collect()
    }
}

impl Subscription {
    /// Takes no more packets from now on: the hub forgets this subscriber (its
    /// sender with it), so `rx` gives what was handed to it before, then `None`, and
    /// the counts of [`Subscription::dropped`] are final. A capture stopped by its
    /// client drains that much and no more (docs/capture.md "Stopping a capture").
    pub(crate) fn detach(&mut self) {
        let mut subs = self.hub.subs.lock().expect("not poisoned");
        let before = subs.len();
        subs.retain(|s| s.id != self.id);
        if subs.len() < before {
            self.hub.active.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.detach();
        self.hub.alive.fetch_sub(1, Ordering::Release);
        self.hub.ended.notify_waiters();
    }
}

/// The hub's task: when the hub closes, every subscription ends.
async fn run(shared: Arc<HubState>) {
    shared.closed.cancelled().await;
    let mut subs = shared.subs.lock().expect("not poisoned");
    shared.active.fetch_sub(subs.len(), Ordering::Relaxed);
    subs.clear();
}

/// `p` to the page, if open, and to each subscriber whose filter keeps it. Stamped
/// while the subscribers are held, so that they get one interface's packets in the
/// order of their times.
fn hand_on(shared: &HubState, mut p: Packet) {
    let i = usize::from(p.iface);
    let subs = shared.subs.lock().expect("not poisoned");
    let p = {
        let mut recent = shared.recent.lock().expect("not poisoned");
        let Some(r) = recent.get_mut(i) else {
            return;
        };
        r.stamp(&mut p);
        let p = Arc::new(p);
        let page = shared.page_until_us.load(Ordering::Relaxed);
        if page != 0 && page > p.at_us {
            r.keep(p.clone());
        }
        p
    };
    if subs.is_empty() {
        return;
    }
    let master = match (p.conn, subs.iter().any(|s| !s.request.masters.is_empty())) {
        (Some(conn), true) => shared
            .conns
            .lock()
            .expect("not poisoned")
            .get(&conn)
            .copied(),
        _ => None,
    };
    for s in subs.iter() {
        if !s.keep[i] || !s.request.keeps(&p, master) {
            continue;
        }
        if s.tx.try_send(p.clone()).is_err() {
            s.dropped[i].fetch_add(1, Ordering::Relaxed);
            shared.lost.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hub() -> Hub {
        let iface = |n: &str| Interface {
            name: n.into(),
            description: String::new(),
        };
        let (hub, task) = Hub::new(vec![iface("tcp"), iface("/dev/ttyX")]);
        tokio::spawn(task);
        hub
    }

    fn frame(unit: u8) -> Packet {
        let mut p = Packet::new(Dir::Out, Part::Query, Proto::Mbtcp, vec![unit]);
        p.unit = Some(unit);
        p
    }

    /// With only the status page open, a packet is among the line's last at once,
    /// without the hub's task (never started here); closed, nothing is kept.
    #[tokio::test]
    async fn with_only_the_page_open_packets_are_kept_without_the_hubs_task() {
        let iface = |n: &str| Interface {
            name: n.into(),
            description: String::new(),
        };
        let (hub, _task) = Hub::new(vec![iface("tcp"), iface("/dev/ttyX")]);
        let tap = hub.tap(1);
        let t0 = Instant::now();
        tap.send(frame(9), t0);
        assert!(hub.page()[1].kept.is_empty(), "the page was closed");
        assert!(tap.on(), "the page is open now");
        for unit in 0..RECENT as u8 + 2 {
            tap.send(frame(unit), t0);
        }
        let recent = &hub.page()[1];
        assert_eq!(recent.total, RECENT as u64 + 2);
        let units: Vec<_> = recent.kept.iter().map(|p| p.unit).collect();
        let want: Vec<_> = (2..RECENT as u8 + 2).map(Some).collect();
        assert_eq!(units, want, "the last RECENT, oldest first");
        assert!(hub.page()[0].kept.is_empty());
    }

    /// The page's packets are filled in place only where nothing else holds them:
    /// a page being written keeps what it took, unchanged, while the line goes on.
    #[tokio::test]
    async fn a_packet_the_page_holds_is_never_filled_again_and_one_it_let_go_is() {
        let (hub, _task) = Hub::new(vec![
            Interface {
                name: "tcp".into(),
                description: String::new(),
            },
            Interface {
                name: "/dev/ttyX".into(),
                description: String::new(),
            },
        ]);
        let tap = hub.tap(1);
        let t0 = Instant::now();
        let fill = |unit: u8| {
            tap.send_with((Dir::Out, Part::Query), t0, |p| {
                p.bytes.extend_from_slice(&[unit; 8]);
                p.unit = Some(unit);
            })
        };
        hub.page();
        for unit in 0..RECENT as u8 {
            fill(unit);
        }
        let held = hub.page();
        let oldest = Arc::as_ptr(&held[1].kept[0]);
        fill(200);
        let recent = hub.page();
        let newest = recent[1].kept.back().unwrap();
        assert_ne!(
            Arc::as_ptr(newest),
            oldest,
            "the held page's packet is not reused"
        );
        assert_eq!(held[1].kept[0].unit, Some(0));
        assert_eq!(
            held[1].kept[0].bytes, [0; 8],
            "what the page holds is unchanged"
        );
        assert_eq!((newest.unit, &newest.bytes[..]), (Some(200), &[200; 8][..]));
        assert_eq!(recent[1].kept[0].unit, Some(1));
        drop((held, recent));
        let second = Arc::as_ptr(&hub.page()[1].kept[0]);
        fill(201);
        let recent = hub.page();
        let newest = recent[1].kept.back().unwrap();
        assert_eq!(Arc::as_ptr(newest), second, "let go: filled again in place");
        let mut want = Packet::new(Dir::Out, Part::Query, Proto::Data, vec![201; 8]);
        (want.iface, want.at_us, want.unit) = (1, unix_us(t0), Some(201));
        assert_eq!(**newest, want, "nothing left of the packet it was");
        assert_eq!(recent[1].total, RECENT as u64 + 2);
    }

    /// A tap asks no clock whether the page is open: the first packet made after the
    /// page's window closes it; the page asked for again opens it.
    #[tokio::test]
    async fn the_page_s_window_is_closed_by_the_first_packet_after_it() {
        let hub = hub();
        let tap = hub.tap(1);
        assert!(!tap.on());
        hub.page();
        assert!(tap.on());
        let late = Instant::now() + PAGE_OPEN_FOR + Duration::from_secs(1);
        assert!(tap.on(), "no packet made since the window ended");
        tap.send_with((Dir::In, Part::Reply), late, |p| p.unit = Some(1));
        assert!(!tap.on(), "closed by the packet after the window");
        assert_eq!(hub.page()[1].total, 0, "and that packet is not kept");
        assert!(tap.on(), "asked for again");
        tap.send(frame(2), Instant::now());
        assert_eq!(hub.page()[1].kept.back().map(|p| p.unit), Some(Some(2)));
    }

    #[tokio::test]
    async fn a_tap_is_off_until_someone_subscribes_and_a_full_subscriber_loses_packets_counted() {
        let hub = hub();
        let tap = hub.tap(1);
        assert!(!tap.on());
        let mut sub = hub
            .subscribe(CaptureRequest::parse("capture unit=1").unwrap())
            .unwrap();
        assert!(tap.on());
        let t0 = Instant::now();
        for _ in 0..PER_SUBSCRIBER + 10 {
            tap.send(frame(1), t0);
            tap.send(frame(2), t0);
            tokio::task::yield_now().await;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        let mut got = 0;
        while let Ok(p) = sub.rx.try_recv() {
            assert_eq!((p.unit, p.iface), (Some(1), 1));
            got += 1;
        }
        assert_eq!(got, PER_SUBSCRIBER);
        assert_eq!(sub.dropped(), [0, 10], "unit 2 filtered out, not dropped");
        drop(sub);
        assert!(!tap.on());
    }

    #[tokio::test]
    async fn times_on_an_interface_never_go_back_and_closing_ends_subscriptions() {
        let hub = hub();
        let mut sub = hub.subscribe(CaptureRequest::default()).unwrap();
        let tap = hub.tap(1);
        let t0 = Instant::now();
        tap.send(frame(1), t0 + Duration::from_millis(5));
        tap.send(frame(1), t0);
        hub.tap(0).send(frame(1), t0);
        let a = sub.rx.recv().await.unwrap();
        let b = sub.rx.recv().await.unwrap();
        let c = sub.rx.recv().await.unwrap();
        assert_eq!(a.at_us, b.at_us);
        assert_eq!(c.at_us, unix_us(t0), "another interface keeps its own time");
        hub.close();
        assert!(sub.rx.recv().await.is_none());
        assert!(hub.subscribe(CaptureRequest::default()).is_err());
    }

    /// A stopping gateway waits for its captures to end, and not for ever.
    #[tokio::test]
    async fn the_hub_has_ended_once_every_subscription_is_dropped() {
        let hub = hub();
        assert!(hub.ended(Duration::ZERO).await, "none to wait for");
        let mut sub = hub.subscribe(CaptureRequest::default()).unwrap();
        hub.tap(1).send(frame(1), Instant::now());
        hub.close();
        assert!(
            !hub.ended(Duration::from_millis(50)).await,
            "one still writing"
        );
        let waiter = {
            let hub = hub.clone();
            tokio::spawn(async move { hub.ended(Duration::from_secs(60)).await })
        };
        assert_eq!(sub.rx.recv().await.map(|p| p.unit), Some(Some(1)));
        assert!(
            sub.rx.recv().await.is_none(),
            "closed after the last packet"
        );
        drop(sub);
        assert!(waiter.await.unwrap());
    }

    #[tokio::test]
    async fn the_page_keeps_each_line_s_last_packets_while_it_is_open() {
        let hub = hub();
        let tap = hub.tap(1);
        tap.send(frame(1), Instant::now());
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(hub.page()[1].kept.is_empty(), "not open yet");
        assert!(tap.on());
        for _ in 0..RECENT + 5 {
            tap.send(frame(1), Instant::now());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        let r = &hub.page()[1];
        assert_eq!((r.kept.len(), r.total), (RECENT, RECENT as u64 + 5));
    }

    #[test]
    fn a_master_that_disconnected_keeps_its_address_for_the_page() {
        let (hub, _task) = Hub::new(vec![]);
        let peer: SocketAddr = "10.0.0.7:40001".parse().unwrap();
        hub.connected(7, peer);
        hub.forget(7);
        assert_eq!(hub.master(7), Some(peer));
        for c in 100..100 + GONE as u64 {
            hub.connected(c, peer);
            hub.forget(c);
        }
        assert_eq!(hub.master(7), None, "the oldest forgotten first");
        assert_eq!(hub.master(99 + GONE as u64), Some(peer));
    }
}
