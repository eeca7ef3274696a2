//! Quaternions, scalar LAST, Shuster convention (`swarmcore/quat.py`): `T(qa ⊗ qb) =
//! T(qa) T(qb)`, `T(q_BI) v_I = v_B`, attitude error `q = δq(a) ⊗ q̂` with
//! `δq(a) = normalise([a/2, 1])` and `a = 2 vec(δq) / δq4`. The formulas are those of the
//! compiled kernels (`swarmcore/kernels.py`: `_qmul_s`, `_att_matrix`, `_retract`,
//! `_rotate_constant_rate`), operation for operation.

pub type Q = [f64; 4];
pub type V3 = [f64; 3];
pub type M3 = [[f64; 3]; 3];

/// Shuster product `a ⊗ b = [a4 b_v + b4 a_v − a_v × b_v, a4 b4 − a_v·b_v]`.
#[inline]
pub fn qmul(a: &Q, b: &Q) -> Q {
    let (a0, a1, a2, a3) = (a[0], a[1], a[2], a[3]);
    let (b0, b1, b2, b3) = (b[0], b[1], b[2], b[3]);
    [
        a3 * b0 + b3 * a0 - (a1 * b2 - a2 * b1),
        a3 * b1 + b3 * a1 - (a2 * b0 - a0 * b2),
        a3 * b2 + b3 * a2 - (a0 * b1 - a1 * b0),
        a3 * b3 - (a0 * b0 + a1 * b1 + a2 * b2),
    ]
}

#[inline]
pub fn qconj(q: &Q) -> Q {
    [-q[0], -q[1], -q[2], q[3]]
}

/// The unit quaternion of `r` with a non-negative scalar part.
#[inline]
pub fn unit_canonical(r: &Q) -> Q {
    let mut nr = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]).sqrt();
    if r[3] < 0.0 {
        nr = -nr;
    }
    [r[0] / nr, r[1] / nr, r[2] / nr, r[3] / nr]
}

/// `T(q) = (q4² − |e|²) I + 2 e eᵀ − 2 q4 [e×]`.
pub fn attitude_matrix(q: &Q) -> M3 {
    let (e0, e1, e2, w) = (q[0], q[1], q[2], q[3]);
    let d = w * w - (e0 * e0 + e1 * e1 + e2 * e2);
    let mut t = [[0.0; 3]; 3];
    t[0][0] = d + 2.0 * e0 * e0;
    t[1][1] = d + 2.0 * e1 * e1;
    t[2][2] = d + 2.0 * e2 * e2;
    t[0][1] = 2.0 * e0 * e1 + 2.0 * w * e2;
    t[1][0] = 2.0 * e0 * e1 - 2.0 * w * e2;
    t[0][2] = 2.0 * e0 * e2 - 2.0 * w * e1;
    t[2][0] = 2.0 * e0 * e2 + 2.0 * w * e1;
    t[1][2] = 2.0 * e1 * e2 + 2.0 * w * e0;
    t[2][1] = 2.0 * e1 * e2 - 2.0 * w * e0;
    t
}

/// `q = normalise(δq(a) ⊗ q̂)` with a non-negative scalar part.
pub fn retract(q_hat: &Q, a: &V3) -> Q {
    let (d0, d1, d2) = (0.5 * a[0], 0.5 * a[1], 0.5 * a[2]);
    let nd = (d0 * d0 + d1 * d1 + d2 * d2 + 1.0).sqrt();
    unit_canonical(&qmul(&[d0 / nd, d1 / nd, d2 / nd, 1.0 / nd], q_hat))
}

/// `a = 2 vec(δq) / δq4`.
#[inline]
pub fn err_from_dq(dq: &Q) -> V3 {
    [2.0 * dq[0] / dq[3], 2.0 * dq[1] / dq[3], 2.0 * dq[2] / dq[3]]
}

/// Attitude error `a` with `q = δq(a) ⊗ q̂`.
pub fn local(q: &Q, q_hat: &Q) -> V3 {
    err_from_dq(&qmul(q, &qconj(q_hat)))
}

/// Exact attitude step at constant body rate: `rotvec(ω Δt) ⊗ q`, canonical sign.
pub fn propagate_constant_rate(q: &Q, w: &V3, dt: f64) -> Q {
    let (t0, t1, t2) = (w[0] * dt, w[1] * dt, w[2] * dt);
    let ang = (t0 * t0 + t1 * t1 + t2 * t2).sqrt();
    let k = if ang < 1e-8 { 0.5 - ang * ang / 48.0 } else { (0.5 * ang).sin() / ang };
    unit_canonical(&qmul(&[k * t0, k * t1, k * t2, (0.5 * ang).cos()], q))
}

pub fn skew(v: &V3) -> M3 {
    [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mat_mul(a: &M3, b: &M3) -> M3 {
        let mut m = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
            }
        }
        m
    }

    #[test]
    fn product_order_matches_the_matrices() {
        let a = unit_canonical(&[0.1, -0.3, 0.2, 0.9]);
        let b = unit_canonical(&[-0.4, 0.1, 0.5, 0.6]);
        let tab = attitude_matrix(&qmul(&a, &b));
        let t = mat_mul(&attitude_matrix(&a), &attitude_matrix(&b));
        for i in 0..3 {
            for j in 0..3 {
                assert!((tab[i][j] - t[i][j]).abs() < 1e-15);
            }
        }
        let e = [0.01, -0.02, 0.005];
        let q = retract(&a, &e);
        let back = local(&q, &a);
        for i in 0..3 {
            assert!((back[i] - e[i]).abs() < 1e-15);
        }
    }
}
