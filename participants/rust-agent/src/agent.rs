//! One satellite's side of the lockstep protocol (`sat_agent/protocol.py`, the reference),
//! with the ideal radio. Step k:
//!
//! 1. wait for its own sensors and camera delivery of k (when the clock lists it live);
//! 2. predict to k, measure its detections, transmit them with its estimator's message as
//!    one batch (`meas/<i>`: an empty one too) to the radio, which the world emulates;
//! 3. wait for the radio's batches of k (`batches`: every live peer's, one message; or,
//!    with `derived.radio_peers`, its radio peers' on its own `batches/<i>`);
//! 4. run the `ci` step and publish the estimate (`est/<i>`) and a health report
//!    (`health/<i>`).
//!
//! Start: the world's prior (`init/<i>`); a restarted agent (or one that comes when the run
//! is under way) starts cold from its own star tracker and GPS (ci has no warm rejoin).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use prost::Message;

use crate::bus::{self, Broken, Ev, Node};
use crate::checks::Msg;
use crate::ci::{Ci, CiState, Received, StepInputs, StepReport, View};
use crate::filter::{Absolute, Est, Rel};
use crate::linalg::Mat;
use crate::log;
use crate::pb::{self, CameraOutput, Clock, EstimatorMessage, Fault, FullEstimate, Health, MeasBatch, Sensors, StepBatches};
use crate::quat::V3;
use crate::scenario::Scenario;
use crate::sensors::{self, Detection};
use crate::streams::{message_dropped, DROP_BATCH, DROP_ESTIMATE};

/// How the agent's run ends before its natural end.
#[derive(Debug)]
pub enum Exit {
    /// SIGTERM / SIGINT: leave cleanly (status 0).
    Stop,
    /// The run is broken (bus lost: 3, world gone: 4) or cannot start (1).
    Broken(Broken),
}

impl From<Broken> for Exit {
    fn from(b: Broken) -> Exit {
        Exit::Broken(b)
    }
}

type Out = (String, Vec<u8>);

/// What the agent knows (the part `handle` updates).
pub struct State {
    pub sc: Scenario,
    pub i: usize,
    pub name: String,
    pub run: String,
    root: String,
    host: String,
    pub restart: bool,
    pub cold: bool,
    pub ci: Ci,
    camera_ok: [bool; 6],
    drop_rate: f64,
    clocks: BTreeMap<u64, Clock>,
    sensors: BTreeMap<u64, Sensors>,
    cams: BTreeMap<u64, CameraOutput>,
    radio: BTreeMap<u64, Vec<StepBatches>>,
    radio_obs: BTreeMap<u64, BTreeSet<u32>>,
    // links.enabled: the steps whose delivery (rx/<i>) came, and the batches not yet used.
    rx_steps: BTreeSet<u64>,
    rx_items: Vec<(u64, MeasBatch)>, // with their delivery's step
    // The first step this process flies: what the radio brought of earlier steps was the
    // satellite's previous process's (`flies_from`).
    first_step: u64,
    peers_alive: BTreeSet<u32>,
    sent_k: i64,
    batches_missing: u64,
    batches_late: u64,
    missing: Vec<u32>,
    pub last_step: i64,
    pub done: bool,
    world_seen: bool,
    sends: Vec<Out>,
    // The messages of the steps before the current one, oldest first: the last
    // `recorder_max_lag_steps + 1` (with `sends`, `recorder_max_lag_steps + 2` steps), for a
    // recorder that comes back up to that many steps behind (`swarmrt.protocol.Outbox`).
    earlier: VecDeque<Vec<Out>>,
    // Fault commands carried out (their bytes), each with the report it made: the world sends
    // its last steps' commands again when the bus or the recorder comes back, and says a
    // command again while its outcome does not show; a command is carried out once, and its
    // report sent again (it may have been lost on its way: sat_agent/protocol.py `_on_fault`).
    commands_seen: BTreeMap<Vec<u8>, Vec<Out>>,
}

