//! The agent's bus presence (after `swarmrt.node.Node`): a Zenoh client session, messages
//! decoded and checked on Zenoh's callback threads and handed to the one main thread as
//! events, malformed-message accounting, liveliness (its own token; its peers', the
//! world's and the recorder's, with vanished tokens held back), the link to the routers
//! watched (events `bus` down/up; exit 3 after `bus_lost_after_s` without one), queries
//! and puts.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::Wait;

use crate::checks::{self, Msg, Refused};
use crate::log;

/// What the main thread is handed.
#[derive(Debug)]
pub enum Ev {
    /// A decoded, checked message.
    Msg { msg: Box<Msg> },
    /// A liveliness token appeared or (after the hold) vanished.
    Alive { key: String, role: String, sat: Option<u32>, alive: bool },
    /// A vanished token, not yet known to be gone for good.
    Held { key: String },
    /// A held token came back: nothing was lost as far as anyone need know.
    Resync { key: String },
    /// The link to the routers went (false) or came back (true).
    Bus { alive: bool },
}

/// Malformed messages dropped, shared with the callback threads.
#[derive(Default)]
pub struct Counters {
    pub malformed: AtomicU64,
    pub key_mismatch: AtomicU64,
    logged: AtomicU64,
    /// Thread CPU time spent decoding and checking messages (ns), reset by each estimate.
    pub codec_ns: AtomicU64,
}

impl Counters {
    pub fn count(&self, key: &str, err: &Refused) {
        let n = self.malformed.fetch_add(1, Ordering::SeqCst) + 1;
        if err.key_mismatch {
            self.key_mismatch.fetch_add(1, Ordering::SeqCst);
        }
        // The first few in full, then one in a hundred: a flood must not become a log flood.
        if self.logged.load(Ordering::SeqCst) < 20 || n % 100 == 0 {
            self.logged.fetch_add(1, Ordering::SeqCst);
            log::warn(&format!("dropped malformed message #{n} on {key}: {}", err.reason));
        }
    }
}

/// This thread's CPU time (ns).
pub fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// The run is broken: exit with this status after closing the session.
#[derive(Debug)]
pub struct Broken {
    pub code: i32,
    pub why: String,
}

pub const EXIT_BUS_LOST: i32 = 3;
pub const EXIT_WORLD_LOST: i32 = 4;

#[derive(Clone)]
pub struct BusLimits {
    pub hold_s: f64,
    pub bus_grace_s: f64,
    pub bus_lost_after_s: f64,
}

impl BusLimits {
    /// How long a vanished token of `role` is held before it counts as gone.
    pub fn hold_for(&self, role: &str) -> f64 {
        if role == "world" || role == "recorder" {
            self.bus_lost_after_s
        } else {
            self.hold_s
        }
    }
}

pub struct Node {
    pub session: zenoh::Session,
    pub run: String,
    pub root: String,
    pub n: usize,
    pub counters: Arc<Counters>,
    pub stop: Arc<AtomicBool>,
    tx: Sender<Ev>,
    rx: Receiver<Ev>,
    subs: Vec<zenoh::pubsub::Subscriber<()>>,
    lsubs: Vec<zenoh::pubsub::Subscriber<()>>,
    queryables: Vec<zenoh::query::Queryable<()>>,
    token: Option<LivelinessToken>,
    watcher_stop: Arc<AtomicBool>,
    watcher: Option<std::thread::JoinHandle<()>>,
    limits: BusLimits,
    pub bus_down_since: Option<Instant>,
    held: HashMap<String, (Ev, Option<Instant>)>,
    pub epoch: u64,
    // After a return (the bus back, a held token back), when the bus's return is said again
    // (AGAIN_AFTER_S later, in order): the agent sends its last steps once more (`Node._echo`).
    agains: Vec<Instant>,
}

