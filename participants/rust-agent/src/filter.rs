//! The filter maths a `ci` agent needs, after `swarmcore/mekf.py` and `swarmcore/dynamics.py`:
//! the own satellite's prediction in gyro mode, the relative-measurement residuals and
//! Jacobians, the χ² gate, the update in the three forms of the Python filter (stacked
//! Joseph, sequential Joseph, square-root information; `auto` chooses as it does), the
//! iterated update, and the multiplicative attitude reset.
//!
//! Error state of a satellite's 12-block: `[a, Δω|Δβ, Δr, Δv]` (own: gyro bias), `a` in its
//! body frame with `q = δq(a) ⊗ q̂`.

use crate::linalg::{expm, Mat, NotPd};
use crate::quat::{self, M3, Q, V3};

pub const BLOCK: usize = 12;
/// The pose rows [a, Δr] of a 12-state block.
pub const POSE: [usize; 6] = [0, 1, 2, 6, 7, 8];
pub type M6 = [[f64; 6]; 6];
pub type V6 = [f64; 6];

/// What the filter needs of the scenario (`swarmcore.agent.filter_params`).
#[derive(Clone, Debug)]
pub struct FilterParams {
    pub dt: f64,
    pub mean_motion: f64,
    pub arw: f64,
    pub rrw: f64,
    pub gate_threshold: Option<f64>,
    pub missing_gyro_rate_sigma: f64,
    pub phi_trans: Mat, // 6×6 HCW transition over dt
    pub q_trans: Mat,   // 6×6 HCW process noise over dt
}

impl FilterParams {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        dt: f64,
        mean_motion: f64,
        arw: f64,
        rrw: f64,
        accel: f64,
        pos_rw: f64,
        gate_threshold: Option<f64>,
        missing_gyro_rate_sigma: f64,
    ) -> FilterParams {
        FilterParams {
            dt,
            mean_motion,
            arw,
            rrw,
            gate_threshold,
            missing_gyro_rate_sigma,
            phi_trans: hcw_phi(mean_motion, dt),
            q_trans: hcw_noise_cov(mean_motion, dt, accel, pos_rw),
        }
    }
}

/// An estimate of `m` satellites (row 0 the own one, in gyro mode): `SwarmEstimate`.
#[derive(Clone, Debug)]
pub struct Est {
    pub step: u64,
    pub t: f64,
    pub q: Vec<Q>,
    pub w: Vec<V3>,
    pub r: Vec<V3>,
    pub v: Vec<V3>,
    pub bias: V3,
    pub p: Mat,
}

impl Est {
    pub fn n(&self) -> usize {
        self.q.len()
    }
}

/// A relative measurement: observer i sees target j (ids are rows of the estimate it is
/// applied to, or satellite ids, as the caller says).
#[derive(Clone, Debug)]
pub struct Rel {
    pub observer: usize,
    pub target: usize,
    pub q: Q,    // q_BjBi
    pub r: V3,   // r_ij_Bi (m)
    pub cov: M6, // R_Bi [att, pos]
}

/// Sorted by (observer, target), stably: the order every filter applies them in.
pub fn canonical(rel: &mut [Rel]) {
    rel.sort_by_key(|m| (m.observer, m.target));
}

/// The own satellite's star tracker and GPS at one instant.
#[derive(Clone, Debug)]
pub struct Absolute {
    pub q: Option<Q>,
    pub r: Option<V3>,
    pub sigma_att: f64,
    pub sigma_pos: f64,
}

// ----------------------------------------------------------------------------- dynamics

/// Closed-form HCW transition over `dt` for `[r, v]` (`dynamics.hcw_phi`).
pub fn hcw_phi(n: f64, dt: f64) -> Mat {
    let (c, s) = ((n * dt).cos(), (n * dt).sin());
    let nt = n * dt;
    let rows = [
        [4.0 - 3.0 * c, 0.0, 0.0, s / n, 2.0 * (1.0 - c) / n, 0.0],
        [6.0 * (s - nt), 1.0, 0.0, 2.0 * (c - 1.0) / n, (4.0 * s - 3.0 * nt) / n, 0.0],
        [0.0, 0.0, c, 0.0, 0.0, s / n],
        [3.0 * n * s, 0.0, 0.0, c, 2.0 * s, 0.0],
        [6.0 * n * (c - 1.0), 0.0, 0.0, -2.0 * s, 4.0 * c - 3.0, 0.0],
        [0.0, 0.0, -n * s, 0.0, 0.0, c],
    ];
    Mat::from_rows(6, 6, &rows.concat())
}

