//! What a receiver checks (proto/README.md, "What a receiver checks"; the Python receiver's
//! `swarmrt.bus.messages.decode` and `check_key`), for the messages this agent reads: the
//! clock, its sensors and camera outputs, the ideal radio's batches or (links) its own radio
//! deliveries, fault commands and the
//! world's prior. A failure is an `Err` naming the problem: the caller counts it (and, for a
//! message on a key its sender may not use, as a key mismatch), logs it and drops it.

use prost::Message;

use crate::pb::{self, CameraOutput, Clock, Delivery, EstimatorMessage, Fault, FullEstimate, Matrix, MeasBatch, Sensors, StepBatches};

pub const SCHEMA_VERSION: u32 = 1;
pub const MAX_SAT_ID: u32 = 10_000;
pub const QUAT_TOL: f64 = 1e-6;
pub const SYM_TOL: f64 = 1e-9;
const MIB: usize = 1 << 20;

/// Why a message was refused; `key_mismatch`: a valid message on a key its sender,
/// observer or satellite field may not use.
#[derive(Debug, Clone)]
pub struct Refused {
    pub reason: String,
    pub key_mismatch: bool,
}

impl Refused {
    fn bad(kind: &str, reason: impl Into<String>) -> Refused {
        Refused { reason: format!("invalid {kind} message: {}", reason.into()), key_mismatch: false }
    }

    fn mismatch(reason: impl Into<String>) -> Refused {
        Refused { reason: reason.into(), key_mismatch: true }
    }
}

type R = Result<(), String>;

pub fn run_ok(run: &str) -> bool {
    (1..=64).contains(&run.len()) && run.bytes().all(|c| c.is_ascii_alphanumeric() || matches!(c, b'_' | b'-' | b'.'))
}

fn header(schema_version: u32, run: &str, sender: &str, t_s: f64) -> R {
    if schema_version != SCHEMA_VERSION {
        if schema_version == 0 {
            return Err("schema_version: missing (not a swarm.v1 message)".into());
        }
        return Err(format!("schema_version: unknown version {schema_version} (this receiver reads {SCHEMA_VERSION})"));
    }
    if !run_ok(run) {
        return Err(format!("run: {:?} is not a run id (1-64 letters, digits, '_', '-', '.')", truncate(run, 80)));
    }
    if !(1..=64).contains(&sender.len()) {
        return Err(format!("sender: {} characters (1-64 allowed)", sender.len()));
    }
    if !t_s.is_finite() {
        return Err(format!("t_s: {t_s} is not finite"));
    }
    Ok(())
}

fn truncate(s: &str, n: usize) -> &str {
    match s.char_indices().nth(n) {
        Some((i, _)) => &s[..i],
        None => s,
    }
}

fn id(top: u32, name: &str, v: u32) -> R {
    if v > top {
        return Err(format!("{name}: satellite id {v} out of range (0-{top})"));
    }
    Ok(())
}

fn finite(name: &str, v: &[f64]) -> R {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(format!("{name}: not finite (NaN or infinity)"))
    }
}

fn rows(name: &str, v: &[f64], width: usize, n: Option<usize>) -> R {
    if v.len() % width != 0 || n.is_some_and(|n| v.len() != n * width) {
        let want = n.map_or(format!("a multiple of {width}"), |n| format!("{n} × {width}"));
        return Err(format!("{name}: {} numbers, expected {want}", v.len()));
    }
    finite(name, v)
}

fn unit(name: &str, q: &[f64]) -> R {
    for c in q.chunks(4) {
        let s: f64 = c.iter().map(|x| x * x).sum();
        let err = (s - 1.0).abs();
        if !(err <= 2.0 * QUAT_TOL) {
            return Err(format!("{name}: not a unit quaternion (|‖q‖² − 1| = {err:.3e} > {:e})", 2.0 * QUAT_TOL));
        }
    }
    Ok(())
}

fn matrix<'a>(name: &str, m: Option<&'a Matrix>, shape: &[u32]) -> Result<&'a [f64], String> {
    let m = m.ok_or_else(|| format!("{name}: missing"))?;
    if m.shape != shape {
        return Err(format!("{name}: shape {:?}, expected {:?}", m.shape, shape));
    }
    let need: usize = shape.iter().map(|&x| x as usize).product();
    if m.data.len() != need {
        return Err(format!("{name}: shape {shape:?} needs {need} numbers, got {}", m.data.len()));
    }
    finite(name, &m.data)?;
    Ok(&m.data)
}

