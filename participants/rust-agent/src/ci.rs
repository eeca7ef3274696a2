//! The `ci` estimator (`swarmcore/estimators/ci.py`): decentralized cooperative localization
//! by split covariance intersection (Carrillo-Arce et al. 2013; Julier & Uhlmann 2001).
//!
//! The agent keeps its own satellite's 12 error states `[a, Δβ, Δr, Δv]` (gyro mode) and
//! broadcasts its prior pose each step ([`CiState`]). Each step: the own star tracker and
//! GPS update the prior (a plain Kalman update); then every relative measurement of the step
//! that involves the own satellite and whose peer's broadcast came is gated against
//! `S = Hᵢ Pᵢ Hᵢᵀ + Hp Pp Hpᵀ + R` and fused at once with one ω:
//! `P⁺⁻¹ = ω P⁻¹ + (1 − ω) Hᵀ C⁻¹ H`, `C = R + m Hp Pp Hpᵀ / (1 − ω)` (split CI, the peers'
//! mutual correlation bounded by m × their block diagonal for m peers), ω minimising
//! `log det P⁺` by bounded Brent on [1e-4, 1 − 1e-4].

use std::collections::BTreeMap;

use crate::brent::fminbound;
use crate::filter::{self, canonical, Absolute, Est, FilterParams, Rel, BLOCK, POSE};
use crate::linalg::{eigh, Mat, NotPd};
use crate::quat::{self, Q, V3};

/// Variance given to a peer's rate and velocity states in the joint update (they cannot
/// reach the own posterior: any positive value gives the same result).
const UNUSED_VAR: f64 = 1.0;

#[derive(Clone, Debug)]
pub struct CiParams {
    pub split: bool,
    pub criterion_det: bool,
    pub correlated_peers: bool,
}

impl Default for CiParams {
    fn default() -> Self {
        CiParams { split: true, criterion_det: true, correlated_peers: true }
    }
}

/// What a `ci` agent broadcasts each step: its prior pose at the step.
#[derive(Clone, Debug)]
pub struct CiState {
    pub q: Q,
    pub w: V3,
    pub r: V3,
    pub v: V3,
    pub p_pose: Mat, // 6 × 6 over [a, Δr]
}

/// One peer transmission the radio delivered.
#[derive(Clone, Debug)]
pub struct Received {
    pub sender: usize,
    pub step: u64,
    pub meas: Vec<Rel>, // satellite ids
    pub payload: Option<CiState>,
}

/// Everything the estimator learns at a step (`StepInputs`).
#[derive(Clone, Debug)]
pub struct StepInputs {
    pub step: u64,
    pub t: f64,
    pub gyro: Option<V3>,
    pub absolute: Option<Absolute>,
    pub own: Vec<Rel>,           // observer = own
    pub received: Vec<Received>, // ordered by (step, sender)
}

#[derive(Clone, Debug)]
pub struct StepReport {
    pub gate_accepted: u32,
    pub gate_rejected: u32,
    pub nis: f64,
    pub nis_dof: u32,
    pub iterations: u32,
    pub late_used: u32,
    pub late_dropped: u32,
    pub replayed_steps: u32,
}

/// What the estimator claims (`EstimateView`): rows `ids` (ascending, own among them).
#[derive(Clone, Debug)]
pub struct View {
    pub step: u64,
    pub t: f64,
    pub own: usize,
    pub ids: Vec<usize>,
    pub q: Vec<Q>,
    pub w: Vec<V3>,
    pub r: Vec<V3>,
    pub v: Vec<V3>,
    pub bias: V3,
    pub p_pose: Vec<Mat>,
    pub p_rel_pose: Vec<Mat>,
    pub p_diag: Vec<f64>,
}

pub fn pose_block(p12: &Mat) -> Mat {
    p12.take(&POSE, &POSE)
}

pub struct Ci {
    pub own: usize,
    pub fp: FilterParams,
    pub params: CiParams,
    est: Option<Est>,
    pending: bool,
    peers: BTreeMap<usize, CiState>,
    /// The peers whose measurements it fused at the current step (its view's rows).
    used: Vec<usize>,
    pub unusable: u64,
    pub last_omega: Option<f64>,
}