fn hcw_a(n: f64) -> Mat {
    let mut a = Mat::zeros(6, 6);
    for i in 0..3 {
        a.set(i, 3 + i, 1.0);
    }
    a.set(3, 0, 3.0 * n * n);
    a.set(3, 4, 2.0 * n);
    a.set(4, 3, -2.0 * n);
    a.set(5, 2, -n * n);
    a
}

/// Discrete HCW process noise over `dt` (Van Loan), `dynamics.hcw_noise_cov`.
pub fn hcw_noise_cov(n: f64, dt: f64, sigma_acc: f64, sigma_pos: f64) -> Mat {
    let g = Mat::diag(&[sigma_pos, sigma_pos, sigma_pos, sigma_acc, sigma_acc, sigma_acc]);
    let f = hcw_a(n);
    let mut a = Mat::zeros(12, 12);
    a.set_block(0, 0, &f.scale(dt).scale(-1.0));
    a.set_block(0, 6, &g.mul(&g.t()).scale(dt));
    a.set_block(6, 6, &f.t().scale(dt));
    let b = expm(&a);
    let q = b.block(6, 6, 6, 6).t().mul(&b.block(0, 6, 6, 6));
    q.sym()
}

/// `T_IH(t)`: H coordinates to I coordinates (a rotation about z by n t).
pub fn t_ih(n: f64, t: f64) -> M3 {
    let (c, s) = ((n * t).cos(), (n * t).sin());
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// Van Loan discretisation of the own satellite's attitude block `[a, Δβ]` (gyro mode):
/// `ȧ = −[ω̂×] a − Δβ`, `Δβ̇ = 0`, noise arw² on a, rrw² on Δβ (`mekf.attitude_phi_q`).
fn attitude_phi_q_own(w: &V3, p: &FilterParams) -> (Mat, Mat) {
    let mut f = Mat::zeros(6, 6);
    let sk = quat::skew(w);
    for i in 0..3 {
        for j in 0..3 {
            f.set(i, j, -sk[i][j]);
        }
        f.set(i, 3 + i, -1.0);
    }
    let mut gqg = Mat::zeros(6, 6);
    for i in 0..3 {
        gqg.set(i, i, p.arw * p.arw);
        gqg.set(3 + i, 3 + i, p.rrw * p.rrw);
    }
    let mut a = Mat::zeros(12, 12);
    a.set_block(0, 0, &f.scale(-1.0));
    a.set_block(0, 6, &gqg);
    a.set_block(6, 6, &f.t());
    let b = expm(&a.scale(p.dt));
    let phi = b.block(6, 6, 6, 6).t();
    let q = phi.mul(&b.block(0, 6, 6, 6));
    (phi, q.sym())
}

/// Predict a one-satellite estimate (own, gyro mode) by one step (`mekf.predict`, n = 1).
/// `gyro`: the gyro's mean rate over the step (bias included); None holds the last rate.
pub fn predict_own(est: &Est, p: &FilterParams, gyro: Option<&V3>) -> Est {
    assert_eq!(est.n(), 1, "predict_own: an estimate of the own satellite alone");
    let w_own: V3 = match gyro {
        Some(g) => [g[0] - est.bias[0], g[1] - est.bias[1], g[2] - est.bias[2]],
        None => est.w[0],
    };
    let (phi_att, mut q_att) = attitude_phi_q_own(&w_own, p);
    if gyro.is_none() {
        let v = (p.missing_gyro_rate_sigma * p.dt) * (p.missing_gyro_rate_sigma * p.dt);
        for i in 0..3 {
            q_att.add_at(i, i, v);
        }
    }
    let mut phi = Mat::zeros(12, 12);
    let mut qn = Mat::zeros(12, 12);
    phi.set_block(0, 0, &phi_att);
    qn.set_block(0, 0, &q_att);
    phi.set_block(6, 6, &p.phi_trans);
    qn.set_block(6, 6, &p.q_trans);
    let q_new = quat::propagate_constant_rate(&est.q[0], &w_own, p.dt);
    let x = [est.r[0][0], est.r[0][1], est.r[0][2], est.v[0][0], est.v[0][1], est.v[0][2]];
    let rv = p.phi_trans.mul_vec(&x);
    let right = phi.mul(&est.p).mul_t(&phi).add(&qn);
    Est {
        step: est.step.saturating_add(1),
        t: est.t + p.dt,
        q: vec![q_new],
        w: vec![w_own],
        r: vec![[rv[0], rv[1], rv[2]]],
        v: vec![[rv[3], rv[4], rv[5]]],
        bias: est.bias,
        p: right.sym(),
    }
}

// ---------------------------------------------------------------------------- residuals

/// Residuals and Jacobian blocks of relative measurements (rows of `est`), the compiled
/// kernel `kernels._relative_residuals` operation for operation.
pub fn relative_residuals(est: &Est, mean_motion: f64, meas: &[Rel]) -> (Vec<V6>, Vec<M6>, Vec<M6>) {
    let n = est.n();
    let tih = t_ih(mean_motion, est.t);
    let mut t_all = Vec::with_capacity(n);
    let mut c_all = Vec::with_capacity(n);
    for s in 0..n {
        let t = quat::attitude_matrix(&est.q[s]);
        let mut c = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                c[a][b] = t[a][0] * tih[0][b] + t[a][1] * tih[1][b] + t[a][2] * tih[2][b];
            }
        }
        t_all.push(t);
        c_all.push(c);
    }
    let mut ys = Vec::with_capacity(meas.len());
    let mut his = Vec::with_capacity(meas.len());
    let mut hjs = Vec::with_capacity(meas.len());
    for m in meas {
        let (i, j) = (m.observer, m.target);
        let (ri, rj) = (&est.r[i], &est.r[j]);
        let (d0, d1, d2) = (rj[0] - ri[0], rj[1] - ri[1], rj[2] - ri[2]);
        let c = &c_all[i];
        let rh0 = c[0][0] * d0 + c[0][1] * d1 + c[0][2] * d2;
        let rh1 = c[1][0] * d0 + c[1][1] * d1 + c[1][2] * d2;
        let rh2 = c[2][0] * d0 + c[2][1] * d1 + c[2][2] * d2;
        let qi = &est.q[i];
        let h = quat::qmul(&est.q[j], &[-qi[0], -qi[1], -qi[2], qi[3]]);
        let e = quat::qmul(&[-h[0], -h[1], -h[2], h[3]], &m.q);
        let y = [2.0 * e[0] / e[3], 2.0 * e[1] / e[3], 2.0 * e[2] / e[3], m.r[0] - rh0, m.r[1] - rh1, m.r[2] - rh2];
        let mut hi = [[0.0; 6]; 6];
        let mut hj = [[0.0; 6]; 6];
        let (ti, tj) = (&t_all[i], &t_all[j]);
        for a in 0..3 {
            hi[a][a] = -1.0;
            for b in 0..3 {
                hj[a][b] = ti[a][0] * tj[b][0] + ti[a][1] * tj[b][1] + ti[a][2] * tj[b][2];
                hi[3 + a][3 + b] = -c[a][b];
                hj[3 + a][3 + b] = c[a][b];
            }
        }
        hi[3][1] = -rh2;
        hi[3][2] = rh1;
        hi[4][0] = rh2;
        hi[4][2] = -rh0;
        hi[5][0] = -rh1;
        hi[5][1] = rh0;
        ys.push(y);
        his.push(hi);
        hjs.push(hj);
    }
    (ys, his, hjs)
}