impl State {
    pub fn new(sc: Scenario, i: usize, run: &str, ci: Ci, restart: bool) -> State {
        State {
            i,
            name: format!("agent-{i}"),
            run: run.to_string(),
            root: format!("swarm/{run}"),
            host: hostname(),
            restart,
            cold: false,
            ci,
            camera_ok: [true; 6],
            drop_rate: 0.0,
            clocks: BTreeMap::new(),
            sensors: BTreeMap::new(),
            cams: BTreeMap::new(),
            radio: BTreeMap::new(),
            radio_obs: BTreeMap::new(),
            rx_steps: BTreeSet::new(),
            rx_items: vec![],
            first_step: 0,
            peers_alive: BTreeSet::new(),
            sent_k: -1,
            batches_missing: 0,
            batches_late: 0,
            missing: vec![],
            last_step: -1,
            done: false,
            world_seen: false,
            sends: vec![],
            earlier: VecDeque::new(),
            commands_seen: BTreeMap::new(),
            sc,
        }
    }

    fn key(&self, tail: &str) -> String {
        format!("{}/{tail}", self.root)
    }

    /// An event from the bus; returns what to publish in answer.
    pub fn handle(&mut self, ev: Ev) -> Result<Vec<Out>, Broken> {
        match ev {
            // The bus came back, or a token we held came back: send this step's messages
            // (and the last step's) again; receivers drop what they already have.
            Ev::Bus { alive: true } | Ev::Resync { .. } => {
                // Every step kept when our own bus or the recorder came back (the recorder may
                // be up to recorder_max_lag_steps behind); the previous and current step when
                // another peer's token did (no step ends while a peer's token is held).
                let all = match &ev {
                    Ev::Resync { key } => {
                        log::debug(&format!("{key} came back within the hold: sending the step's messages again"));
                        key.contains("/alive/recorder/")
                    }
                    _ => true,
                };
                let skip = if all { 0 } else { self.earlier.len().saturating_sub(1) };
                return Ok(self.earlier.iter().skip(skip).flatten().chain(&self.sends).cloned().collect());
            }
            Ev::Held { key } => log::debug(&format!("{key} gone: held for the grace")),
            Ev::Bus { alive: false } => {}
            Ev::Alive { role, sat, alive, .. } => {
                if role == "world" {
                    if alive {
                        self.world_seen = true;
                    } else if self.world_seen && !self.done {
                        return Err(Broken {
                            code: bus::EXIT_WORLD_LOST,
                            why: format!("the world is gone before the end of the run (last step {})", self.last_step),
                        });
                    }
                } else if role == "agent" {
                    if let Some(s) = sat.filter(|&s| s as usize != self.i) {
                        if alive {
                            self.peers_alive.insert(s);
                        } else {
                            self.peers_alive.remove(&s);
                        }
                    }
                }
            }
            Ev::Msg { msg, .. } => match *msg {
                Msg::Clock(c) => {
                    if c.done {
                        self.done = true;
                    } else {
                        self.clocks.insert(c.k, c);
                    }
                }
                Msg::Sensors(s) => {
                    self.sensors.insert(s.k, s);
                }
                Msg::Cam(c) => {
                    self.cams.insert(c.k, c);
                }
                Msg::Batches(b) => self.on_batches(b),
                Msg::Rx(d) => self.on_delivery(d),
                Msg::Fault(f) => return Ok(self.on_fault(f)),
                Msg::FullEst(_) => {}
            },
        }
        Ok(vec![])
    }

    fn on_batches(&mut self, b: StepBatches) {
        let k = b.k;
        if k < self.first_step {
            return; // the previous process's (sent again after the bus came back)
        }
        let obs: BTreeSet<u32> = b.observers.iter().copied().filter(|&o| o as usize != self.i).collect();
        let seen = self.radio_obs.entry(k).or_default();
        if obs.is_subset(seen) && (!obs.is_empty() || self.radio.contains_key(&k)) {
            return; // a copy sent again after the bus came back
        }
        let new = obs.difference(seen).count() as u64;
        seen.extend(obs);
        if ki(k) <= self.last_step {
            self.batches_late += new; // its step is done: too late to use
        } else {
            self.radio.entry(k).or_default().push(b);
        }
    }

    /// The radio with links: the world's delivery of step k (once per step, an empty one
    /// too), each item a peer's batch; one of an earlier step is late (`_linked_radio`).
    fn on_delivery(&mut self, d: pb::Delivery) {
        if self.rx_steps.contains(&d.k) || ki(d.k) < self.last_step - 1 || d.k < self.first_step {
            return; // a delivery sent again after the bus came back, or the previous process's
        }
        self.rx_steps.insert(d.k);
        let (i, k) = (self.i, d.k);
        self.rx_items.extend(d.items.into_iter().filter_map(|it| it.batch).filter(|b| b.observer as usize != i).map(|b| (k, b)));
    }

