//! Logging to stderr, one line per event, in the Python roles' format
//! (`2026-01-02 03:04:05,678 agent-1 INFO message`).

use std::io::Write;
use std::sync::OnceLock;
use std::time::{SystemTime, UNIX_EPOCH};

static NAME: OnceLock<String> = OnceLock::new();

pub fn set_name(name: &str) {
    let _ = NAME.set(name.to_string());
}

fn stamp() -> String {
    let d = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm), UTC.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02},{:03}", rem / 3600, rem % 3600 / 60, rem % 60, d.subsec_millis())
}

fn line(level: &str, msg: &str) {
    let name = NAME.get().map(String::as_str).unwrap_or("agent-?");
    let mut e = std::io::stderr().lock();
    let _ = writeln!(e, "{} {name} {level} {msg}", stamp());
}

/// Whether debug lines are written (SWARM_AGENT_DEBUG=1: each step's ω and gate).
pub fn debug_enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var("SWARM_AGENT_DEBUG").is_ok_and(|v| v == "1"))
}

pub fn debug(msg: &str) {
    if debug_enabled() {
        line("DEBUG", msg);
    }
}

pub fn info(msg: &str) {
    line("INFO", msg);
}

pub fn warn(msg: &str) {
    line("WARNING", msg);
}

pub fn error(msg: &str) {
    line("ERROR", msg);
}