/// Each `k × k` block of `data`: symmetric (to SYM_TOL of its largest entry) and
/// positive-definite (Cholesky on the lower triangle).
fn spd(name: &str, data: &[f64], k: usize) -> R {
    for a in data.chunks(k * k) {
        let scale = a.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        for i in 0..k {
            for j in 0..i {
                if !((a[i * k + j] - a[j * k + i]).abs() <= SYM_TOL * scale) {
                    return Err(format!("{name}: not symmetric"));
                }
            }
        }
        let mut l = vec![0.0; k * k];
        for i in 0..k {
            for j in 0..=i {
                let mut s = a[i * k + j];
                for p in 0..j {
                    s -= l[i * k + p] * l[j * k + p];
                }
                if i == j {
                    if !(s > 0.0) {
                        return Err(format!("{name}: not positive-definite"));
                    }
                    l[i * k + i] = s.sqrt();
                } else {
                    l[i * k + j] = s / l[j * k + j];
                }
            }
        }
    }
    Ok(())
}

fn ascending(v: &[u32]) -> bool {
    v.windows(2).all(|w| w[0] < w[1])
}

// ------------------------------------------------------------------------ per message kind

fn clock(m: &Clock, top: u32) -> R {
    for &s in &m.live_agents {
        id(top, "live_agents", s)?;
    }
    if m.mode != "lockstep" && m.mode != "free" {
        return Err(format!("mode: {:?} is not one of [lockstep, free]", truncate(&m.mode, 40)));
    }
    Ok(())
}

fn small(name: &str, v: &[f64], width: usize) -> R {
    if v.is_empty() {
        return Ok(());
    }
    if v.len() != width {
        return Err(format!("{name}: {} numbers, expected 1 × {width}", v.len()));
    }
    finite(name, v)
}

fn sensors(m: &Sensors, top: u32) -> R {
    id(top, "sat", m.sat)?;
    small("gyro_rate_B_rad_s", &m.gyro_rate_b_rad_s, 3)?;
    small("q_BI_star", &m.q_bi_star, 4)?;
    if !m.q_bi_star.is_empty() {
        unit("q_BI_star", &m.q_bi_star)?;
    }
    small("r_H_gps_m", &m.r_h_gps_m, 3)?;
    for (f, v) in [("sigma_star_rad", m.sigma_star_rad), ("sigma_gps_m", m.sigma_gps_m)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{f}: {v} is not a finite number > 0"));
        }
    }
    Ok(())
}

fn cam(m: &CameraOutput, top: u32) -> R {
    id(top, "sat", m.sat)?;
    for (j, d) in m.detections.iter().enumerate() {
        if d.q_bj_bi.len() != 4 || d.r_ij_bi_m.len() != 3 {
            return Err(format!("detections.{j}: {} numbers in q_BjBi (4), {} in r_ij_Bi_m (3)", d.q_bj_bi.len(), d.r_ij_bi_m.len()));
        }
        id(top, &format!("detections.{j}.target"), d.target)?;
        if d.target == m.sat {
            return Err(format!("detections.{j}.target: satellite {} cannot see itself", m.sat));
        }
        if d.camera > 5 {
            return Err(format!("detections.{j}.camera: {} is not a face camera (0-5)", d.camera));
        }
    }
    let q: Vec<f64> = m.detections.iter().flat_map(|d| d.q_bj_bi.iter().copied()).collect();
    rows("detections.q_BjBi", &q, 4, None)?;
    unit("detections.q_BjBi", &q)?;
    let r: Vec<f64> = m.detections.iter().flat_map(|d| d.r_ij_bi_m.iter().copied()).collect();
    rows("detections.r_ij_Bi_m", &r, 3, None)?;
    if let Some(c) = m.cameras_off.iter().max() {
        if *c > 5 {
            return Err(format!("cameras_off: {c} is not a face camera (0-5)"));
        }
    }
    Ok(())
}