/// After a return, when it is said again: a put made while a failover still rebuilds the
/// routers' routes is lost without a trace, and the sending again at the return can be one.
const AGAIN_AFTER_S: [f64; 2] = [1.0, 3.0];

/// How long a client may take to reach one of its routers at start.
pub const CONNECT_TIMEOUT_MS: u64 = 10_000;

/// The Zenoh configuration of a client of `endpoints` with the credential file `cred`.
pub fn zenoh_config(endpoints: &[String], cred: Option<&str>) -> Result<zenoh::Config, String> {
    client_config(endpoints, cred, CONNECT_TIMEOUT_MS)
}

fn client_config(endpoints: &[String], cred: Option<&str>, timeout_ms: u64) -> Result<zenoh::Config, String> {
    let mut c = zenoh::Config::default();
    let mut set = |k: &str, v: String| c.insert_json5(k, &v).map_err(|e| format!("zenoh config {k}: {e}"));
    set("mode", "\"client\"".into())?;
    set("connect/endpoints", serde_json::to_string(endpoints).unwrap_or_default())?;
    set("connect/timeout_ms", timeout_ms.to_string())?;
    // Rejoin quickly after a partition heals (as the Python roles: swarmrt.bus.session).
    set("connect/retry", r#"{"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}"#.into())?;
    set("scouting/multicast/enabled", "false".into())?;
    // Every put carries this session's clock (the recorder measures bus latency from it).
    set("timestamping/enabled", "true".into())?;
    if let Some(path) = cred {
        let text = std::fs::read_to_string(path).map_err(|e| format!("credential {path}: {e}"))?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("credential {path}: {e}"))?;
        for field in ["user", "password"] {
            let s = v.get(field).and_then(|x| x.as_str()).ok_or_else(|| format!("credential {path}: no \"{field}\""))?;
            set(&format!("transport/auth/usrpwd/{field}"), serde_json::to_string(s).unwrap_or_default())?;
        }
        // The CA is for TLS endpoints only (contract clause 1): over TCP (a local swarm run,
        // compose's bus network) a credential that names one is used as it is.
        let tls: Vec<&String> = endpoints.iter().filter(|e| e.starts_with("tls/")).collect();
        if !tls.is_empty() {
            return Err(format!("endpoint {}: TLS, and this agent is built without Zenoh's TLS transport (TCP endpoints only)", tls[0]));
        }
    }
    Ok(c)
}

/// A session of a client of `endpoints`: the first router that is up, within
/// [`CONNECT_TIMEOUT_MS`] in all. As swarmrt.bus.session.open_session, and for the same
/// reason: a Zenoh 1.x client whose connect/timeout_ms is set retries its first endpoint
/// until the timeout and never tries the others (a router of two that is down when the
/// agent starts would keep it off the bus), so each attempt puts another endpoint first,
/// with a share of the time.
pub fn open_client(endpoints: &[String], cred: Option<&str>) -> Result<zenoh::Session, String> {
    let fail = |e: zenoh::Error| format!("cannot open a Zenoh session: {e}");
    if endpoints.len() < 2 {
        return zenoh::open(client_config(endpoints, cred, CONNECT_TIMEOUT_MS)?).wait().map_err(fail);
    }
    let deadline = Instant::now() + Duration::from_millis(CONNECT_TIMEOUT_MS);
    let share_ms = (CONNECT_TIMEOUT_MS / (2 * endpoints.len() as u64)).max(500);
    let mut attempt = 0usize;
    loop {
        let mut order = endpoints.to_vec();
        order.rotate_left(attempt % endpoints.len());
        let left_ms = deadline.saturating_duration_since(Instant::now()).as_millis() as u64;
        match zenoh::open(client_config(&order, cred, share_ms.min(left_ms).max(100))?).wait() {
            Ok(session) => return Ok(session),
            Err(e) if Instant::now() >= deadline => return Err(fail(e)),
            Err(_) => attempt += 1,
        }
    }
}