/// The own satellite's absolute residual, Jacobian rows on its [a, Δr] and R's diagonal.
pub fn absolute_residual(est: &Est, own: usize, a: &Absolute) -> Option<(Vec<f64>, Vec<usize>, Vec<f64>)> {
    let mut y = Vec::new();
    let mut rows = Vec::new();
    let mut var = Vec::new();
    if let Some(q) = &a.q {
        let e = quat::local(q, &est.q[own]);
        for k in 0..3 {
            y.push(e[k]);
            rows.push(k);
            var.push(a.sigma_att * a.sigma_att);
        }
    }
    if let Some(r) = &a.r {
        for k in 0..3 {
            y.push(r[k] - est.r[own][k]);
            rows.push(3 + k);
            var.push(a.sigma_pos * a.sigma_pos);
        }
    }
    if y.is_empty() {
        None
    } else {
        Some((y, rows, var))
    }
}

// --------------------------------------------------------------------------------- gate

/// Cholesky of a 6×6 SPD matrix into `l` (lower), `kernels._chol6`; false if not PD.
fn chol6(a: &M6, l: &mut M6) -> bool {
    for c in 0..6 {
        let mut s = a[c][c];
        for k in 0..c {
            s -= l[c][k] * l[c][k];
        }
        if s <= 0.0 || s.is_nan() {
            return false;
        }
        l[c][c] = s.sqrt();
        for r in c + 1..6 {
            let mut t = a[r][c];
            for k in 0..c {
                t -= l[r][k] * l[c][k];
            }
            l[r][c] = t / l[c][c];
        }
    }
    true
}