/// An estimator's message (`messages._estimator_msg`).
fn estimator_msg(name: &str, e: &EstimatorMessage, top: u32, sender: u32) -> R {
    use pb::estimator_message::Body;
    if e.kind.is_empty() {
        if e.body.is_some() {
            return Err(format!("{name}: a body without a kind"));
        }
        return Ok(());
    }
    let k = e.kind.as_bytes();
    if !(k.len() <= 64
        && k[0].is_ascii_lowercase()
        && k.iter().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'_' || *c == b'-'))
    {
        return Err(format!("{name}.kind: {:?} is not an estimator name ([a-z][a-z0-9_-], at most 64)", truncate(&e.kind, 40)));
    }
    match &e.body {
        Some(Body::Ci(c)) => {
            rows(&format!("{name}.ci.q_BI"), &c.q_bi, 4, Some(1))?;
            unit(&format!("{name}.ci.q_BI"), &c.q_bi)?;
            rows(&format!("{name}.ci.omega_BI_B_rad_s"), &c.omega_bi_b_rad_s, 3, Some(1))?;
            rows(&format!("{name}.ci.r_H_m"), &c.r_h_m, 3, Some(1))?;
            rows(&format!("{name}.ci.v_H_m_s"), &c.v_h_m_s, 3, Some(1))?;
            let p = matrix(&format!("{name}.ci.P_pose"), c.p_pose.as_ref(), &[6, 6])?;
            spd(&format!("{name}.ci.P_pose"), p, 6)
        }
        Some(Body::Pairwise(w)) => {
            rows(&format!("{name}.pairwise.q_BI"), &w.q_bi, 4, Some(1))?;
            unit(&format!("{name}.pairwise.q_BI"), &w.q_bi)?;
            for (f, v) in
                [("omega_BI_B_rad_s", &w.omega_bi_b_rad_s), ("r_H_m", &w.r_h_m), ("v_H_m_s", &w.v_h_m_s), ("bias_B_rad_s", &w.bias_b_rad_s)]
            {
                rows(&format!("{name}.pairwise.{f}"), v, 3, Some(1))?;
            }
            let p = matrix(&format!("{name}.pairwise.P"), w.p.as_ref(), &[12, 12])?;
            spd(&format!("{name}.pairwise.P"), p, 12)?;
            for &s in &w.partners {
                id(top, &format!("{name}.pairwise.partners"), s)?;
            }
            if !ascending(&w.partners) {
                return Err(format!("{name}.pairwise.partners: not ascending and distinct"));
            }
            if w.partners.contains(&sender) {
                return Err(format!("{name}.pairwise.partners: satellite {sender} cannot be its own partner"));
            }
            matrix(&format!("{name}.pairwise.sigma"), w.sigma.as_ref(), &[w.partners.len() as u32, 12, 12]).map(|_| ())
        }
        Some(Body::Opaque(b)) => {
            if b.len() > 64 * 1024 {
                return Err(format!("{name}.opaque: {} bytes (at most {})", b.len(), 64 * 1024));
            }
            Ok(())
        }
        None => Err(format!("{name}: kind {:?} without a body", e.kind)),
    }
}

/// The measurement columns of `n` rows (`messages._columns` with `fastcheck.check_batch`).
fn columns(camera: &[u32], q: &[f64], r: &[f64], rbi: Option<&Matrix>, n: usize) -> R {
    if camera.len() != n {
        return Err(format!("camera: {} values for {n} measurements", camera.len()));
    }
    if let Some(c) = camera.iter().max() {
        if *c > 6 + MAX_SAT_ID {
            return Err(format!("camera: {c} out of range"));
        }
    }
    for (name, v, w) in [("q_BjBi", q, 4), ("r_ij_Bi_m", r, 3)] {
        if v.len() != w * n {
            return Err(format!("{name}: {} numbers, expected {n} × {w}", v.len()));
        }
    }
    let m = rbi.ok_or("R_Bi: missing")?;
    if m.shape != [n as u32, 6, 6] {
        return Err(format!("R_Bi: shape {:?}, expected {:?}", m.shape, [n, 6, 6]));
    }
    if m.data.len() != 36 * n {
        return Err(format!("R_Bi: shape {:?} needs {} numbers, got {}", [n, 6, 6], 36 * n, m.data.len()));
    }
    if !q.iter().all(|x| x.is_finite()) {
        return Err("q_BjBi: not finite (NaN or infinity)".into());
    }
    for c in q.chunks(4) {
        let s = c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3];
        if !((s - 1.0).abs() <= 2.0 * QUAT_TOL) {
            return Err("q_BjBi: not a unit quaternion".into());
        }
    }
    if !r.iter().all(|x| x.is_finite()) {
        return Err("r_ij_Bi_m: not finite (NaN or infinity)".into());
    }
    if !m.data.iter().all(|x| x.is_finite()) {
        return Err("R_Bi: not finite (NaN or infinity)".into());
    }
    spd("R_Bi", &m.data, 6)
}