    /// This process flies from step k on: what came of earlier steps' radio is forgotten. A
    /// restarted agent hears the world's last steps sent again whenever the bus comes back;
    /// the deliveries of steps before it flies were its previous process's, and whether they
    /// reach this one depends on timing (sat_agent/protocol.py `_flies_from`).
    fn flies_from(&mut self, k: u64) {
        self.first_step = k;
        self.rx_steps.retain(|&s| s >= k);
        self.rx_items.retain(|(s, _)| *s >= k);
        self.radio.retain(|&s, _| s >= k);
        self.radio_obs.retain(|&s, _| s >= k);
    }

    fn on_fault(&mut self, f: Fault) -> Vec<Out> {
        if f.phase != "command" || f.target != Some(self.i as u32) {
            return vec![];
        }
        let key = f.encode_to_vec();
        if let Some(report) = self.commands_seen.get(&key) {
            return report.clone(); // the same command again: carried out already, its report said again
        }
        let report = self.carry_out(f);
        self.commands_seen.insert(key, report.clone());
        report
    }

    fn carry_out(&mut self, f: Fault) -> Vec<Out> {
        match f.action.as_str() {
            "camera" => {
                // In effect from the step the world carries it out at: its camera deliveries
                // say so from then on (`cameras_off`), and they alone set `camera_ok`; a
                // command that reaches this process before or after a health report is sent
                // must not change what the report of that step says (sat_agent/protocol.py:
                // `_cameras`; issue 35).
                if let (Some(c), Some(state)) = (f.camera, &f.state) {
                    log::info(&format!("camera {c} {state} (step {})", f.k));
                }
                vec![]
            }
            "drop" => {
                self.drop_rate = f.rate.unwrap_or(0.0);
                let first = self.sent_k.saturating_add(1) as u64; // the first batch it applies to
                log::info(&format!("dropping {:.0}% of outgoing messages from step {first}", 100.0 * self.drop_rate));
                // The report says from which step: the world's radio then knows which
                // batches will never come (it makes the same draws).
                let done = Fault { phase: "done".into(), sender: self.name.clone(), k: first, ..f };
                let out = (self.key(&format!("fault/{}", self.name)), done.encode_to_vec());
                // Kept with the step's messages, sent again when the bus or the recorder comes
                // back (`Outbox.keep`): a report put while the recorder was away is not lost.
                self.sends.push(out.clone());
                vec![out]
            }
            _ => vec![],
        }
    }

    fn dropped(&self, k: u64, what: u64) -> bool {
        message_dropped(self.sc.seed, self.i as u64, k, what, self.drop_rate)
    }

    fn health(&self, k: u64, t: f64, counters: &bus::Counters) -> Health {
        Health {
            schema_version: 1,
            run: self.run.clone(),
            sender: self.name.clone(),
            k,
            t_s: t,
            sat: self.i as u32,
            camera_ok: self.camera_ok.to_vec(),
            malformed: counters.malformed.load(Ordering::SeqCst),
            batches_missing: self.batches_missing,
            batches_late: self.batches_late,
            drop_rate: self.drop_rate,
            host: self.host.clone(),
            key_mismatch: counters.key_mismatch.load(Ordering::SeqCst),
        }
    }

    fn prune(&mut self, k: u64) {
        let keep = |s: &u64| s.saturating_add(2) >= k;
        self.sensors.retain(|s, _| keep(s));
        self.cams.retain(|s, _| keep(s));
        self.radio.retain(|s, _| keep(s));
        self.radio_obs.retain(|s, _| keep(s));
        self.rx_steps.retain(|s| keep(s));
        self.clocks.retain(|s, _| keep(s));
    }
}

/// A step number as the signed counters compare it (a step beyond i64 is the far future).
fn ki(k: u64) -> i64 {
    i64::try_from(k).unwrap_or(i64::MAX)
}

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname").map(|s| s.trim().to_string()).unwrap_or_default()
}

fn gyro_of(s: &Sensors) -> Option<V3> {
    (s.gyro_rate_b_rad_s.len() == 3).then(|| [s.gyro_rate_b_rad_s[0], s.gyro_rate_b_rad_s[1], s.gyro_rate_b_rad_s[2]])
}

fn absolute_of(s: &Sensors) -> Option<Absolute> {
    if s.q_bi_star.is_empty() && s.r_h_gps_m.is_empty() {
        return None;
    }
    Some(Absolute {
        q: (s.q_bi_star.len() == 4).then(|| [s.q_bi_star[0], s.q_bi_star[1], s.q_bi_star[2], s.q_bi_star[3]]),
        r: (s.r_h_gps_m.len() == 3).then(|| [s.r_h_gps_m[0], s.r_h_gps_m[1], s.r_h_gps_m[2]]),
        sigma_att: s.sigma_star_rad,
        sigma_pos: s.sigma_gps_m,
    })
}