pub fn observed_indices(n: usize) -> Vec<usize> {
    (0..n).flat_map(|b| POSE.iter().map(move |k| BLOCK * b + k)).collect()
}

/// Squared Mahalanobis distance of each relative measurement against the prior,
/// `kernels._gate_d2` operation for operation (∞ where S is not positive-definite).
pub fn gate_d2(p_oo: &Mat, meas: &[Rel], y: &[V6], hi: &[M6], hj: &[M6]) -> Vec<f64> {
    let mut out = Vec::with_capacity(meas.len());
    let mut l = [[0.0; 6]; 6];
    let mut z = [0.0; 6];
    for (k, m) in meas.iter().enumerate() {
        let (oi, oj) = (6 * m.observer, 6 * m.target);
        let mut pm = [[0.0; 12]; 12];
        let mut h = [[0.0; 12]; 6];
        for r in 0..6 {
            for c in 0..6 {
                pm[r][c] = p_oo.at(oi + r, oi + c);
                pm[r][c + 6] = p_oo.at(oi + r, oj + c);
                pm[r + 6][c] = p_oo.at(oj + r, oi + c);
                pm[r + 6][c + 6] = p_oo.at(oj + r, oj + c);
                h[r][c] = hi[k][r][c];
                h[r][c + 6] = hj[k][r][c];
            }
        }
        let mut hp = [[0.0; 12]; 6];
        for r in 0..6 {
            for c in 0..12 {
                let mut s = 0.0;
                for q in 0..12 {
                    s += h[r][q] * pm[q][c];
                }
                hp[r][c] = s;
            }
        }
        let mut sm = [[0.0; 6]; 6];
        for r in 0..6 {
            for c in 0..6 {
                let mut s = m.cov[r][c];
                for q in 0..12 {
                    s += hp[r][q] * h[c][q];
                }
                sm[r][c] = s;
            }
        }
        for r in 0..6 {
            for c in 0..r {
                let v = 0.5 * (sm[r][c] + sm[c][r]);
                sm[r][c] = v;
                sm[c][r] = v;
            }
        }
        if !chol6(&sm, &mut l) {
            out.push(f64::INFINITY);
            continue;
        }
        let mut d2 = 0.0;
        for r in 0..6 {
            let mut t = y[k][r];
            for q in 0..r {
                t -= l[r][q] * z[q];
            }
            z[r] = t / l[r][r];
            d2 += z[r] * z[r];
        }
        out.push(d2);
    }
    out
}

// ------------------------------------------------------------------------------- update

/// The gate of each relative measurement (rows of `est`) against the prior
/// (`mekf.gate`): residuals, Jacobian blocks, d² and the verdicts (all accepted without a
/// threshold).
pub fn gate(est: &Est, p: &FilterParams, rel: &[Rel]) -> (Vec<V6>, Vec<M6>, Vec<M6>, Vec<f64>, Vec<bool>) {
    let (y, hi, hj) = relative_residuals(est, p.mean_motion, rel);
    if rel.is_empty() {
        return (y, hi, hj, vec![], vec![]);
    }
    let o = observed_indices(est.n());
    let p_oo = est.p.take(&o, &o);
    let d2 = gate_d2(&p_oo, rel, &y, &hi, &hj);
    let acc = match p.gate_threshold {
        None => vec![true; rel.len()],
        Some(th) => d2.iter().map(|&d| d <= th).collect(),
    };
    (y, hi, hj, d2, acc)
}

/// Multiplicative attitude reset and additive corrections (`mekf.apply_correction`).
pub fn apply_correction(est: &Est, own: usize, dx: &[f64], p: &Mat) -> Est {
    let n = est.n();
    let mut out = Est {
        step: est.step,
        t: est.t,
        q: Vec::with_capacity(n),
        w: est.w.clone(),
        r: est.r.clone(),
        v: est.v.clone(),
        bias: est.bias,
        p: p.sym(),
    };
    for s in 0..n {
        let d = &dx[BLOCK * s..BLOCK * (s + 1)];
        out.q.push(quat::retract(&est.q[s], &[d[0], d[1], d[2]]));
        for k in 0..3 {
            out.w[s][k] = est.w[s][k] + d[3 + k];
            out.r[s][k] = est.r[s][k] + d[6 + k];
            out.v[s][k] = est.v[s][k] + d[9 + k];
        }
    }
    let d = &dx[BLOCK * own..BLOCK * (own + 1)];
    for k in 0..3 {
        out.bias[k] = est.bias[k] + d[3 + k];
        out.w[own][k] = est.w[own][k] - d[3 + k];
    }
    out
}