fn step_batches(m: &StepBatches, top: u32) -> R {
    if m.counts.len() != m.observers.len() {
        return Err(format!("counts: {} values for {} observers", m.counts.len(), m.observers.len()));
    }
    for &o in &m.observers {
        id(top, "observers", o)?;
    }
    if !ascending(&m.observers) {
        return Err("observers: not ascending and distinct".into());
    }
    let n: usize = m.counts.iter().map(|&c| c as usize).sum();
    if m.target.len() != n {
        return Err(format!("target: {} values for {n} rows (the sum of counts)", m.target.len()));
    }
    if let Some(t) = m.target.iter().max() {
        id(top, "target", *t)?;
    }
    let mut row = 0;
    for (&o, &c) in m.observers.iter().zip(&m.counts) {
        for &t in &m.target[row..row + c as usize] {
            if t == o {
                return Err(format!("target: satellite {o} cannot measure itself"));
            }
        }
        row += c as usize;
    }
    if !(m.estimators.is_empty() || m.estimators.len() == m.observers.len()) {
        return Err(format!("estimators: {} messages for {} observers", m.estimators.len(), m.observers.len()));
    }
    for (&o, e) in m.observers.iter().zip(&m.estimators) {
        estimator_msg(&format!("estimators[{o}]"), e, top, o)?;
    }
    columns(&m.camera, &m.q_bj_bi, &m.r_ij_bi_m, m.r_bi.as_ref(), n)
}

/// One observer's batch (`messages._meas`).
fn meas_batch(m: &MeasBatch, top: u32) -> R {
    id(top, "observer", m.observer)?;
    for &t in &m.target {
        id(top, "target", t)?;
    }
    if m.target.contains(&m.observer) {
        return Err(format!("target: satellite {} cannot measure itself", m.observer));
    }
    if let Some(e) = &m.estimator {
        estimator_msg("estimator", e, top, m.observer)?;
    }
    columns(&m.camera, &m.q_bj_bi, &m.r_ij_bi_m, m.r_bi.as_ref(), m.target.len())
}

/// What the radio delivered to satellite `sat` by step k (links; `messages._rx`).
fn delivery(m: &Delivery, top: u32) -> R {
    id(top, "sat", m.sat)?;
    for (j, it) in m.items.iter().enumerate() {
        if !it.arrival_t_s.is_finite() {
            return Err(format!("items.{j}.arrival_t_s: not finite"));
        }
        let b = it.batch.as_ref().ok_or_else(|| format!("items.{j}: no batch"))?;
        header(b.schema_version, &b.run, &b.sender, b.t_s).and_then(|_| meas_batch(b, top)).map_err(|e| format!("items.{j}.batch: {e}"))?;
        if b.observer == m.sat {
            return Err(format!("items.{j}.batch: satellite {}'s own batch delivered to it", m.sat));
        }
    }
    Ok(())
}

/// A fault action's schema value from its name on the wire (proto/swarm/v1/fault.proto:
/// "kill-agent" is `FAULT_ACTION_KILL_AGENT`); the schema is the one list, nothing is copied
/// here. None for a name it does not declare, and for the unspecified value.
fn wire_enum<T>(name: &str, prefix: &str, from: fn(&str) -> Option<T>) -> Option<T> {
    if name.is_empty() || name.len() > 64 || !name.bytes().all(|b| b.is_ascii_lowercase() || b == b'-') {
        return None;
    }
    from(&format!("{prefix}{}", name.to_ascii_uppercase().replace('-', "_"))).filter(|_| name != "unspecified")
}

/// The schema's names of an enum's values as they go on the wire, for error messages.
fn wire_names(prefix: &str, names: impl Iterator<Item = &'static str>) -> Vec<String> {
    names.map(|n| n.trim_start_matches(prefix).to_ascii_lowercase().replace('_', "-")).collect()
}

fn fault_actions() -> Vec<String> {
    wire_names("FAULT_ACTION_", (1..100).filter_map(|i| pb::FaultAction::try_from(i).ok()).map(|a| a.as_str_name()))
}