impl Node {
    pub fn open(session: zenoh::Session, run: &str, n: usize, limits: BusLimits, stop: Arc<AtomicBool>) -> Result<Node, String> {
        let (tx, rx) = mpsc::channel();
        let watcher_stop = Arc::new(AtomicBool::new(false));
        // The link to the routers: polled (transport events are an unstable Zenoh API).
        let watcher = {
            let s = session.clone();
            let tx = tx.clone();
            let stop_w = watcher_stop.clone();
            std::thread::Builder::new()
                .name("routers".into())
                .spawn(move || {
                    let mut up = false;
                    while !stop_w.load(Ordering::SeqCst) {
                        let now_up = s.info().routers_zid().wait().next().is_some();
                        if now_up != up {
                            up = now_up;
                            if tx.send(Ev::Bus { alive: up }).is_err() {
                                return;
                            }
                        }
                        std::thread::sleep(Duration::from_millis(50));
                    }
                })
                .map_err(|e| format!("thread: {e}"))?
        };
        Ok(Node {
            session,
            run: run.to_string(),
            root: format!("swarm/{run}"),
            n,
            counters: Arc::new(Counters::default()),
            stop,
            tx,
            rx,
            subs: vec![],
            lsubs: vec![],
            queryables: vec![],
            token: None,
            watcher_stop,
            watcher: Some(watcher),
            limits,
            bus_down_since: None,
            held: HashMap::new(),
            epoch: 0,
            agains: vec![],
        })
    }

    /// Samples of `key` are decoded, checked and queued as events.
    pub fn subscribe(&mut self, key: &str) -> Result<(), String> {
        let tx = self.tx.clone();
        let counters = self.counters.clone();
        let (run, n) = (self.run.clone(), self.n);
        let sub = self
            .session
            .declare_subscriber(key)
            .callback(move |sample| {
                let t0 = thread_cpu_ns();
                let key = sample.key_expr().as_str().to_string();
                let ev = if sample.kind() == SampleKind::Delete {
                    Err(Refused { reason: "unexpected delete".into(), key_mismatch: false })
                } else {
                    decode_sample(&key, &sample.payload().to_bytes(), &run, n)
                };
                counters.codec_ns.fetch_add(thread_cpu_ns().saturating_sub(t0), Ordering::Relaxed);
                match ev {
                    Ok(ev) => {
                        let _ = tx.send(ev);
                    }
                    Err(e) => counters.count(&key, &e),
                }
            })
            .wait()
            .map_err(|e| format!("subscribe {key}: {e}"))?;
        self.subs.push(sub);
        Ok(())
    }

    /// Liveliness tokens matching `pattern` (with those already declared) as events.
    pub fn watch_liveliness(&mut self, pattern: &str) -> Result<(), String> {
        let tx = self.tx.clone();
        let counters = self.counters.clone();
        let run = self.run.clone();
        let sub = self
            .session
            .liveliness()
            .declare_subscriber(pattern)
            .history(true)
            .callback(move |sample| {
                let key = sample.key_expr().as_str().to_string();
                let parts: Vec<&str> = key.split('/').collect();
                if parts.len() != 5 || parts[0] != "swarm" || parts[2] != "alive" || parts[1] != run {
                    counters.count(&key, &Refused { reason: format!("unexpected liveliness key {key:?}"), key_mismatch: false });
                    return;
                }
                let sat = parts[4].parse::<u32>().ok().filter(|_| parts[4].bytes().all(|c| c.is_ascii_digit()));
                let _ = tx.send(Ev::Alive { role: parts[3].to_string(), sat, alive: sample.kind() == SampleKind::Put, key });
            })
            .wait()
            .map_err(|e| format!("watch {pattern}: {e}"))?;
        self.lsubs.push(sub);
        Ok(())
    }

