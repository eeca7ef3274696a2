//! swarm-watch: joins a running swarm-coloc swarm as a Zenoh client and prints, for every
//! agent, its estimate of one satellite, step by step. It is written against the schema
//! files (proto/swarm/v1) and the key space (docs/architecture.md, "Key space") only: nothing
//! of the Python emulator's code.
//!
//!     swarm-watch --connect tcp/127.0.0.1:7447 --run RUN --sat 2 [--json] [--timeout-s 600]
//!                 [--credential observer.json]
//!
//! With security on (the default), the router admits only sessions with a credential: give
//! the `observer` one (read-only: clock, estimates, health; a `swarm keys` directory, or
//! `observer.json` in the `keys` directory that a local `swarm run` names in its run.json),
//! a JSON object {"user", "password"}.
//!
//! Each estimate is checked as the schema's README asks of every receiver (schema version,
//! run, sender against the key, finite numbers, unit quaternions, array lengths against
//! their shapes); a message that fails is counted and dropped. The program ends when the
//! world's clock says the run is done (after a short grace for the last estimates), or at
//! the timeout. Output, one line per (step, agent):
//!
//!     k=12 agent=0 sat=2 q_BI=[...] r_H_m=[...] sigma_pos_m=[...]
//!
//! or with --json one JSON object per line (numbers in shortest round-trip form, so they
//! read back bit for bit).

use std::collections::BTreeSet;
use std::time::Duration;

use prost::Message;

pub mod swarm {
    pub mod v1 {
        include!(concat!(env!("OUT_DIR"), "/swarm.v1.rs"));
    }
}
use swarm::v1::{Clock, Estimate};

const SCHEMA_VERSION: u32 = 1;
const QUAT_TOL: f64 = 1e-6;

struct Args {
    connect: Vec<String>,
    run: String,
    sat: usize,
    json: bool,
    timeout_s: f64,
    credential: Option<String>,
}

fn usage(msg: &str) -> ! {
    eprintln!("swarm-watch: {msg}");
    eprintln!("usage: swarm-watch --connect tcp/HOST:PORT --run RUN --sat J [--json] [--timeout-s S] [--credential FILE]");
    std::process::exit(2)
}

fn parse_args() -> Args {
    let mut a = Args { connect: vec![], run: String::new(), sat: usize::MAX, json: false, timeout_s: 600.0, credential: None };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut val = |name: &str| it.next().unwrap_or_else(|| usage(&format!("{name} needs a value")));
        match arg.as_str() {
            "--connect" => a.connect.push(val("--connect")),
            "--run" => a.run = val("--run"),
            "--sat" => a.sat = val("--sat").parse().unwrap_or_else(|_| usage("--sat: expected a satellite number")),
            "--timeout-s" => a.timeout_s = val("--timeout-s").parse().unwrap_or_else(|_| usage("--timeout-s: expected seconds")),
            "--credential" => a.credential = Some(val("--credential")),
            "--json" => a.json = true,
            "-h" | "--help" => usage("watch every agent's estimate of one satellite"),
            other => usage(&format!("unknown argument {other:?}")),
        }
    }
    if a.connect.is_empty() || a.run.is_empty() || a.sat == usize::MAX {
        usage("--connect, --run and --sat are required");
    }
    if a.run.is_empty() || a.run.len() > 64 || !a.run.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c)) {
        usage("--run: 1-64 letters, digits, '_', '-' or '.'");
    }
    a
}

/// Agent i's estimate of satellite `sat`, checked.
struct Row {
    k: u64,
    agent: u32,
    t_s: f64,
    q_bi: [f64; 4],
    r_h_m: [f64; 3],
    v_h_m_s: [f64; 3],
    p_pose_diag: [f64; 6],
}

fn finite(name: &str, v: &[f64]) -> Result<(), String> {
    if v.iter().all(|x| x.is_finite()) { Ok(()) } else { Err(format!("{name}: not finite")) }
}

/// The checks every receiver makes (proto/README.md, "What a receiver checks").
fn check(key: &str, run: &str, sat: usize, m: &Estimate) -> Result<Row, String> {
    if m.schema_version != SCHEMA_VERSION {
        return Err(format!("schema_version {} (this receiver reads {SCHEMA_VERSION})", m.schema_version));
    }
    if m.run != run {
        return Err(format!("run {:?} is not {run:?}", m.run));
    }
    let id: u32 = key.rsplit('/').next().and_then(|s| s.parse().ok()).ok_or("key without a satellite id")?;
    if m.own != id {
        return Err(format!("key says satellite {id}, message own says {}", m.own));
    }
    if m.sender != format!("agent-{id}") {
        return Err(format!("sender {:?} may not publish on {key}", m.sender));
    }
    if m.phase != "prior" && m.phase != "posterior" {
        return Err(format!("phase {:?}", m.phase));
    }
    if !m.t_s.is_finite() {
        return Err("t_s: not finite".into());
    }
    let n = m.q_bi.len() / 4;
    if n == 0 || m.q_bi.len() != 4 * n {
        return Err(format!("q_BI: {} numbers", m.q_bi.len()));
    }
    for (name, v) in [("omega_BI_B_rad_s", &m.omega_bi_b_rad_s), ("r_H_m", &m.r_h_m), ("v_H_m_s", &m.v_h_m_s)] {
        if v.len() != 3 * n {
            return Err(format!("{name}: {} numbers for {n} satellites", v.len()));
        }
        finite(name, v)?;
    }
    finite("q_BI", &m.q_bi)?;
    for q in m.q_bi.chunks(4) {
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if (norm - 1.0).abs() > QUAT_TOL {
            return Err(format!("q_BI: not a unit quaternion (|q| = {norm})"));
        }
    }
    let p = m.p_pose.as_ref().ok_or("P_pose missing")?;
    if p.shape != [n as u32, 6, 6] || p.data.len() != 36 * n {
        return Err(format!("P_pose: shape {:?} with {} numbers for {n} satellites", p.shape, p.data.len()));
    }
    finite("P_pose", &p.data)?;
    if sat >= n {
        return Err(format!("satellite {sat} is not in an estimate of {n}"));
    }
    let b = &p.data[36 * sat..36 * (sat + 1)];
    Ok(Row {
        k: m.k,
        agent: id,
        t_s: m.t_s,
        q_bi: m.q_bi[4 * sat..4 * sat + 4].try_into().unwrap(),
        r_h_m: m.r_h_m[3 * sat..3 * sat + 3].try_into().unwrap(),
        v_h_m_s: m.v_h_m_s[3 * sat..3 * sat + 3].try_into().unwrap(),
        p_pose_diag: std::array::from_fn(|i| b[7 * i]),
    })
}