fn fault(m: &Fault, top: u32) -> R {
    let Some(action) = wire_enum(&m.action, "FAULT_ACTION_", pb::FaultAction::from_str_name) else {
        return Err(format!("action: {:?} is not one of {:?}", truncate(&m.action, 40), fault_actions()));
    };
    if wire_enum(&m.phase, "FAULT_PHASE_", pb::FaultPhase::from_str_name).is_none() {
        let phases = wire_names("FAULT_PHASE_", (1..4).filter_map(|i| pb::FaultPhase::try_from(i).ok()).map(|p| p.as_str_name()));
        return Err(format!("phase: {:?} is not one of {phases:?}", truncate(&m.phase, 40)));
    }
    match m.target {
        Some(t) => id(top, "target", t)?,
        // The schema's numbering: an action below 50 acts on a satellite.
        None if (action as i32) < 50 => return Err(format!("target: {} needs a target satellite", m.action)),
        None => {}
    }
    if m.camera.is_some_and(|c| c > 5) {
        return Err(format!("camera: {} is not a face camera (0-5)", m.camera.unwrap_or(0)));
    }
    if let Some(s) = &m.state {
        if s != "on" && s != "off" {
            return Err(format!("state: {:?} is not one of [on, off]", truncate(s, 40)));
        }
    }
    if m.action == "camera" && (m.camera.is_none() || m.state.is_none()) {
        return Err("camera: a camera fault needs camera and state".into());
    }
    if let Some(r) = m.rate {
        if !(0.0..=1.0).contains(&r) {
            return Err(format!("rate: {r} is not in [0, 1]"));
        }
    }
    if m.action == "drop" && m.rate.is_none() {
        return Err("rate: a drop fault needs a rate".into());
    }
    if let Some(d) = m.down_s {
        if !(0.0..=3600.0).contains(&d) {
            return Err(format!("down_s: {d} is not in [0, 3600] s"));
        }
    }
    if m.action.starts_with("stall-") && m.phase == "command" && !m.down_s.is_some_and(|d| d > 0.0) {
        return Err(format!("down_s: {} needs down_s > 0 (how long the process stays stopped, wall s)", m.action));
    }
    if let Some(p) = m.peer {
        id(top, "peer", p)?;
        if m.target == Some(p) {
            return Err(format!("peer: satellite {p} has no link to itself"));
        }
    }
    if let Some(d) = m.delay_s {
        if !(0.0..=3600.0).contains(&d) {
            return Err(format!("delay_s: {d} is not in [0, 3600] s"));
        }
    }
    if m.action == "link" && m.phase == "command" && m.state.is_none() && m.delay_s.is_none() && m.rate.is_none() {
        return Err("link: a link fault needs state, delay_s or rate".into());
    }
    if let Some(n) = &m.netem {
        if !(1..=200).contains(&n.len()) {
            return Err(format!("netem: {} characters (1-200 allowed)", n.len()));
        }
    }
    if m.action == "netem" && m.netem.is_none() {
        return Err("netem: action netem needs netem (tc netem arguments or 'clear')".into());
    }
    if m.detail.len() > 1000 {
        return Err(format!("detail: {} characters (at most 1000)", m.detail.len()));
    }
    Ok(())
}

fn full_est(m: &FullEstimate, top: u32) -> R {
    id(top, "own", m.own)?;
    rows("q_BI", &m.q_bi, 4, None)?;
    let n = m.q_bi.len() / 4;
    if n == 0 {
        return Err("q_BI: no satellites".into());
    }
    unit("q_BI", &m.q_bi)?;
    rows("omega_BI_B_rad_s", &m.omega_bi_b_rad_s, 3, Some(n))?;
    rows("r_H_m", &m.r_h_m, 3, Some(n))?;
    rows("v_H_m_s", &m.v_h_m_s, 3, Some(n))?;
    rows("bias_B_rad_s", &m.bias_b_rad_s, 3, Some(1))?;
    if m.ids.is_empty() {
        if m.own as usize >= n {
            return Err(format!("own: satellite {} in an estimate of {n}", m.own));
        }
    } else {
        if m.ids.len() != n {
            return Err(format!("ids: {} satellites for {n} rows", m.ids.len()));
        }
        for &s in &m.ids {
            id(top, "ids", s)?;
        }
        if !ascending(&m.ids) {
            return Err("ids: not ascending and distinct".into());
        }
        if !m.ids.contains(&m.own) {
            return Err(format!("own: satellite {} is not among the rows", m.own));
        }
    }
    let d = 12 * n as u32;
    let p = matrix("P", m.p.as_ref(), &[d, d])?;
    spd("P", p, d as usize)
}

// ------------------------------------------------------------------------------ decoding

