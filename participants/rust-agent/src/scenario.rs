//! The resolved scenario (`SWARM_SCENARIO_JSON`: `Scenario.model_dump(mode="json")` plus
//! `derived`), the parts this agent flies by, and what it refuses.
//!
//! Numbers are read exactly: serde_json's default float parsing may be one unit in the last
//! place off for long mantissas (exact parsing is a crate feature that would rebuild the
//! zenoh crate's tree, which shares serde_json), so every number token is quoted before
//! parsing and read with Rust's correctly rounded `str::parse::<f64>`.

use serde_json::Value;

use crate::ci::CiParams;
use crate::filter::FilterParams;

#[derive(Clone, Debug)]
pub enum RelativeModel {
    Isotropic { sigma_att: f64, sigma_pos: f64 },
    Camera { sigma_att_c: [f64; 3], sigma_pos_c: [f64; 3], range_exponent: f64, reference_range: f64 },
}

#[derive(Clone, Debug)]
pub struct InitialSigma {
    pub att_rad: f64,
    pub rate_rad_s: f64,
    pub bias_rad_s: f64,
    pub pos_m: f64,
    pub vel_m_s: f64,
}

#[derive(Clone, Debug)]
pub struct Emulator {
    pub step_timeout_s: f64,
    pub startup_timeout_s: f64,
    pub liveliness_hold_s: f64,
    pub bus_grace_s: f64,
    pub bus_lost_after_s: f64,
    pub shutdown_linger_s: f64,
    /// The world runs at most this many steps ahead of the recorder: an agent keeps its
    /// messages of the last `recorder_max_lag_steps + 2` steps for a recorder that comes back.
    pub recorder_max_lag_steps: usize,
}

#[derive(Clone, Debug)]
pub struct Scenario {
    pub name: String,
    pub seed: u64,
    pub n_sats: usize,
    pub filter: FilterParams,
    pub ci: CiParams,
    pub relative: RelativeModel,
    pub initial_sigma: InitialSigma,
    pub velocity_max_m_s: f64,
    pub emulator: Emulator,
    /// `links.enabled`: the peers' batches come as the link model's deliveries (`rx/<i>`).
    pub links_enabled: bool,
    /// The ideal radio's peers of every satellite (`derived.radio_peers`, the world's
    /// `swarmcore.graphs.radio_peers`): each agent is sent its peers' batches on its own
    /// `batches/<i>`. None (null or absent): every peer's batches, on `batches`.
    pub radio_peers: Option<Vec<Vec<u32>>>,
}

/// The JSON text with every number token quoted (strings untouched).
fn quote_numbers(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len() + 64);
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c == b'"' {
            let start = i;
            i += 1;
            while i < b.len() && b[i] != b'"' {
                i += if b[i] == b'\\' { 2 } else { 1 };
            }
            i = (i + 1).min(b.len());
            out.push_str(&text[start..i]);
        } else if c == b'-' || c.is_ascii_digit() {
            let start = i;
            while i < b.len() && (b[i].is_ascii_digit() || matches!(b[i], b'-' | b'+' | b'.' | b'e' | b'E')) {
                i += 1;
            }
            out.push('"');
            out.push_str(&text[start..i]);
            out.push('"');
        } else {
            out.push(c as char);
            i += 1;
        }
    }
    out
}

struct Doc(Value);

impl Doc {
    fn get(&self, path: &str) -> Result<&Value, String> {
        let mut v = &self.0;
        for part in path.split('.') {
            v = v.get(part).ok_or_else(|| format!("scenario: no field {path}"))?;
        }
        Ok(v)
    }

    fn f(&self, path: &str) -> Result<f64, String> {
        let v = self.get(path)?;
        let s = v.as_str().ok_or_else(|| format!("scenario: {path} is not a number"))?;
        let x: f64 = s.parse().map_err(|_| format!("scenario: {path}: {s:?} is not a number"))?;
        if !x.is_finite() {
            return Err(format!("scenario: {path}: {s} is not finite"));
        }
        Ok(x)
    }

    fn opt_f(&self, path: &str) -> Result<Option<f64>, String> {
        match self.get(path)? {
            Value::Null => Ok(None),
            _ => self.f(path).map(Some),
        }
    }

    fn u(&self, path: &str) -> Result<u64, String> {
        let v = self.get(path)?;
        let s = v.as_str().ok_or_else(|| format!("scenario: {path} is not a number"))?;
        s.parse().map_err(|_| format!("scenario: {path}: {s:?} is not a non-negative integer"))
    }