    /// A queryable that answers nothing (a `ci` agent has no full estimate to serve a
    /// restarted peer: `cov/<i>` stays silent, as the Python agent's).
    pub fn silent_queryable(&mut self, key: &str) -> Result<(), String> {
        let q = self.session.declare_queryable(key).callback(|_query| {}).wait().map_err(|e| format!("queryable {key}: {e}"))?;
        self.queryables.push(q);
        Ok(())
    }

    /// Declare this agent alive (after its subscriptions: "alive" means "listening").
    pub fn announce(&mut self, key: &str) -> Result<(), String> {
        if self.token.is_none() {
            self.token = Some(self.session.liveliness().declare_token(key).wait().map_err(|e| format!("token {key}: {e}"))?);
        }
        Ok(())
    }

    /// Publish (reliably: congestion control BLOCK).
    pub fn session_put(&self, key: &str, bytes: Vec<u8>) -> Result<(), String> {
        self.session.put(key, bytes).congestion_control(CongestionControl::Block).wait().map_err(|e| e.to_string())
    }

    /// The first valid reply to a query, decoded and checked, or None after `timeout`.
    pub fn query(&self, key: &str, kind: &str, timeout: Duration) -> Option<Msg> {
        let replies = match self.session.get(key).timeout(timeout).wait() {
            Ok(r) => r,
            Err(e) => {
                log::warn(&format!("query {key}: {e}"));
                return None;
            }
        };
        let deadline = Instant::now() + timeout + Duration::from_millis(500);
        while let Ok(Some(reply)) = replies.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            let Ok(sample) = reply.result() else { continue };
            let rkey = sample.key_expr().as_str().to_string();
            let got = checks::decode(kind, &sample.payload().to_bytes(), self.n).and_then(|m| {
                let (run, _k, sat) =
                    checks::parse_key(&rkey).ok_or_else(|| Refused { reason: format!("unexpected key {rkey:?}"), key_mismatch: false })?;
                if run != self.run || m.run() != self.run {
                    return Err(Refused { reason: format!("a reply of another run ({run:?}, {:?})", m.run()), key_mismatch: false });
                }
                checks::check_key(&rkey, kind, sat, &m)?;
                Ok(m)
            });
            match got {
                Ok(m) => return Some(m),
                Err(e) => self.counters.count(key, &e),
            }
        }
        None
    }

    // -- the bus's health ---------------------------------------------------------------

    /// What the main loop is told of `ev` (`Node._filter`): a vanished token is held back
    /// (`hold_s`; while the bus is down, and `bus_grace_s` after it is back) and forgotten
    /// if it comes back meanwhile.
    fn filter(&mut self, ev: Ev) -> Option<Ev> {
        let now = Instant::now();
        match ev {
            Ev::Bus { alive: false } => {
                if self.bus_down_since.is_some() {
                    return None;
                }
                self.bus_down_since = Some(now);
                self.agains.clear(); // no use while no router is reachable: its return sends again
                for v in self.held.values_mut() {
                    v.1 = None;
                }
                log::warn(&format!(
                    "bus lost: no Zenoh router reachable; waiting for it to come back (at most {:.0} s)",
                    self.limits.bus_lost_after_s
                ));
                Some(Ev::Bus { alive: false })
            }
            Ev::Bus { alive: true } => {
                let since = self.bus_down_since?; // the first link is not a return
                log::warn(&format!("bus back after {:.2} s", now.duration_since(since).as_secs_f64()));
                self.bus_down_since = None;
                self.epoch += 1;
                let limits = self.limits.clone();
                for v in self.held.values_mut() {
                    let role = if let Ev::Alive { role, .. } = &v.0 { role.as_str() } else { "" };
                    v.1 = Some(now + Duration::from_secs_f64(limits.bus_grace_s.max(limits.hold_for(role))));
                }
                Some(Ev::Bus { alive: true })
            }
            Ev::Alive { key, role, sat, alive: false } => {
                // The world's and the recorder's tokens are held as long as a bus loss is
                // (`Node.set_bus_limits`): a world may only be stalled, a recorder failing over.
                let hold = self.limits.hold_for(&role);
                let at = if self.bus_down_since.is_some() { None } else { Some(now + Duration::from_secs_f64(hold)) };
                self.held.insert(key.clone(), (Ev::Alive { key: key.clone(), role, sat, alive: false }, at));
                Some(Ev::Held { key })
            }
            Ev::Alive { key, role, sat, alive: true } => {
                if self.held.remove(&key).is_some() {
                    self.epoch += 1;
                    return Some(Ev::Resync { key });
                }
                Some(Ev::Alive { key, role, sat, alive: true })
            }
            other => Some(other),
        }
    }

    fn due(&mut self, now: Instant) -> Option<Ev> {
        let key = self.held.iter().find(|(_, (_, at))| at.is_some_and(|t| t <= now)).map(|(k, _)| k.clone())?;
        self.held.remove(&key).map(|(ev, _)| ev)
    }

    /// A return handed on; `AGAIN_AFTER_S` later the bus's return is said again (the agent
    /// then sends every step it keeps once more). One series for a burst of returns (a
    /// failover brings every token back at once): a later return moves it (`Node._echo`).
    fn echo(&mut self, ev: Ev) -> Ev {
        if matches!(ev, Ev::Bus { alive: true } | Ev::Resync { .. }) {
            let now = Instant::now();
            self.agains = AGAIN_AFTER_S.iter().map(|d| now + Duration::from_secs_f64(*d)).collect();
        }
        ev
    }

    fn next_wake(&self) -> Option<Instant> {
        let mut t = self.held.values().filter_map(|(_, at)| *at).min();
        if let Some(&at) = self.agains.first() {
            t = Some(t.map_or(at, |x| x.min(at)));
        }
        if let Some(d) = self.bus_down_since {
            let lost = d + Duration::from_secs_f64(self.limits.bus_lost_after_s);
            t = Some(t.map_or(lost, |x| x.min(lost)));
        }
        t
    }

    /// The next event, or None when `timeout` passes (or the agent is asked to stop).
    /// `Err` once no router has been reachable for `bus_lost_after_s`.
    pub fn next_event(&mut self, timeout: Option<Duration>) -> Result<Option<Ev>, Broken> {
        let deadline = timeout.map(|t| Instant::now() + t);
        loop {
            let now = Instant::now();
            if let Some(ev) = self.due(now) {
                return Ok(Some(ev));
            }
            if self.agains.first().is_some_and(|&at| at <= now) {
                self.agains.remove(0);
                return Ok(Some(Ev::Bus { alive: true }));
            }
            if let Some(d) = self.bus_down_since {
                let gone = now.duration_since(d).as_secs_f64();
                if gone >= self.limits.bus_lost_after_s {
                    return Err(Broken {
                        code: EXIT_BUS_LOST,
                        why: format!("no Zenoh router reachable for {gone:.1} s: the run is broken"),
                    });
                }
            }
            if self.stop.load(Ordering::SeqCst) {
                return Ok(None);
            }
            // Wake at least every 100 ms to notice a stop request (a signal).
            let mut until = now + Duration::from_millis(100);
            if let Some(d) = deadline {
                until = until.min(d);
            }
            if let Some(w) = self.next_wake() {
                until = until.min(w.max(now));
            }
            match self.rx.recv_timeout(until.saturating_duration_since(now)) {
                Ok(ev) => {
                    if let Some(ev) = self.filter(ev) {
                        return Ok(Some(self.echo(ev)));
                    }
                }
                Err(RecvTimeoutError::Timeout) => {
                    if deadline.is_some_and(|d| Instant::now() >= d) {
                        return Ok(None);
                    }
                }
                Err(RecvTimeoutError::Disconnected) => return Ok(None),
            }
        }
    }

    /// Whether the recorder still runs: then keep the session open until its token goes
    /// (it drops it once it holds every live agent's final estimate), at most `timeout`.
    pub fn linger_while_recording(&self, timeout: Duration) {
        let key = format!("{}/alive/recorder/*", self.root);
        let (gtx, grx) = mpsc::channel::<()>();
        let sub = self
            .session
            .liveliness()
            .declare_subscriber(&key)
            .callback(move |s| {
                if s.kind() == SampleKind::Delete {
                    let _ = gtx.send(());
                }
            })
            .wait();
        let present = match self.session.liveliness().get(&key).timeout(timeout.min(Duration::from_secs(5))).wait() {
            Ok(replies) => {
                let mut any = false;
                while let Ok(r) = replies.recv() {
                    any |= r.result().is_ok();
                }
                any
            }
            Err(e) => {
                log::warn(&format!("liveliness query {key}: {e}"));
                false
            }
        };
        if present && sub.is_ok() {
            let deadline = Instant::now() + timeout;
            loop {
                if self.stop.load(Ordering::SeqCst) {
                    break;
                }
                match grx.recv_timeout(Duration::from_millis(100)) {
                    Ok(()) => break,
                    Err(_) if Instant::now() >= deadline => {
                        log::warn(&format!(
                            "the recorder was still running {:.0} s after the run ended; leaving anyway",
                            timeout.as_secs_f64()
                        ));
                        break;
                    }
                    Err(_) => {}
                }
            }
        }
        drop(sub);
    }

    /// Undeclare everything and close the session.
    pub fn close(mut self) {
        self.watcher_stop.store(true, Ordering::SeqCst);
        if let Some(w) = self.watcher.take() {
            let _ = w.join();
        }
        if let Some(t) = self.token.take() {
            let _ = t.undeclare().wait();
        }
        for s in self.subs.drain(..).chain(self.lsubs.drain(..)) {
            let _ = s.undeclare().wait();
        }
        for q in self.queryables.drain(..) {
            let _ = q.undeclare().wait();
        }
        if let Err(e) = self.session.close().wait() {
            log::warn(&format!("closing the session: {e}"));
        }
    }
}