impl Ci {
    pub fn new(own: usize, fp: FilterParams, params: CiParams) -> Ci {
        Ci { own, fp, params, est: None, pending: true, peers: BTreeMap::new(), used: vec![], unusable: 0, last_omega: None }
    }

    pub fn start(&mut self, prior: Est, step_pending: bool) {
        assert_eq!(prior.n(), 1, "ci: a prior of its own satellite only");
        self.est = Some(prior);
        self.pending = step_pending;
    }

    pub fn started(&self) -> bool {
        self.est.is_some()
    }

    pub fn e(&self) -> &Est {
        self.est.as_ref().expect("ci estimator not started")
    }

    pub fn step_index(&self) -> u64 {
        self.e().step
    }

    /// Bring a posterior to step `k − 1` across missed steps (predictions only).
    pub fn coast_to(&mut self, k: u64, mut gyro_of: impl FnMut(u64) -> Option<V3>) {
        if self.pending && self.e().step < k {
            self.pending = false;
        }
        while self.e().step.saturating_add(1) < k {
            let g = gyro_of(self.e().step.saturating_add(1));
            let next = filter::predict_own(self.e(), &self.fp, g.as_ref());
            self.est = Some(next);
        }
    }

    /// Predict to step `k` (its prior of the step) before anything of k is measured.
    pub fn predict(&mut self, k: u64, gyro: Option<&V3>) {
        if !self.pending && self.e().step.saturating_add(1) == k {
            let next = filter::predict_own(self.e(), &self.fp, gyro);
            self.est = Some(next);
            self.pending = true;
        }
    }

    /// Its message of step `k`: its prior pose.
    pub fn transmit(&self, k: u64) -> Result<CiState, String> {
        let e = self.e();
        if e.step != k {
            return Err(format!("ci estimator of satellite {}: transmit({k}) with its estimate at step {}", self.own, e.step));
        }
        Ok(CiState { q: e.q[0], w: e.w[0], r: e.r[0], v: e.v[0], p_pose: pose_block(&e.p) })
    }