fn print_row(r: &Row, sat: usize, json: bool) {
    if json {
        let v = serde_json::json!({
            "k": r.k, "agent": r.agent, "sat": sat, "t_s": r.t_s,
            "q_BI": r.q_bi, "r_H_m": r.r_h_m, "v_H_m_s": r.v_h_m_s, "P_pose_diag": r.p_pose_diag,
        });
        println!("{v}");
    } else {
        let sd: Vec<String> = r.p_pose_diag[3..].iter().map(|v| format!("{:.3e}", v.sqrt())).collect();
        println!(
            "k={:4} agent={:3} sat={sat} q_BI=[{:+.6}, {:+.6}, {:+.6}, {:+.6}] r_H_m=[{:+.4}, {:+.4}, {:+.4}] sigma_pos_m=[{}]",
            r.k, r.agent, r.q_bi[0], r.q_bi[1], r.q_bi[2], r.q_bi[3], r.r_h_m[0], r.r_h_m[1], r.r_h_m[2], sd.join(", ")
        );
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let a = parse_args();
    let mut config = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: String| c.insert_json5(k, &v).unwrap_or_else(|e| usage(&format!("zenoh config {k}: {e}")));
    set(&mut config, "mode", "\"client\"".into());
    set(&mut config, "connect/endpoints", serde_json::to_string(&a.connect).unwrap());
    set(&mut config, "connect/timeout_ms", "10000".into());
    set(&mut config, "scouting/multicast/enabled", "false".into());
    if let Some(path) = &a.credential {
        let text = std::fs::read_to_string(path).unwrap_or_else(|e| usage(&format!("--credential {path}: {e}")));
        let cred: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| usage(&format!("--credential {path}: {e}")));
        for field in ["user", "password"] {
            let v = cred.get(field).and_then(|v| v.as_str()).unwrap_or_else(|| usage(&format!("--credential {path}: no \"{field}\"")));
            set(&mut config, &format!("transport/auth/usrpwd/{field}"), serde_json::to_string(v).unwrap());
        }
    }
    let session = match zenoh::open(config).await {
        Ok(s) => s,
        Err(e) => {
            eprintln!("swarm-watch: cannot join {:?}: {e}", a.connect);
            std::process::exit(1)
        }
    };
    let root = format!("swarm/{}", a.run);
    let est = session.declare_subscriber(format!("{root}/est/*")).await.expect("subscribe est");
    let clock = session.declare_subscriber(format!("{root}/clock")).await.expect("subscribe clock");
    eprintln!("swarm-watch: READY on {root} (satellite {})", a.sat);

    let (mut received, mut malformed) = (0u64, 0u64);
    let mut agents = BTreeSet::new();
    let mut done_at: Option<tokio::time::Instant> = None;
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(a.timeout_s);
    loop {
        // After the world's last clock, keep listening a little for the last estimates.
        let until = done_at.map_or(deadline, |t| t.min(deadline));
        tokio::select! {
            s = est.recv_async() => {
                let Ok(s) = s else { break };
                let key = s.key_expr().as_str().to_owned();
                let bytes = s.payload().to_bytes();
                match Estimate::decode(bytes.as_ref()).map_err(|e| e.to_string()).and_then(|m| check(&key, &a.run, a.sat, &m).map(|r| (m.phase, r))) {
                    Ok((phase, row)) => {
                        received += 1;
                        if phase == "posterior" {
                            agents.insert(row.agent);
                            print_row(&row, a.sat, a.json);
                        }
                    }
                    Err(e) => {
                        malformed += 1;
                        if malformed <= 20 {
                            eprintln!("swarm-watch: dropped a malformed estimate on {key}: {e}");
                        }
                    }
                }
            }
            s = clock.recv_async() => {
                let Ok(s) = s else { break };
                match Clock::decode(s.payload().to_bytes().as_ref()) {
                    Ok(c) if c.schema_version == SCHEMA_VERSION && c.run == a.run && c.sender == "world" => {
                        if c.done && done_at.is_none() {
                            done_at = Some(tokio::time::Instant::now() + Duration::from_secs(2));
                        }
                    }
                    _ => malformed += 1,
                }
            }
            _ = tokio::time::sleep_until(until) => break,
        }
    }
    eprintln!(
        "swarm-watch: {received} estimates from agents {:?}, {malformed} malformed messages dropped{}",
        agents,
        if done_at.is_some() { "; the run is done" } else { "; stopped at the timeout" }
    );
    let _ = session.close().await;
    std::process::exit(if done_at.is_some() { 0 } else { 3 });
}