fn matrix(shape: &[usize], data: Vec<f64>) -> pb::Matrix {
    pb::Matrix { shape: shape.iter().map(|&x| x as u32).collect(), data }
}

fn ci_state_msg(s: &CiState) -> EstimatorMessage {
    EstimatorMessage {
        kind: "ci".into(),
        version: 1,
        body: Some(pb::estimator_message::Body::Ci(pb::CiState {
            q_bi: s.q.to_vec(),
            omega_bi_b_rad_s: s.w.to_vec(),
            r_h_m: s.r.to_vec(),
            v_h_m_s: s.v.to_vec(),
            p_pose: Some(matrix(&[6, 6], s.p_pose.d.clone())),
        })),
    }
}

/// A peer's estimator message as a `CiState` (None: another estimator's or layout's).
fn ci_state(e: &EstimatorMessage) -> Option<CiState> {
    if e.kind != "ci" || e.version != 1 {
        return None;
    }
    match &e.body {
        Some(pb::estimator_message::Body::Ci(c)) => Some(CiState {
            q: [c.q_bi[0], c.q_bi[1], c.q_bi[2], c.q_bi[3]],
            w: [c.omega_bi_b_rad_s[0], c.omega_bi_b_rad_s[1], c.omega_bi_b_rad_s[2]],
            r: [c.r_h_m[0], c.r_h_m[1], c.r_h_m[2]],
            v: [c.v_h_m_s[0], c.v_h_m_s[1], c.v_h_m_s[2]],
            p_pose: Mat::from_rows(6, 6, &c.p_pose.as_ref()?.data),
        }),
        _ => None,
    }
}

/// What the ideal radio's message carries of each observer but `skip` (`received_from_step`).
fn received_from_step(m: &StepBatches, skip: usize) -> Vec<Received> {
    let mut out = vec![];
    let mut start = 0usize;
    let r_bi = m.r_bi.as_ref().map(|x| &x.data[..]).unwrap_or(&[]);
    for (idx, (&o, &c)) in m.observers.iter().zip(&m.counts).enumerate() {
        let (a, b) = (start, start + c as usize);
        start = b;
        if o as usize == skip {
            continue;
        }
        let meas = rel_rows(o as usize, &m.target, &m.q_bj_bi, &m.r_ij_bi_m, r_bi, a..b);
        let payload = m.estimators.get(idx).filter(|e| !e.kind.is_empty()).and_then(ci_state);
        out.push(Received { sender: o as usize, step: m.k, meas, payload });
    }
    out
}

/// One batch the radio delivered (links), with its estimator's message (`received_from_batches`).
fn received_from_batch(b: &MeasBatch) -> Received {
    let r_bi = b.r_bi.as_ref().map(|x| &x.data[..]).unwrap_or(&[]);
    let meas = rel_rows(b.observer as usize, &b.target, &b.q_bj_bi, &b.r_ij_bi_m, r_bi, 0..b.target.len());
    let payload = b.estimator.as_ref().filter(|e| !e.kind.is_empty()).and_then(ci_state);
    Received { sender: b.observer as usize, step: b.k, meas, payload }
}

/// Rows `rows` of one observer's measurement columns (a batch's, or a run of a step's
/// batches laid end to end) as measurements: the one row builder of both radio paths.
fn rel_rows(observer: usize, target: &[u32], q_bj_bi: &[f64], r_ij_bi_m: &[f64], r_bi: &[f64], rows: std::ops::Range<usize>) -> Vec<Rel> {
    rows.map(|r| Rel {
        observer,
        target: target[r] as usize,
        q: std::array::from_fn(|x| q_bj_bi[4 * r + x]),
        r: std::array::from_fn(|x| r_ij_bi_m[3 * r + x]),
        cov: std::array::from_fn(|x| std::array::from_fn(|y| r_bi[36 * r + 6 * x + y])),
    })
    .collect()
}