/// The Kalman update of a one-satellite estimate in Joseph form with the multiplicative
/// reset: prior covariance `p`, measurement `y = H x + ν` with `H` (rows × 12) and noise
/// `r`. Returns the posterior and the gain (`K y` is the correction).
pub fn joseph_update(est: &Est, p: &Mat, h: &Mat, r: &Mat, y: &[f64]) -> Result<(Est, Mat), NotPd> {
    let pht = p.mul_t(h);
    let s = h.mul(&pht).add(r);
    let k = s.solve(&pht.t())?.t();
    let a = Mat::eye(BLOCK).sub(&k.mul(h));
    let post = a.mul(p).mul_t(&a).add(&k.mul(r).mul_t(&k));
    let dx = k.mul_vec(y);
    Ok((apply_correction(est, 0, &dx, &post), s))
}

/// The own star tracker and GPS on a one-satellite estimate (`own.absolute_update`): a
/// Kalman update in Joseph form on its 12 states with the multiplicative reset. Returns the
/// posterior, its NIS and degrees of freedom.
pub fn absolute_update(est: &Est, a: &Absolute) -> Result<(Est, f64, usize), NotPd> {
    let Some((y, rows, var)) = absolute_residual(est, 0, a) else { return Ok((est.clone(), 0.0, 0)) };
    let mut h = Mat::zeros(y.len(), BLOCK);
    for (i, &row) in rows.iter().enumerate() {
        h.set(i, POSE[row], 1.0);
    }
    let (post, s) = joseph_update(est, &est.p, &h, &Mat::diag(&var), &y)?;
    let sy = s.solve(&Mat::from_rows(y.len(), 1, &y))?;
    let nis = y.iter().zip(&sy.d).fold(0.0, |acc, (a, b)| acc + a * b);
    Ok((post, nis, y.len()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> FilterParams {
        FilterParams::new(1.0, 1.08e-3, 3.16e-7, 3.16e-10, 1e-8, 5e-5, Some(22.457744484825323), 1e-3)
    }

    #[test]
    fn hcw_noise_is_symmetric_and_positive() {
        let q = hcw_noise_cov(1.08e-3, 1.0, 1e-8, 5e-5);
        assert!(q.sub(&q.t()).max_abs() == 0.0);
        assert!(q.cholesky().is_ok());
        assert!((q.at(0, 0) - 2.5e-9).abs() < 1e-12);
    }

    #[test]
    fn the_star_tracker_and_gps_pull_the_estimate_to_their_readings() {
        let mut p = Mat::zeros(12, 12);
        for (k, v) in [1e-4, 1e-4, 1e-4, 1e-10, 1e-10, 1e-10, 1e-2, 1e-2, 1e-2, 1e-6, 1e-6, 1e-6].iter().enumerate() {
            p.set(k, k, *v);
        }
        let est = Est {
            step: 0,
            t: 0.0,
            q: vec![quat::unit_canonical(&[0.1, 0.2, -0.3, 0.9])],
            w: vec![[0.0; 3]],
            r: vec![[1.0, 2.0, 3.0]],
            v: vec![[0.0; 3]],
            bias: [0.0; 3],
            p,
        };
        let truth_q = quat::retract(&est.q[0], &[1e-3, -2e-3, 5e-4]);
        let ab = Absolute { q: Some(truth_q), r: Some([1.05, 1.98, 3.0]), sigma_att: 2.9e-5, sigma_pos: 0.01 };
        let (post, nis, dof) = absolute_update(&est, &ab).unwrap();
        assert_eq!(dof, 6);
        assert!(nis > 0.0);
        let left = quat::local(&truth_q, &post.q[0]);
        assert!(left.iter().all(|x| x.abs() < 1e-6), "{left:?}");
        assert!((post.r[0][0] - 1.05).abs() < 0.01);
        assert!(post.p.at(0, 0) < 1e-9 && post.p.at(6, 6) < 1e-4);
        let _ = params();
    }
}