/// A message of a kind this agent reads, decoded and checked.
#[derive(Debug)]
pub enum Msg {
    Clock(Clock),
    Sensors(Sensors),
    Cam(CameraOutput),
    Batches(StepBatches),
    Rx(Delivery),
    Fault(Fault),
    FullEst(FullEstimate),
}

impl Msg {
    pub fn run(&self) -> &str {
        match self {
            Msg::Clock(m) => &m.run,
            Msg::Sensors(m) => &m.run,
            Msg::Cam(m) => &m.run,
            Msg::Batches(m) => &m.run,
            Msg::Rx(m) => &m.run,
            Msg::Fault(m) => &m.run,
            Msg::FullEst(m) => &m.run,
        }
    }

    pub fn sender(&self) -> &str {
        match self {
            Msg::Clock(m) => &m.sender,
            Msg::Sensors(m) => &m.sender,
            Msg::Cam(m) => &m.sender,
            Msg::Batches(m) => &m.sender,
            Msg::Rx(m) => &m.sender,
            Msg::Fault(m) => &m.sender,
            Msg::FullEst(m) => &m.sender,
        }
    }
}

/// Parse and check a payload of `kind` (`clock`, `sensors`, `cam`, `batches`, `rx`,
/// `fault`, `full_est`) for a swarm of `n_sats`.
pub fn decode(kind: &str, payload: &[u8], n_sats: usize) -> Result<Msg, Refused> {
    let limit = if matches!(kind, "batches" | "full_est" | "rx") { 64 * MIB } else { 8 * MIB };
    if payload.len() > limit {
        return Err(Refused::bad(kind, format!("{} bytes, more than the {limit} a {kind} message may have", payload.len())));
    }
    let top = (n_sats as u32).saturating_sub(1).min(MAX_SAT_ID);
    let bad = |e: prost::DecodeError| Refused::bad(kind, format!("not a swarm.v1 message of its kind ({e})"));
    macro_rules! go {
        ($ty:ty, $variant:ident, $check:ident) => {{
            let m = <$ty>::decode(payload).map_err(bad)?;
            header(m.schema_version, &m.run, &m.sender, m.t_s).and_then(|_| $check(&m, top)).map_err(|e| Refused::bad(kind, e))?;
            Ok(Msg::$variant(m))
        }};
    }
    match kind {
        "clock" => go!(Clock, Clock, clock),
        "sensors" => go!(Sensors, Sensors, sensors),
        "cam" => go!(CameraOutput, Cam, cam),
        "batches" => go!(StepBatches, Batches, step_batches),
        "rx" => go!(Delivery, Rx, delivery),
        "fault" => go!(Fault, Fault, fault),
        "full_est" => go!(FullEstimate, FullEst, full_est),
        other => Err(Refused::bad(other, "a kind this agent does not read")),
    }
}

/// The message agrees with the key it came on (`messages.check_key`): the satellite the key
/// names is the one the message is about, and the sender may publish on that key.
/// `tail`: the key's last segment (for `fault` keys).
pub fn check_key(key: &str, kind: &str, sat: Option<u32>, m: &Msg) -> Result<(), Refused> {
    let owner = match m {
        Msg::Sensors(x) => Some(x.sat),
        Msg::Cam(x) => Some(x.sat),
        Msg::FullEst(x) => Some(x.own),
        Msg::Rx(x) => Some(x.sat),
        _ => None,
    };
    if let (Some(s), Some(o)) = (sat, owner) {
        if s != o {
            return Err(Refused::mismatch(format!("key says satellite {s}, message says {o}")));
        }
    }
    let want: Vec<String> = match m {
        Msg::Fault(f) => {
            let tail = key.rsplit('/').next().unwrap_or("");
            if tail == "fault" {
                if f.phase != "command" {
                    return Err(Refused::mismatch(format!("a fault {:?} report on {key} (reports go on fault/<reporter>)", f.phase)));
                }
                vec!["cli".into(), "world".into()]
            } else {
                if f.phase == "command" {
                    return Err(Refused::mismatch(format!("a fault command on {key} (commands go on fault)")));
                }
                vec![tail.to_string()]
            }
        }
        Msg::FullEst(_) if key.contains("/init/") => vec!["world".into()],
        Msg::FullEst(_) => vec![format!("agent-{}", sat.unwrap_or(u32::MAX))],
        _ => vec!["world".into()],
    };
    let _ = kind;
    if !want.iter().any(|w| w == m.sender()) {
        return Err(Refused::mismatch(format!(
            "sender {:?} may not publish on {key} (expected {})",
            truncate(m.sender(), 64),
            want.join(" or ")
        )));
    }
    Ok(())
}