fn view_msg(v: &View, st: &State, phase: &str) -> pb::Estimate {
    let m = v.ids.len();
    pb::Estimate {
        schema_version: 1,
        run: st.run.clone(),
        sender: st.name.clone(),
        k: v.step,
        t_s: v.t,
        own: v.own as u32,
        phase: phase.into(),
        q_bi: v.q.iter().flatten().copied().collect(),
        omega_bi_b_rad_s: v.w.iter().flatten().copied().collect(),
        r_h_m: v.r.iter().flatten().copied().collect(),
        v_h_m_s: v.v.iter().flatten().copied().collect(),
        bias_b_rad_s: v.bias.to_vec(),
        p_pose: Some(matrix(&[m, 6, 6], v.p_pose.iter().flat_map(|p| p.d.iter().copied()).collect())),
        p_diag: Some(matrix(&[12 * m], v.p_diag.clone())),
        p_rel_pose: Some(matrix(&[m, 6, 6], v.p_rel_pose.iter().flat_map(|p| p.d.iter().copied()).collect())),
        ids: v.ids.iter().map(|&x| x as u32).collect(),
        estimator: "ci".into(),
        ..Default::default()
    }
}

/// The agent: its knowledge and its bus.
pub struct Agent {
    pub st: State,
    pub node: Node,
}

impl Agent {
    fn put(&mut self, key: String, bytes: Vec<u8>, keep: bool) {
        if let Err(e) = self.node.session_put(&key, bytes.clone()) {
            log::warn(&format!("put {key}: {e}"));
        }
        if keep {
            self.st.sends.push((key, bytes));
        }
    }

    fn send<M: Message>(&mut self, tail: &str, msg: &M) {
        let key = self.st.key(tail);
        self.put(key, msg.encode_to_vec(), true);
    }

    fn on_event(&mut self, ev: Ev) -> Result<(), Exit> {
        for (key, bytes) in self.st.handle(ev)? {
            self.put(key, bytes, false);
        }
        Ok(())
    }

    /// Hand events to the state until `cond` holds (true) or `timeout_s` passes (false);
    /// the timeout counts from the bus's return while it is down (`Node.wait_for`).
    fn wait_for(&mut self, cond: impl Fn(&State) -> bool, timeout_s: f64) -> Result<bool, Exit> {
        let timeout = Duration::from_secs_f64(timeout_s.max(0.0));
        let mut deadline = Instant::now() + timeout;
        let mut epoch = self.node.epoch;
        while !cond(&self.st) {
            if self.node.stop.load(Ordering::SeqCst) {
                return Err(Exit::Stop);
            }
            let now = Instant::now();
            if self.node.bus_down_since.is_some() || self.node.epoch != epoch {
                deadline = deadline.max(now + timeout);
                epoch = self.node.epoch;
            }
            let remaining = deadline.saturating_duration_since(now);
            if remaining.is_zero() {
                // Take in what has already arrived before giving up.
                match self.node.next_event(Some(Duration::ZERO))? {
                    None => return Ok(false),
                    Some(ev) => self.on_event(ev)?,
                }
                continue;
            }
            if let Some(ev) = self.node.next_event(Some(remaining))? {
                self.on_event(ev)?;
            }
        }
        Ok(true)
    }

    /// The whole run: start, then every step until the world's clock says done.
    pub fn run(&mut self) -> Result<(), Exit> {
        self.initialise()?;
        while !self.st.done {
            let last = self.st.last_step;
            if let Some(&k) = self.st.clocks.keys().rev().find(|&&s| ki(s) > last) {
                // The newest step: in lockstep there is only ever one ahead, unless this
                // agent fell behind; then it predicts across the gap and rejoins the present.
                self.st.clocks.retain(|&s, _| s >= k);
                self.step(k)?;
                continue;
            }
            self.wait_for(|st| st.done || st.clocks.keys().any(|&s| ki(s) > st.last_step), 0.5)?;
        }
        log::info(&format!(
            "done at step {}; {} malformed ({} on a key not their sender's), {} missing, {} late batches",
            self.st.last_step,
            self.node.counters.malformed.load(Ordering::SeqCst),
            self.node.counters.key_mismatch.load(Ordering::SeqCst),
            self.st.batches_missing,
            self.st.batches_late
        ));
        Ok(())
    }