/// A sample as an event (`Node._decode`): the key parsed (this run, a satellite of the
/// swarm), the payload decoded and checked, then checked against the key.
fn decode_sample(key: &str, payload: &[u8], run: &str, n: usize) -> Result<Ev, Refused> {
    let bad = |r: String| Refused { reason: r, key_mismatch: false };
    let (krun, kind, sat) = checks::parse_key(key).ok_or_else(|| bad(format!("unexpected key {key:?}")))?;
    if krun != run {
        return Err(bad(format!("run id {krun:?} is not this swarm's ({run:?})")));
    }
    if let Some(s) = sat {
        if s as usize >= n {
            return Err(bad(format!("unknown satellite {s} in the key (swarm has 0..{})", n - 1)));
        }
    }
    let msg = checks::decode(&kind, payload, n)?;
    if msg.run() != run {
        return Err(bad(format!("message run id {:?} is not this swarm's", msg.run())));
    }
    checks::check_key(key, &kind, sat, &msg)?;
    Ok(Ev::Msg { msg: Box::new(msg) })
}

#[cfg(test)]
mod tests {
    use super::zenoh_config;

    #[test]
    fn a_ca_is_used_over_tcp_and_a_tls_endpoint_is_refused() {
        let dir = std::env::temp_dir().join(format!("swarm-rust-agent-cred-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cred = dir.join("agent-1.json");
        std::fs::write(&cred, r#"{"user": "agent-1", "password": "pw", "ca": "ca.pem"}"#).unwrap();
        let c = cred.to_str().unwrap();
        assert!(zenoh_config(&["tcp/127.0.0.1:7447".to_string()], Some(c)).is_ok());
        let e = zenoh_config(&["tcp/a:1".to_string(), "tls/router:7449".to_string()], Some(c)).unwrap_err();
        assert!(e.contains("endpoint tls/router:7449"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