    /// A cold start from the own star tracker and GPS (`base.cold_prior`): false when the
    /// step gives too little (no attitude or no position reading).
    #[allow(clippy::too_many_arguments)]
    pub fn cold_start(
        &mut self,
        inputs: &StepInputs,
        att_rad: f64,
        rate_rad_s: f64,
        bias_rad_s: f64,
        pos_m: f64,
        vel_m_s: f64,
        velocity_max_m_s: f64,
    ) -> bool {
        let Some(a) = &inputs.absolute else { return false };
        let (Some(q), Some(r)) = (a.q, a.r) else { return false };
        let att = a.sigma_att.max(att_rad);
        let pos = a.sigma_pos.max(pos_m);
        let vel = vel_m_s.max(velocity_max_m_s);
        let d = [att, att, att, bias_rad_s, bias_rad_s, bias_rad_s, pos, pos, pos, vel, vel, vel];
        let _ = rate_rad_s; // the own block holds its bias, not a rate
        let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let mut qn = [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
        if qn[3] < 0.0 {
            qn = [-qn[0], -qn[1], -qn[2], -qn[3]];
        }
        let prior = Est {
            step: inputs.step,
            t: inputs.t,
            q: vec![qn],
            w: vec![inputs.gyro.unwrap_or([0.0; 3])],
            r: vec![r],
            v: vec![[0.0; 3]],
            bias: [0.0; 3],
            p: Mat::diag(&d.map(|s| s * s)),
        };
        self.start(prior, false);
        true
    }

    /// Step `inputs.step`: predict (unless done), the absolute update, the CI fusion.
    pub fn step(&mut self, inputs: &StepInputs) -> Result<StepReport, String> {
        let k = inputs.step;
        if !self.pending {
            self.predict(k, inputs.gyro.as_ref());
        }
        if self.e().step != k {
            return Err(format!("ci estimator of satellite {}: step({k}) with its estimate at step {}", self.own, self.e().step));
        }
        let mut rep = StepReport {
            gate_accepted: 0,
            gate_rejected: 0,
            nis: f64::NAN,
            nis_dof: 0,
            iterations: 1,
            late_used: 0,
            late_dropped: 0,
            replayed_steps: 0,
        };
        // Late batches are dropped (filter.late: drop): counted as the Python ci counts them,
        // the late measurements of this satellite.
        let own = self.own;
        rep.late_dropped =
            inputs.received.iter().filter(|r| r.step < k).map(|r| r.meas.iter().filter(|m| m.target == own).count() as u32).sum();
        let (mut nis, mut dof) = (0.0, 0u32);
        if let Some(a) = &inputs.absolute {
            let (post, n, d) = filter::absolute_update(self.e(), a).map_err(|NotPd| "absolute update: not positive-definite")?;
            self.est = Some(post);
            nis += n;
            dof += d as u32;
        }
        self.peers = inputs.received.iter().filter(|r| r.step == k).filter_map(|r| r.payload.clone().map(|p| (r.sender, p))).collect();
        self.used.clear();
        let rel = self.involving_me(inputs);
        if !rel.is_empty() {
            let (acc, d2) = self.fuse(&rel).map_err(|NotPd| "ci update: not positive-definite".to_string())?;
            rep.gate_accepted = acc as u32;
            rep.gate_rejected = (rel.len() - acc) as u32;
            nis += d2;
            dof += 6 * acc as u32;
        }
        if dof > 0 {
            rep.nis = nis;
            rep.nis_dof = dof;
        }
        self.pending = false;
        Ok(rep)
    }

    /// Every measurement of this step that involves the own satellite and whose peer's
    /// estimate came, in canonical order.
    fn involving_me(&mut self, inputs: &StepInputs) -> Vec<Rel> {
        let me = self.own;
        let mut out = Vec::new();
        for m in &inputs.own {
            if self.peers.contains_key(&m.target) {
                out.push(m.clone());
            } else {
                self.unusable += 1;
            }
        }
        for r in inputs.received.iter().filter(|r| r.step == inputs.step) {
            let mine: Vec<&Rel> = r.meas.iter().filter(|m| m.target == me).collect();
            if mine.is_empty() {
                continue;
            }
            if self.peers.contains_key(&r.sender) {
                out.extend(mine.into_iter().cloned());
            } else {
                self.unusable += mine.len() as u64;
            }
        }
        canonical(&mut out);
        out
    }

    /// Gate, choose ω and apply the CI update; returns (accepted, their summed d²).
    ///
    /// The measurements are linearised on the joint [own, peers] estimate (residuals,
    /// Jacobian blocks and the gate's d²); the update is then the Kalman update of the own
    /// state with the prior `P/ω` and the measurement noise `C(ω)`, in Joseph form, with the
    /// multiplicative reset — the own block of the joint update (`ci.CIEstimator._fuse`).
    fn fuse(&mut self, rel: &[Rel]) -> Result<(usize, f64), NotPd> {
        let e = self.e().clone();
        let mut peers: Vec<usize> = rel.iter().flat_map(|m| [m.observer, m.target]).filter(|&s| s != self.own).collect();
        peers.sort_unstable();
        peers.dedup();
        self.used = peers.clone();
        let row = |s: usize| if s == self.own { 0 } else { 1 + peers.binary_search(&s).expect("a peer of the step") };
        let m = 1 + peers.len();
        let st: Vec<&CiState> = peers.iter().map(|j| &self.peers[j]).collect();
        let mut p = Mat::zeros(BLOCK * m, BLOCK * m);
        p.set_block(0, 0, &e.p);
        for (r, s) in st.iter().enumerate() {
            let mut blk = Mat::diag(&[UNUSED_VAR; BLOCK]);
            blk.put(&POSE, &POSE, &s.p_pose);
            p.set_block(BLOCK * (r + 1), BLOCK * (r + 1), &blk);
        }
        let joint = Est {
            step: e.step,
            t: e.t,
            q: std::iter::once(e.q[0]).chain(st.iter().map(|s| s.q)).collect(),
            w: std::iter::once(e.w[0]).chain(st.iter().map(|s| s.w)).collect(),
            r: std::iter::once(e.r[0]).chain(st.iter().map(|s| s.r)).collect(),
            v: std::iter::once(e.v[0]).chain(st.iter().map(|s| s.v)).collect(),
            bias: e.bias,
            p,
        };
        let mut local: Vec<Rel> = rel.iter().map(|x| Rel { observer: row(x.observer), target: row(x.target), ..x.clone() }).collect();
        canonical(&mut local);
        let (y, hi, hj, d2, accepted) = filter::gate(&joint, &self.fp, &local);
        let acc: Vec<usize> = (0..local.len()).filter(|&i| accepted[i]).collect();
        if acc.is_empty() {
            return Ok((0, 0.0));
        }
        // The accepted rows: Jacobian on the own [a, Δr] and on the peer's, noise R.
        let k = acc.len();
        let np = peers.len();
        let mut ho = Mat::zeros(6 * k, BLOCK);
        let mut hp = Mat::zeros(6 * k, 6 * np);
        let mut r = Mat::zeros(6 * k, 6 * k);
        let mut ys = Vec::with_capacity(6 * k);
        for (n, &i) in acc.iter().enumerate() {
            let mine_obs = local[i].observer == 0;
            let (h_own, h_peer) = if mine_obs { (&hi[i], &hj[i]) } else { (&hj[i], &hi[i]) };
            let peer_row = if mine_obs { local[i].target } else { local[i].observer } - 1;
            for a in 0..6 {
                for b in 0..6 {
                    ho.set(6 * n + a, POSE[b], h_own[a][b]);
                    hp.set(6 * n + a, 6 * peer_row + b, h_peer[a][b]);
                    r.set(6 * n + a, 6 * n + b, local[i].cov[a][b]);
                }
            }
            ys.extend_from_slice(&y[i]);
        }
        let mut pp = Mat::zeros(6 * np, 6 * np);
        for (n, s) in st.iter().enumerate() {
            pp.set_block(6 * n, 6 * n, &s.p_pose);
        }
        let bound = if self.params.correlated_peers { np as f64 } else { 1.0 };
        let c_p = hp.mul(&pp).mul_t(&hp).scale(bound);
        let split = self.params.split;
        let c_of = |w: f64| -> Mat {
            if split {
                r.add(&c_p.div(1.0 - w))
            } else {
                r.add(&c_p).div(1.0 - w)
            }
        };
        let w = if self.params.criterion_det {
            let cost = logdet_cost(&e.p, &ho, &r, &c_p, split)?;
            fminbound(cost, 1e-4, 1.0 - 1e-4, 1e-6, 500)
        } else {
            let cost = |w: f64| -> f64 {
                let pw = e.p.div(w);
                let s = ho.mul(&pw).mul_t(&ho).add(&c_of(w));
                match s.solve(&ho.mul(&pw)) {
                    Ok(x) => {
                        let kk = x.t();
                        let post = pw.sub(&kk.mul(&s).mul_t(&kk));
                        POSE.iter().fold(0.0, |acc, &i| acc + post.at(i, i))
                    }
                    Err(_) => f64::INFINITY,
                }
            };
            fminbound(cost, 1e-4, 1.0 - 1e-4, 1e-6, 500)
        };
        let (post, _) = filter::joseph_update(&e, &e.p.div(w), &ho, &c_of(w), &ys)?;
        self.est = Some(post);
        self.last_omega = Some(w);
        let sum_d2 = acc.iter().fold(0.0, |s, &i| s + d2[i]);
        Ok((k, sum_d2))
    }

    /// What it claims now: its own posterior and each peer it fused with at the step (their
    /// broadcast prior: what it knows of them), without cross-covariance.
    pub fn view(&self) -> View {
        let e = self.e();
        let mut ids: Vec<usize> = self.used.iter().copied().chain(std::iter::once(self.own)).collect();
        ids.sort_unstable();
        let mut v = View {
            step: e.step,
            t: e.t,
            own: self.own,
            ids: ids.clone(),
            q: vec![],
            w: vec![],
            r: vec![],
            v: vec![],
            bias: e.bias,
            p_pose: vec![],
            p_rel_pose: vec![],
            p_diag: vec![],
        };
        let own_pose = pose_block(&e.p);
        for &s in &ids {
            if s == self.own {
                v.q.push(e.q[0]);
                v.w.push(e.w[0]);
                v.r.push(e.r[0]);
                v.v.push(e.v[0]);
                v.p_pose.push(own_pose.clone());
                v.p_diag.extend(e.p.diagonal());
                v.p_rel_pose.push(Mat::zeros(6, 6));
            } else {
                let st = &self.peers[&s];
                v.q.push(st.q);
                v.w.push(st.w);
                v.r.push(st.r);
                v.v.push(st.v);
                v.p_pose.push(st.p_pose.clone());
                let mut d = [f64::NAN; BLOCK];
                for (a, &i) in POSE.iter().enumerate() {
                    d[i] = st.p_pose.at(a, a);
                }
                v.p_diag.extend(d);
                v.p_rel_pose.push(relative_pose_cov(&e.q[0], &st.q, &own_pose, &st.p_pose));
            }
        }
        v
    }
}

/// `cost(ω) = log det P⁺(ω) − log det P` of the CI update in 12 × 12 (`ci._logdet_cost`):
/// by Sylvester's identity `−12 log ω − log det(I + Ŵᵀ C̃(ω)⁻¹ Ŵ / ω)`, `Ŵ = Hₒ chol(P)` whitened
/// by a factor of the ω-independent part, in which `C̃(ω)` is diagonal (split: `R = L Lᵀ`,
/// `L⁻¹ C_p L⁻ᵀ = U Λ Uᵀ`, `C̃ = I + Λ/(1−ω)`; plain: `C̃ = I/(1−ω)`).
fn logdet_cost(p: &Mat, ho: &Mat, r: &Mat, c_p: &Mat, split: bool) -> Result<impl Fn(f64) -> f64, NotPd> {
    let hl = ho.mul(&p.cholesky()?); // (6k, 12)
    let (w, lam) = if split {
        let l = r.cholesky()?;
        let qt = l.lower_solve(&l.lower_solve(c_p).t());
        let (lam, u) = eigh(&qt.add(&qt.t()).scale(0.5));
        (u.t_mul(&l.lower_solve(&hl)), lam.into_iter().map(|x| x.max(0.0)).collect::<Vec<f64>>())
    } else {
        let l = r.add(c_p).cholesky()?;
        let w = l.lower_solve(&hl);
        let rows = w.r;
        (w, vec![0.0; rows])
    };
    let n = p.r;
    Ok(move |om: f64| -> f64 {
        let d: Vec<f64> = lam.iter().map(|&l| if split { (1.0 - om) / (1.0 - om + l) } else { 1.0 - om }).collect();
        let mut wt_d = w.t(); // (12, 6k), columns scaled by d
        for i in 0..wt_d.r {
            for (j, dj) in d.iter().enumerate() {
                let v = wt_d.at(i, j) * dj;
                wt_d.set(i, j, v);
            }
        }
        let g = wt_d.mul(&w).div(om);
        match Mat::eye(n).add(&g).logdet_spd() {
            Ok(ld) => -(n as f64) * om.ln() - ld,
            Err(_) => f64::INFINITY,
        }
    })
}

/// Covariance of a peer's pose relative to the own satellite, no cross-covariance
/// (`views.relative_pose_cov`): `P_jj + A P_ii Aᵀ`, `A = diag(−T(q_j ⊗ q_i⁻¹), −I)`.
fn relative_pose_cov(q_own: &Q, q_peer: &Q, p_own: &Mat, p_peer: &Mat) -> Mat {
    let t = quat::attitude_matrix(&quat::qmul(q_peer, &quat::qconj(q_own)));
    let mut a = Mat::zeros(6, 6);
    for i in 0..3 {
        for j in 0..3 {
            a.set(i, j, -t[i][j]);
        }
        a.set(3 + i, 3 + i, -1.0);
    }
    p_peer.add(&a.mul(p_own).mul_t(&a)).sym()
}