    fn initialise(&mut self) -> Result<(), Exit> {
        const INIT_RETRY_S: f64 = 0.2;
        let i = self.st.i;
        let startup = self.st.sc.emulator.startup_timeout_s;
        if !self.st.restart {
            let deadline = Instant::now() + Duration::from_secs_f64(startup);
            while !self.st.ci.started() && Instant::now() < deadline {
                if self.node.stop.load(Ordering::SeqCst) {
                    return Err(Exit::Stop);
                }
                let key = self.st.key(&format!("init/{i}"));
                if let Some(Msg::FullEst(m)) = self.node.query(&key, "full_est", Duration::from_secs(2)) {
                    let prior = prior_of(&m, i).map_err(|why| Exit::Broken(Broken { code: 1, why }))?;
                    self.st.last_step = ki(m.k).saturating_sub(1);
                    self.st.flies_from(m.k);
                    self.st.ci.start(prior, true);
                    break;
                }
                // No prior yet (the world's queryable not declared, so the query came back at
                // once): ask again after a pause, not in a spin of thousands of queries.
                self.wait_for(|st| !st.clocks.is_empty(), INIT_RETRY_S)?;
                if !self.st.clocks.is_empty() {
                    // The world serves priors only before the run starts: we are late.
                    log::info("the run is under way; starting cold");
                    self.st.restart = true;
                    break;
                }
            }
            if !self.st.ci.started() && !self.st.restart {
                return Err(Exit::Broken(Broken { code: 1, why: format!("agent {i}: no prior from the world within {startup} s") }));
            }
            if self.st.ci.started() {
                log::info(&format!("initialised from the world's prior at step {}", self.st.ci.step_index()));
            }
        }
        if self.st.restart {
            // Nothing a peer holds can restart a ci estimator: it starts from its own
            // sensors at its next step.
            // Its health report says it is here, so that the world counts it live again and
            // sends it its sensors.
            self.st.cold = true;
            log::info("restarted: estimator 'ci' starts cold at the next step");
            let k_now = self.st.clocks.keys().next_back().copied().unwrap_or(0);
            let t_now = self.st.clocks.get(&k_now).map_or(0.0, |c| c.t_s);
            let h = self.st.health(k_now, t_now, &self.node.counters);
            self.send(&format!("health/{i}"), &h);
            return Ok(());
        }
        let msg = view_msg(&self.st.ci.view(), &self.st, "prior");
        self.send(&format!("est/{i}"), &msg);
        Ok(())
    }