    fn s(&self, path: &str) -> Result<&str, String> {
        self.get(path)?.as_str().ok_or_else(|| format!("scenario: {path} is not a string"))
    }

    fn b(&self, path: &str) -> Result<bool, String> {
        self.get(path)?.as_bool().ok_or_else(|| format!("scenario: {path} is not true or false"))
    }

    /// A list of lists of satellite ids, or None (null or absent).
    fn opt_id_lists(&self, path: &str) -> Result<Option<Vec<Vec<u32>>>, String> {
        let v = match self.get(path) {
            Err(_) | Ok(Value::Null) => return Ok(None),
            Ok(v) => v,
        };
        let rows = v.as_array().ok_or_else(|| format!("scenario: {path} is not a list"))?;
        let mut out = Vec::with_capacity(rows.len());
        for (i, row) in rows.iter().enumerate() {
            let ids = row.as_array().ok_or_else(|| format!("scenario: {path}.{i} is not a list"))?;
            let mut r = Vec::with_capacity(ids.len());
            for (k, x) in ids.iter().enumerate() {
                r.push(x.as_str().and_then(|s| s.parse().ok()).ok_or_else(|| format!("scenario: {path}.{i}.{k} is not a satellite id"))?);
            }
            out.push(r);
        }
        Ok(Some(out))
    }

    fn f3(&self, path: &str) -> Result<[f64; 3], String> {
        let arr = self.get(path)?.as_array().ok_or_else(|| format!("scenario: {path} is not a list"))?;
        if arr.len() != 3 {
            return Err(format!("scenario: {path}: {} numbers, expected 3", arr.len()));
        }
        let mut out = [0.0; 3];
        for (k, v) in arr.iter().enumerate() {
            out[k] = v.as_str().and_then(|s| s.parse().ok()).ok_or_else(|| format!("scenario: {path}.{k} is not a number"))?;
        }
        Ok(out)
    }
}

/// Why this agent cannot fly a scenario (the message names the field), or None.
pub type Refusal = String;