/// `(run, kind, satellite)` of a key this agent may receive (`messages.parse_key`), None if
/// it is none of them.
pub fn parse_key(key: &str) -> Option<(String, String, Option<u32>)> {
    let rest = key.strip_prefix("swarm/")?;
    let (run, tail) = rest.split_once('/')?;
    let parts: Vec<&str> = tail.split('/').collect();
    let num = |s: &str| -> Option<u32> {
        if !s.is_empty() && s.bytes().all(|c| c.is_ascii_digit()) {
            s.parse().ok()
        } else {
            None
        }
    };
    let (kind, sat) = match parts.as_slice() {
        ["clock"] => ("clock", None),
        ["batches"] => ("batches", None),
        ["batches", s] => ("batches", Some(num(s)?)),
        ["rx", s] => ("rx", Some(num(s)?)),
        ["fault"] => ("fault", None),
        ["fault", _] => ("fault", None),
        ["sat", s, k @ ("sensors" | "cam" | "img")] => (*k, Some(num(s)?)),
        ["init", s] | ["cov", s] => ("full_est", Some(num(s)?)),
        ["alive", _role, _id] => ("alive", None),
        _ => return None,
    };
    Some((run.to_string(), kind.to_string(), sat))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys() {
        assert_eq!(parse_key("swarm/r1/sat/3/cam"), Some(("r1".into(), "cam".into(), Some(3))));
        assert_eq!(parse_key("swarm/r1/fault/agent-2").map(|x| x.1), Some("fault".into()));
        assert_eq!(parse_key("swarm/r1/sat/x/cam"), None);
        assert_eq!(parse_key("swarm/r1/est/3"), None);
        assert_eq!(parse_key("swarm/r1/batches/3"), Some(("r1".into(), "batches".into(), Some(3))));
        assert_eq!(parse_key("swarm/r1/batches/x"), None);
    }

    /// The fault actions and phases come from the schema (fault.proto), by their wire names.
    #[test]
    fn fault_actions_and_phases_are_the_schemas() {
        let all = fault_actions();
        assert_eq!(all.len(), 20, "{all:?}");
        assert!(all.iter().any(|a| a == "partition-nodes") && all.iter().any(|a| a == "stall-router"), "{all:?}");
        let f = |action: &str, phase: &str, target: Option<u32>| Fault {
            schema_version: 1,
            run: "r".into(),
            sender: "cli".into(),
            action: action.into(),
            phase: phase.into(),
            target,
            ..Default::default()
        };
        assert!(fault(&f("kill-router", "command", None), 4).is_ok());
        assert!(fault(&f("kill-agent", "done", Some(2)), 4).is_ok());
        for (m, why) in [
            (f("kill-agent", "command", None), "needs a target"),
            (f("kill_agent", "command", Some(1)), "action"),
            (f("unspecified", "command", Some(1)), "action"),
            (f("KILL-AGENT", "command", Some(1)), "action"),
            (f("kill-agent", "unspecified", Some(1)), "phase"),
            (f("kill-agent", "Done", Some(1)), "phase"),
        ] {
            let e = fault(&m, 4).unwrap_err();
            assert!(e.contains(why), "{e}");
        }
    }

    /// Valid messages of every kind this agent reads, mutated (bytes flipped, cut, spliced)
    /// many times over: every result is a verdict, never a panic.
    #[test]
    fn mutated_messages_never_panic() {
        use crate::pb::{CiState, Detection, EstimatorMessage};
        let m6 = |v: f64| Some(Matrix { shape: vec![6, 6], data: (0..36).map(|i| if i % 7 == 0 { v } else { 0.0 }).collect() });
        let ci = EstimatorMessage {
            kind: "ci".into(),
            version: 1,
            body: Some(crate::pb::estimator_message::Body::Ci(CiState {
                q_bi: vec![0.0, 0.0, 0.0, 1.0],
                omega_bi_b_rad_s: vec![0.0; 3],
                r_h_m: vec![1.0; 3],
                v_h_m_s: vec![0.0; 3],
                p_pose: m6(1e-4),
            })),
        };
        let batches = StepBatches {
            schema_version: 1,
            run: "r".into(),
            sender: "world".into(),
            k: 3,
            t_s: 3.0,
            observers: vec![0, 2],
            counts: vec![1, 1],
            target: vec![1, 1],
            camera: vec![0, 1],
            q_bj_bi: vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            r_ij_bi_m: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            r_bi: Some(Matrix { shape: vec![2, 6, 6], data: (0..72).map(|i| if (i % 36) % 7 == 0 { 1e-4 } else { 0.0 }).collect() }),
            estimators: vec![ci.clone(), ci],
        };
        let cam = CameraOutput {
            schema_version: 1,
            run: "r".into(),
            sender: "world".into(),
            k: 3,
            t_s: 3.0,
            sat: 1,
            detections: vec![Detection { target: 0, camera: 2, q_bj_bi: vec![0.0, 0.0, 0.0, 1.0], r_ij_bi_m: vec![1.0, 2.0, 3.0] }],
            cameras_off: vec![4],
        };
        let sensors = Sensors {
            schema_version: 1,
            run: "r".into(),
            sender: "world".into(),
            k: 3,
            t_s: 3.0,
            sat: 1,
            gyro_rate_b_rad_s: vec![0.0; 3],
            q_bi_star: vec![0.0, 0.0, 0.0, 1.0],
            r_h_gps_m: vec![1.0; 3],
            sigma_star_rad: 1e-5,
            sigma_gps_m: 0.01,
        };
        let prior = FullEstimate {
            schema_version: 1,
            run: "r".into(),
            sender: "world".into(),
            k: 0,
            t_s: 0.0,
            own: 1,
            q_bi: vec![0.0, 0.0, 0.0, 1.0],
            omega_bi_b_rad_s: vec![0.0; 3],
            r_h_m: vec![0.0; 3],
            v_h_m_s: vec![0.0; 3],
            bias_b_rad_s: vec![0.0; 3],
            p: Some(Matrix { shape: vec![12, 12], data: (0..144).map(|i| if i % 13 == 0 { 1e-4 } else { 0.0 }).collect() }),
            ids: vec![1],
        };
        let fault = Fault {
            schema_version: 1,
            run: "r".into(),
            sender: "world".into(),
            k: 3,
            t_s: 3.0,
            action: "drop".into(),
            phase: "command".into(),
            target: Some(1),
            rate: Some(0.5),
            ..Default::default()
        };
        let seeds: Vec<(&str, Vec<u8>)> = vec![
            ("batches", batches.encode_to_vec()),
            ("cam", cam.encode_to_vec()),
            ("sensors", sensors.encode_to_vec()),
            ("full_est", prior.encode_to_vec()),
            ("fault", fault.encode_to_vec()),
        ];
        for (kind, bytes) in &seeds {
            assert!(decode(kind, bytes, 4).is_ok(), "{kind}: the seed itself");
        }
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for round in 0..20_000 {
            let (kind, seed) = &seeds[round % seeds.len()];
            let mut b = seed.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() as usize) % b.len().max(1);
                match next() % 4 {
                    0 if !b.is_empty() => b[at] ^= 1 << (next() % 8),
                    1 if !b.is_empty() => b[at] = next() as u8,
                    2 => b.truncate(at),
                    _ => {
                        let (_, other) = &seeds[(next() as usize) % seeds.len()];
                        let from = (next() as usize) % other.len();
                        b.splice(at.min(b.len())..at.min(b.len()), other[from..].iter().copied().take(16));
                    }
                }
            }
            let _ = decode(kind, &b, 4).map(|m| check_key("swarm/r/sat/1/cam", kind, Some(1), &m));
        }
    }

    #[test]
    fn a_forged_clock_is_refused() {
        let c = Clock {
            schema_version: 1,
            run: "r".into(),
            sender: "agent-1".into(),
            k: 3,
            t_s: 3.0,
            live_agents: vec![0, 1],
            mode: "lockstep".into(),
            done: false,
            malformed: 0,
            key_mismatch: 0,
            ..Default::default()
        };
        let m = decode("clock", &c.encode_to_vec(), 4).unwrap();
        assert!(check_key("swarm/r/clock", "clock", None, &m).unwrap_err().key_mismatch);
        let c2 = Clock { t_s: f64::NAN, sender: "world".into(), ..c.clone() };
        assert!(decode("clock", &c2.encode_to_vec(), 4).is_err());
        let c3 = Clock { live_agents: vec![7], sender: "world".into(), ..c };
        assert!(decode("clock", &c3.encode_to_vec(), 4).is_err());
        assert!(decode("clock", b"\xff\x00 not protobuf", 4).is_err());
    }
}