    fn step(&mut self, k: u64) -> Result<(), Exit> {
        let i = self.st.i;
        let done = std::mem::take(&mut self.st.sends);
        self.st.earlier.push_back(done);
        while self.st.earlier.len() > self.st.sc.emulator.recorder_max_lag_steps + 1 {
            self.st.earlier.pop_front();
        }
        let clock = self.st.clocks.remove(&k).expect("the step's clock");
        let t = clock.t_s;
        if !self.st.ci.started() && !clock.live_agents.contains(&(i as u32)) {
            // Restarted cold, and this clock went out before the world counted us live again
            // (our health report crossed it): no sensors of this step will come to start
            // from. Say again that we are here and start at a step that lists us.
            let h = self.st.health(k, t, &self.node.counters);
            self.send(&format!("health/{i}"), &h);
            return Ok(());
        }
        if !self.st.ci.started() {
            self.st.flies_from(k); // a cold start: from the first step that lists us live
        }
        let timeout = self.st.sc.emulator.step_timeout_s;
        if clock.live_agents.contains(&(i as u32)) {
            self.wait_for(|st| st.sensors.contains_key(&k) && st.cams.contains_key(&k), timeout)?;
        }
        let sens = self.st.sensors.remove(&k);
        let gyro = sens.as_ref().and_then(gyro_of);
        let (t0, c0) = (Instant::now(), bus::thread_cpu_ns());
        if self.st.ci.started() {
            let sensors = &mut self.st.sensors;
            self.st.ci.coast_to(k, |s| sensors.remove(&s).as_ref().and_then(gyro_of));
            self.st.ci.predict(k, gyro.as_ref());
        }
        let ms_pred = t0.elapsed().as_secs_f64() * 1e3;
        let cpu_pred = bus::thread_cpu_ns().saturating_sub(c0);
        // Its own measurements: the detections of the cameras it believes work.
        let delivery = self.st.cams.remove(&k);
        if let Some(c) = &delivery {
            // The step's delivery says which cameras are off (the world's state at step k):
            // what the satellite measures with and reports in its health of k.
            self.st.camera_ok = [true; 6];
            for &off in c.cameras_off.iter().filter(|&&off| off < 6) {
                self.st.camera_ok[off as usize] = false;
            }
        }
        let dets: Vec<Detection> = match delivery {
            Some(c) => c
                .detections
                .iter()
                .filter(|d| self.st.camera_ok[d.camera as usize])
                .map(|d| Detection {
                    target: d.target as usize,
                    camera: d.camera,
                    q: [d.q_bj_bi[0], d.q_bj_bi[1], d.q_bj_bi[2], d.q_bj_bi[3]],
                    r: [d.r_ij_bi_m[0], d.r_ij_bi_m[1], d.r_ij_bi_m[2]],
                })
                .collect(),
            None => vec![],
        };
        let (rel_own, cameras) = sensors::measure(&self.st.sc.relative, i, &dets);
        let message = if self.st.ci.started() {
            Some(ci_state_msg(&self.st.ci.transmit(k).map_err(|why| Exit::Broken(Broken { code: 1, why }))?))
        } else {
            None
        };
        let mut batch = MeasBatch {
            schema_version: 1,
            run: String::new(),
            sender: self.st.name.clone(),
            k,
            t_s: t,
            observer: i as u32,
            target: rel_own.iter().map(|m| m.target as u32).collect(),
            camera: cameras,
            q_bj_bi: rel_own.iter().flat_map(|m| m.q).collect(),
            r_ij_bi_m: rel_own.iter().flat_map(|m| m.r).collect(),
            r_bi: Some(matrix(&[rel_own.len(), 6, 6], rel_own.iter().flat_map(|m| m.cov.into_iter().flatten()).collect())),
            estimator: message,
        };
        // The bytes it takes on the radio: as encoded, less the run id (radio_bytes).
        let bytes_sent = batch.encoded_len() as u64;
        batch.run = self.st.run.clone();
        if !self.st.dropped(k, DROP_BATCH) {
            self.send(&format!("meas/{i}"), &batch);
        }
        self.st.sent_k = ki(k);
        let received =
            if self.st.sc.links_enabled { self.linked_radio(k, &clock, timeout)? } else { self.ideal_radio(k, &clock, timeout)? };
        let inputs = StepInputs { step: k, t, gyro, absolute: sens.as_ref().and_then(absolute_of), own: rel_own, received };
        let (t1, c1) = (Instant::now(), bus::thread_cpu_ns());
        let report: Option<StepReport>;
        if !self.st.ci.started() {
            let s = &self.st.sc.initial_sigma;
            let (a, r, b, p, v, vm) = (s.att_rad, s.rate_rad_s, s.bias_rad_s, s.pos_m, s.vel_m_s, self.st.sc.velocity_max_m_s);
            if !self.st.ci.cold_start(&inputs, a, r, b, p, v, vm) {
                // Nothing of its own to start from (no star tracker and GPS reading): an
                // estimator without warm rejoin cannot come back on this satellite.
                return Err(Exit::Broken(Broken {
                    code: 1,
                    why: format!("agent {i}: estimator 'ci' cannot restart cold without its own star tracker and GPS readings (step {k})"),
                }));
            }
            log::info(&format!("started cold at step {k}"));
            report = None;
        } else {
            match self.st.ci.step(&inputs) {
                Ok(r) => report = Some(r),
                Err(why) => {
                    // The Python agent would die here; this one says so and carries on
                    // with its prior as the step's estimate.
                    log::error(&format!("step {k}: {why}"));
                    report = None;
                }
            }
        }
        self.st.last_step = ki(k);
        if let Some(r) = &report {
            if log::debug_enabled() {
                let w = self.st.ci.last_omega.take().map_or("none".to_string(), |w| format!("{w:.17e}"));
                log::debug(&format!("step {k}: omega {w} gate {}/{} nis {:.17e}", r.gate_accepted, r.gate_rejected, r.nis));
            }
        }
        let ms = t1.elapsed().as_secs_f64() * 1e3 + ms_pred;
        let cpu = bus::thread_cpu_ns().saturating_sub(c1) + cpu_pred;
        let codec_ns = self.node.counters.codec_ns.swap(0, Ordering::Relaxed);
        let mut msg = view_msg(&self.st.ci.view(), &self.st, "posterior");
        if let Some(r) = &report {
            msg.gate_accepted = r.gate_accepted;
            msg.gate_rejected = r.gate_rejected;
            msg.nis = if r.nis.is_finite() { r.nis } else { 0.0 };
            msg.nis_dof = r.nis_dof;
            msg.iterations = r.iterations;
            msg.late_used = r.late_used;
            msg.late_dropped = r.late_dropped;
            msg.replayed_steps = r.replayed_steps;
        }
        msg.step_ms = ms;
        msg.step_cpu_ms = cpu as f64 / 1e6;
        msg.codec_cpu_ms = codec_ns as f64 / 1e6;
        msg.batches_used =
            inputs.received.iter().filter(|r| r.step == k).map(|r| r.sender as u32).collect::<BTreeSet<_>>().into_iter().collect();
        msg.batches_missing = self.st.missing.clone();
        msg.batches_late = self.st.batches_late as u32;
        msg.bytes_sent = bytes_sent;
        if !self.st.dropped(k, DROP_ESTIMATE) {
            self.send(&format!("est/{i}"), &msg);
        }
        let h = self.st.health(k, t, &self.node.counters);
        self.send(&format!("health/{i}"), &h);
        self.st.prune(k);
        Ok(())
    }

