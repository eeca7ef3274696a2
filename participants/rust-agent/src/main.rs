//! swarm-rust-agent: one satellite of a swarm-coloc swarm, flying the `ci` estimator
//! (split covariance intersection) in Rust. Started by `swarm run --agent I='PROGRAM'` (or
//! a scenario's `emulator.agent_commands`), which gives it, in its environment:
//!
//!   SWARM_SAT_ID         its satellite
//!   SWARM_RUN            the run id (every key is under swarm/<run>/)
//!   SWARM_CONNECT        the Zenoh routers' endpoints, comma-separated
//!   SWARM_CREDENTIAL     its credential file {"user", "password"} (empty: security off)
//!   SWARM_SCENARIO_JSON  the resolved scenario, as JSON (with "derived")
//!   SWARM_RESTART        "1" after a kill, when the supervisor restarts it
//!
//! Exit status: 0 at the end of the run or on SIGTERM/SIGINT (after closing its session),
//! 2 for a scenario it does not fly or a bad environment, 3 when no router was reachable for
//! emulator.bus_lost_after_s, 4 when the world went before the end of the run, 1 otherwise.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

mod agent;
mod brent;
mod bus;
mod checks;
mod ci;
mod filter;
mod linalg;
mod log;
mod quat;
mod scenario;
mod sensors;
mod streams;

pub mod pb {
    include!(concat!(env!("OUT_DIR"), "/swarm.v1.rs"));
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_sig: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_signal_handlers() {
    // SAFETY: the handler only stores to an atomic (async-signal-safe).
    unsafe {
        let h = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
        libc::signal(libc::SIGTERM, h);
        libc::signal(libc::SIGINT, h);
    }
}

fn env(name: &str) -> Result<String, String> {
    std::env::var(name).map_err(|_| format!("{name} is not set (this program is started by `swarm run --agent I=...`)"))
}

fn fail(code: i32, msg: &str) -> ! {
    log::error(msg);
    std::process::exit(code)
}

fn main() {
    if std::env::args().any(|a| a == "-h" || a == "--help") {
        eprintln!(
            "swarm-rust-agent: a satellite agent flying the ci estimator; started by `swarm run --agent I=PATH` \
                   (see participants/rust-agent/README.md)"
        );
        return;
    }
    install_signal_handlers();
    let sat: usize = match env("SWARM_SAT_ID").and_then(|s| s.parse().map_err(|_| format!("SWARM_SAT_ID: {s:?} is not a number"))) {
        Ok(s) => s,
        Err(e) => fail(2, &e),
    };
    log::set_name(&format!("agent-{sat}"));
    let run = env("SWARM_RUN").unwrap_or_else(|e| fail(2, &e));
    if !checks::run_ok(&run) {
        fail(2, &format!("SWARM_RUN: {run:?} is not a run id (1-64 letters, digits, '_', '-', '.')"));
    }
    let endpoints: Vec<String> =
        env("SWARM_CONNECT").unwrap_or_else(|e| fail(2, &e)).split(',').filter(|s| !s.is_empty()).map(String::from).collect();
    if endpoints.is_empty() {
        fail(2, "SWARM_CONNECT: no endpoint");
    }
    let cred = std::env::var("SWARM_CREDENTIAL").ok().filter(|s| !s.is_empty());
    let restart = std::env::var("SWARM_RESTART").is_ok_and(|s| s == "1");
    let path = env("SWARM_SCENARIO_JSON").unwrap_or_else(|e| fail(2, &e));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| fail(2, &format!("SWARM_SCENARIO_JSON {path}: {e}")));
    let sc = match scenario::Scenario::from_json(&text) {
        Ok(sc) => sc,
        Err(why) => fail(2, &format!("cannot fly this scenario: {why}")),
    };
    if sat >= sc.n_sats {
        fail(2, &format!("SWARM_SAT_ID {sat} is not a satellite of this {}-satellite swarm", sc.n_sats));
    }
    if cred.is_none() {
        log::warn("SECURITY OFF (no SWARM_CREDENTIAL): connecting without a credential");
    }
    // The configuration checked first (a credential it cannot use: exit 2), then opened.
    bus::zenoh_config(&endpoints, cred.as_deref()).unwrap_or_else(|e| fail(2, &e));
    let em = sc.emulator.clone();
    let limits = bus::BusLimits { hold_s: em.liveliness_hold_s, bus_grace_s: em.bus_grace_s, bus_lost_after_s: em.bus_lost_after_s };
    let stop = Arc::new(AtomicBool::new(false));
    {
        // The signal flag, seen by the node's waits.
        let stop = stop.clone();
        std::thread::Builder::new()
            .name("signals".into())
            .spawn(move || loop {
                if STOP.load(Ordering::SeqCst) {
                    stop.store(true, Ordering::SeqCst);
                    return;
                }
                std::thread::sleep(Duration::from_millis(20));
            })
            .expect("a thread");
    }
    let session = bus::open_client(&endpoints, cred.as_deref()).unwrap_or_else(|e| fail(1, &e));
    let mut node = match bus::Node::open(session, &run, sc.n_sats, limits, stop.clone()) {
        Ok(n) => n,
        Err(e) => fail(1, &e),
    };
    log::info(&format!(
        "on the bus at {} (scenario {:?}, estimator ci, {} satellites{})",
        endpoints.join(","),
        sc.name,
        sc.n_sats,
        if restart { ", restarted" } else { "" }
    ));
    let root = format!("swarm/{run}");
    let setup = (|| -> Result<(), String> {
        // What satellite i may hear: the clock, its own sensors and cameras, the ideal
        // radio's batches (every peer's on batches, or its radio peers' on batches/<i>),
        // fault commands; liveliness of agents, the world and the recorder.
        let radio = if sc.links_enabled {
            format!("rx/{sat}")
        } else if sc.radio_peers.is_some() {
            format!("batches/{sat}")
        } else {
            "batches".into()
        };
        for tail in ["clock".to_string(), format!("sat/{sat}/sensors"), format!("sat/{sat}/cam"), radio, "fault".into()] {
            node.subscribe(&format!("{root}/{tail}"))?;
        }
        node.watch_liveliness(&format!("{root}/alive/agent/*"))?;
        node.watch_liveliness(&format!("{root}/alive/world/*"))?;
        node.watch_liveliness(&format!("{root}/alive/recorder/*"))?;
        node.silent_queryable(&format!("{root}/cov/{sat}"))?;
        node.announce(&format!("{root}/alive/agent/{sat}"))
    })();
    if let Err(e) = setup {
        node.close();
        fail(1, &e);
    }
    let estimator = ci::Ci::new(sat, sc.filter.clone(), sc.ci.clone());
    let linger = Duration::from_secs_f64(em.shutdown_linger_s + 5.0);
    let mut a = agent::Agent { st: agent::State::new(sc, sat, &run, estimator, restart), node };
    let outcome = a.run();
    let code = match outcome {
        Ok(()) => {
            // Our final estimate may still be on its way: leave when the recorder has it.
            a.node.linger_while_recording(linger);
            0
        }
        Err(agent::Exit::Stop) => {
            log::info("stopped (signal); leaving");
            0
        }
        Err(agent::Exit::Broken(b)) => {
            log::error(&format!("{}; exiting", b.why));
            b.code
        }
    };
    a.node.close();
    std::process::exit(code);
}