impl Scenario {
    /// Parse the resolved scenario; `Err` for a malformed document or a scenario this agent
    /// does not fly (a message naming the field).
    pub fn from_json(text: &str) -> Result<Scenario, Refusal> {
        let v: Value = serde_json::from_str(&quote_numbers(text)).map_err(|e| format!("scenario JSON: {e}"))?;
        let d = Doc(v);
        // What this agent flies: ci, the ideal radio in lockstep, synthetic cameras.
        let kind = d.s("estimator.kind")?;
        if kind != "ci" {
            return Err(format!("estimator.kind: {kind:?}: this agent flies the ci estimator only (estimator.kind: ci)"));
        }
        let pipeline = d.s("vision.pipeline")?;
        if pipeline != "none" {
            return Err(format!(
                "vision.pipeline: {pipeline:?}: this agent measures synthetic camera detections only (vision.pipeline: none)"
            ));
        }
        // With links the radio's deliveries (rx/<i>) may be late: this agent drops late
        // batches (and counts them), it does not replay them.
        let links_enabled = d.b("links.enabled")?;
        if links_enabled {
            let late = d.s("filter.late")?;
            if late != "drop" {
                return Err(format!(
                    "filter.late: {late:?} with links.enabled: this agent drops late batches and does not replay them (filter.late: drop)"
                ));
            }
        }
        let mode = d.s("emulator.time_mode")?;
        if mode != "lockstep" {
            return Err(format!("emulator.time_mode: {mode:?}: this agent runs in lockstep only"));
        }
        // Relative motion by Hill–Clohessy–Wiltshire only (a later orbit model, if a scenario
        // names one, is refused rather than flown wrongly).
        // `filter.dynamics: auto` follows `orbit.model`, checked first.
        for (field, allowed) in [("orbit.model", &["hcw"][..]), ("filter.dynamics", &["hcw", "auto"][..])] {
            if let Ok(v) = d.get(field) {
                if !v.as_str().is_some_and(|s| allowed.contains(&s)) {
                    return Err(format!("{field}: {v}: this agent predicts by Hill–Clohessy–Wiltshire only (hcw)"));
                }
            }
        }
        // Pose measurements only: an angles-only camera's bearings are refused, not misread.
        if let Ok(v) = d.get("sensors.relative.model") {
            if v.as_str() == Some("bearing") {
                return Err("sensors.relative.model: \"bearing\": this agent fuses relative pose measurements only".into());
            }
        }
        let strategy = d.s("selection.strategy")?;
        if !matches!(strategy, "none" | "complete" | "random" | "random_tree") {
            return Err(format!(
                "selection.strategy: {strategy:?} plans from every satellite's full-swarm covariance, which the ci \
                                estimator does not keep; use none, complete, random or random_tree"
            ));
        }
        let mut ci = CiParams::default();
        if let Some(obj) = d.get("estimator")?.as_object() {
            for (key, val) in obj {
                match key.as_str() {
                    "kind" => {}
                    "split" => ci.split = val.as_bool().ok_or("estimator.split: not true or false")?,
                    "correlated_peers" => ci.correlated_peers = val.as_bool().ok_or("estimator.correlated_peers: not true or false")?,
                    "criterion" => match val.as_str() {
                        Some("det") => ci.criterion_det = true,
                        Some("trace") => ci.criterion_det = false,
                        _ => return Err(format!("estimator.criterion: {val}: det or trace")),
                    },
                    other => return Err(format!("estimator.{other}: not a parameter of the ci estimator")),
                }
            }
        }
        let gate = if d.b("filter.gate.enabled")? {
            Some(d.opt_f("derived.gate_threshold")?.ok_or("derived.gate_threshold: null with the gate enabled")?)
        } else {
            None
        };
        let dt = d.f("dt_s")?;
        let initial_sigma = InitialSigma {
            att_rad: d.f("filter.initial_sigma.att_rad")?,
            rate_rad_s: d.f("filter.initial_sigma.rate_rad_s")?,
            bias_rad_s: d.f("filter.initial_sigma.bias_rad_s")?,
            pos_m: d.f("filter.initial_sigma.pos_m")?,
            vel_m_s: d.f("filter.initial_sigma.vel_m_s")?,
        };
        let filter = FilterParams::new(
            dt,
            d.f("orbit.mean_motion_rad_s")?,
            d.f("sensors.gyro.arw_rad_sqrt_s")?,
            d.f("sensors.gyro.rrw_rad_s15")?,
            d.f("disturbances.accel_sigma_m_s15")?,
            d.f("filter.pos_rw_m_sqrt_s")?,
            gate,
            initial_sigma.rate_rad_s,
        );
        let relative = match d.s("sensors.relative.model")? {
            "isotropic" => RelativeModel::Isotropic {
                sigma_att: d.f("sensors.relative.sigma_att_rad")?,
                sigma_pos: d.f("sensors.relative.sigma_pos_m")?,
            },
            "camera" => RelativeModel::Camera {
                sigma_att_c: d.f3("sensors.relative.sigma_att_camera_rad")?,
                sigma_pos_c: d.f3("sensors.relative.sigma_pos_camera_m")?,
                range_exponent: d.f("sensors.relative.range_exponent")?,
                reference_range: d.f("sensors.relative.reference_range_m")?,
            },
            other => return Err(format!("sensors.relative.model: {other:?}")),
        };
        let n_sats = d.u("n_sats")? as usize;
        if !(2..=10_000).contains(&n_sats) {
            return Err(format!("n_sats: {n_sats}"));
        }
        let radio_peers = d.opt_id_lists("derived.radio_peers")?;
        if let Some(rp) = &radio_peers {
            if rp.len() != n_sats || rp.iter().flatten().any(|&j| j as usize >= n_sats) {
                return Err(format!("derived.radio_peers: {} lists, expected one per satellite (0..{n_sats})", rp.len()));
            }
        }
        Ok(Scenario {
            links_enabled,
            radio_peers,
            name: d.s("name")?.to_string(),
            seed: d.u("seed")?,
            n_sats,
            filter,
            ci,
            relative,
            initial_sigma,
            velocity_max_m_s: d.f("initial.velocity_max_m_s")?,
            emulator: Emulator {
                step_timeout_s: d.f("emulator.step_timeout_s")?,
                startup_timeout_s: d.f("emulator.startup_timeout_s")?,
                liveliness_hold_s: d.f("emulator.liveliness_hold_s")?,
                bus_grace_s: d.f("emulator.bus_grace_s")?,
                bus_lost_after_s: d.f("emulator.bus_lost_after_s")?,
                shutdown_linger_s: d.f("emulator.shutdown_linger_s")?,
                recorder_max_lag_steps: d.f("emulator.recorder_max_lag_steps")?.max(1.0) as usize,
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_quoted_outside_strings() {
        let q = quote_numbers(r#"{"a": -1.5e-3, "b": "x1 \"2\"", "c": [1, 2.0], "d": null, "e": true}"#);
        assert_eq!(q, r#"{"a": "-1.5e-3", "b": "x1 \"2\"", "c": ["1", "2.0"], "d": null, "e": true}"#);
    }
}