    /// The radio with links (lockstep): what the world's link model delivered by t_k —
    /// on-time batches of k and late ones of earlier steps, which the ci estimator drops and
    /// counts (`filter.late: drop`, the only setting this agent flies with links).
    fn linked_radio(&mut self, k: u64, clock: &Clock, timeout: f64) -> Result<Vec<Received>, Exit> {
        self.st.missing = vec![];
        if clock.live_agents.contains(&(self.st.i as u32)) {
            self.wait_for(|st| st.rx_steps.contains(&k), timeout)?;
        }
        let (now, later): (Vec<(u64, MeasBatch)>, Vec<(u64, MeasBatch)>) =
            std::mem::take(&mut self.st.rx_items).into_iter().partition(|(_, b)| b.k <= k);
        self.st.rx_items = later;
        let now: Vec<MeasBatch> = now.into_iter().map(|(_, b)| b).collect();
        self.st.batches_late += now.iter().filter(|b| b.k < k).count() as u64;
        let mut received: Vec<Received> = now.iter().map(received_from_batch).collect();
        received.sort_by_key(|r| (r.step, r.sender));
        Ok(received)
    }

    /// The ideal radio in lockstep: one message with every live peer's batch of k (or, with
    /// `derived.radio_peers`, with its live radio peers', on its own `batches/<i>`).
    fn ideal_radio(&mut self, k: u64, clock: &Clock, timeout: f64) -> Result<Vec<Received>, Exit> {
        let i = self.st.i;
        let peers = self.st.sc.radio_peers.as_ref().map(|rp| &rp[i]);
        let expected: Vec<u32> =
            clock.live_agents.iter().copied().filter(|&j| j as usize != i && peers.is_none_or(|p| p.contains(&j))).collect();
        self.wait_for(|st| st.radio.contains_key(&k), timeout)?;
        let got = self.st.radio_obs.get(&k).cloned().unwrap_or_default();
        self.st.missing = expected.into_iter().filter(|j| !got.contains(j)).collect();
        self.st.batches_missing += self.st.missing.len() as u64;
        let mut parts = self.st.radio.remove(&k).unwrap_or_default();
        parts.sort_by_key(|m| m.observers.first().map_or(-1, |&o| i64::from(o)));
        let mut received: Vec<Received> = parts.iter().flat_map(|m| received_from_step(m, i)).collect();
        received.sort_by_key(|r| r.sender);
        Ok(received)
    }
}

/// The world's prior of the own satellite (`estimate_from_full`): one row, `ids` [i].
fn prior_of(m: &FullEstimate, i: usize) -> Result<Est, String> {
    let rows = m.q_bi.len() / 4;
    if rows != 1 || !(m.ids.is_empty() || m.ids == [i as u32]) || m.own as usize != i {
        return Err(format!("the world's prior has {rows} rows (ids {:?}): a ci agent starts from its own satellite's alone", m.ids));
    }
    let p = m.p.as_ref().ok_or("the prior has no P")?;
    Ok(Est {
        step: m.k,
        t: m.t_s,
        q: vec![[m.q_bi[0], m.q_bi[1], m.q_bi[2], m.q_bi[3]]],
        w: vec![[m.omega_bi_b_rad_s[0], m.omega_bi_b_rad_s[1], m.omega_bi_b_rad_s[2]]],
        r: vec![[m.r_h_m[0], m.r_h_m[1], m.r_h_m[2]]],
        v: vec![[m.v_h_m_s[0], m.v_h_m_s[1], m.v_h_m_s[2]]],
        bias: [m.bias_b_rad_s[0], m.bias_b_rad_s[1], m.bias_b_rad_s[2]],
        p: Mat::from_rows(12, 12, &p.data),
    })
}
