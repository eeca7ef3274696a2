"""Per-measurement loops of the update, compiled with numba, with numpy twins.

Every relative measurement touches two satellites' 6×6 blocks, so the gate (one 6×6
innovation covariance per measurement) and the information assembly (four 6×6 blocks per
measurement) are loops of tiny fixed-size products. Batched numpy spends most of its
time in per-call overhead there (and calls LAPACK once per 6×6 matrix); numba compiles
the loop. Each kernel has a numpy twin (``*_numpy``) that the tests hold it equal to, and
that is used when numba is missing.

Kernels take contiguous float64 arrays: ``y`` (m, 6), ``Hi``/``Hj`` (m, 6, 6) on the
observer's and target's ``[a, Δr]``, ``R`` (m, 6, 6), ``P_OO`` (6n, 6n).
"""

from __future__ import annotations

import functools
import os

import numpy as np

__all__ = ["gate_d2", "information", "split_observed", "join_observed", "ci_det_weight", "warm_up", "HAVE_NUMBA"]

try:  # pragma: no cover - exercised by whichever is installed
    if os.environ.get("SWARM_NO_NUMBA"):
        raise ImportError("disabled by SWARM_NO_NUMBA")
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    numba = None  # type: ignore[assignment]
    HAVE_NUMBA = False


# --------------------------------------------------------------------------- numpy twins


def gate_d2_numpy(P_OO, observer, target, y, Hi, Hj, R):
    n6 = P_OO.shape[0]
    n = n6 // 6
    P4 = P_OO.reshape(n, 6, n, 6)
    i, j = observer, target
    top = np.concatenate([P4[i, :, i, :], P4[i, :, j, :]], axis=2)
    bot = np.concatenate([P4[j, :, i, :], P4[j, :, j, :]], axis=2)
    Pm = np.concatenate([top, bot], axis=1)
    H = np.concatenate([Hi, Hj], axis=2)
    S = H @ Pm @ np.swapaxes(H, -1, -2) + R
    return np.sum(y * np.linalg.solve(S, y[:, :, None])[:, :, 0], axis=1)


def information_numpy(n, observer, target, y, Hi, Hj, R):
    Lam4 = np.zeros((n, n, 6, 6))
    b = np.zeros((n, 6))
    W = np.linalg.inv(R)
    Hi_T = np.swapaxes(Hi, -1, -2)
    Hj_T = np.swapaxes(Hj, -1, -2)
    Wy = (W @ y[:, :, None])[:, :, 0]
    HiWHj = Hi_T @ (W @ Hj)
    blocks = np.concatenate([Hi_T @ (W @ Hi), Hj_T @ (W @ Hj), HiWHj, np.swapaxes(HiWHj, -1, -2)])
    rows = np.concatenate([observer, target, observer, target])
    cols = np.concatenate([observer, target, target, observer])
    idx = ((rows * n + cols)[:, None] * 36 + np.arange(36)).ravel()
    Lam4 += np.bincount(idx, weights=blocks.ravel(), minlength=n * n * 36).reshape(n, n, 6, 6)
    bvec = np.concatenate([(Hi_T @ Wy[:, :, None])[:, :, 0], (Hj_T @ Wy[:, :, None])[:, :, 0]])
    b_idx = (np.concatenate([observer, target])[:, None] * 6 + np.arange(6)).ravel()
    b += np.bincount(b_idx, weights=bvec.ravel(), minlength=n * 6).reshape(n, 6)
    yRy = float(np.sum(y * Wy))
    return Lam4.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n), b.ravel(), yRy


@functools.lru_cache(maxsize=64)
def _observed_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """State indices of the observed errors O = [a, Δr] and the others U = [Δω|Δβ, Δv] of
    every satellite's 12-state block (the order of :func:`swarmcore.mekf.observed_indices`);
    computed once per swarm size (read-only)."""
    base = 12 * np.arange(n)[:, None]
    O, U = (base + np.r_[0:3, 6:9]).ravel(), (base + np.r_[3:6, 9:12]).ravel()
    O.flags.writeable = U.flags.writeable = False
    return O, U


def split_observed_numpy(P, n):
    O, U = _observed_split(n)
    return P[np.ix_(O, O)], np.asfortranarray(P[np.ix_(O, U)]), P[np.ix_(U, U)]


def join_observed_numpy(A_OO, C_OU, A_UU, n):
    O, U = _observed_split(n)
    P = np.empty((12 * n, 12 * n))
    lo = np.tril(A_OO)
    P[np.ix_(O, O)] = lo + np.tril(lo, -1).T
    P[np.ix_(O, U)] = C_OU
    P[np.ix_(U, O)] = np.asarray(C_OU).T
    lu = np.tril(A_UU)
    P[np.ix_(U, U)] = lu + np.tril(lu, -1).T
    return P


# --------------------------------------------------------------------------- numba kernels

if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False)
    def _chol6(A, L):
        """Cholesky of a 6×6 SPD matrix into L (lower); returns False if not PD."""
        for c in range(6):
            s = A[c, c]
            for k in range(c):
                s -= L[c, k] * L[c, k]
            if s <= 0.0:
                return False
            L[c, c] = np.sqrt(s)
            for r in range(c + 1, 6):
                t = A[r, c]
                for k in range(c):
                    t -= L[r, k] * L[c, k]
                L[r, c] = t / L[c, c]
        return True

    @numba.njit(cache=True, fastmath=False)
    def _gate_d2(P_OO, observer, target, y, Hi, Hj, R):
        m = y.shape[0]
        out = np.empty(m)
        Pm = np.empty((12, 12))
        H = np.empty((6, 12))
        HP = np.empty((6, 12))
        S = np.empty((6, 6))
        L = np.zeros((6, 6))
        z = np.empty(6)
        for k in range(m):
            oi = 6 * observer[k]
            oj = 6 * target[k]
            for r in range(6):
                for c in range(6):
                    Pm[r, c] = P_OO[oi + r, oi + c]
                    Pm[r, c + 6] = P_OO[oi + r, oj + c]
                    Pm[r + 6, c] = P_OO[oj + r, oi + c]
                    Pm[r + 6, c + 6] = P_OO[oj + r, oj + c]
                    H[r, c] = Hi[k, r, c]
                    H[r, c + 6] = Hj[k, r, c]
            for r in range(6):
                for c in range(12):
                    s = 0.0
                    for q in range(12):
                        s += H[r, q] * Pm[q, c]
                    HP[r, c] = s
            for r in range(6):
                for c in range(6):
                    s = R[k, r, c]
                    for q in range(12):
                        s += HP[r, q] * H[c, q]
                    S[r, c] = s
            for r in range(6):  # symmetrise
                for c in range(r):
                    v = 0.5 * (S[r, c] + S[c, r])
                    S[r, c] = v
                    S[c, r] = v
            if not _chol6(S, L):
                out[k] = np.inf
                continue
            d2 = 0.0
            for r in range(6):
                t = y[k, r]
                for q in range(r):
                    t -= L[r, q] * z[q]
                z[r] = t / L[r, r]
                d2 += z[r] * z[r]
            out[k] = d2
        return out

    @numba.njit(cache=True, fastmath=False)
    def _information(n, observer, target, y, Hi, Hj, R):
        m = y.shape[0]
        Lam = np.zeros((6 * n, 6 * n))
        b = np.zeros(6 * n)
        L = np.zeros((6, 6))
        Winv = np.empty((6, 6))
        WHi = np.empty((6, 6))
        WHj = np.empty((6, 6))
        Wy = np.empty(6)
        e = np.empty(6)
        yRy = 0.0
        for k in range(m):
            if not _chol6(R[k], L):
                continue
            # R⁻¹ column by column: solve L Lᵀ x = e_c.
            for c in range(6):
                for r in range(6):
                    e[r] = 1.0 if r == c else 0.0
                for r in range(6):
                    t = e[r]
                    for q in range(r):
                        t -= L[r, q] * e[q]
                    e[r] = t / L[r, r]
                for r in range(5, -1, -1):
                    t = e[r]
                    for q in range(r + 1, 6):
                        t -= L[q, r] * e[q]
                    e[r] = t / L[r, r]
                for r in range(6):
                    Winv[r, c] = e[r]
            for r in range(6):
                sy = 0.0
                for c in range(6):
                    sy += Winv[r, c] * y[k, c]
                Wy[r] = sy
                for c in range(6):
                    si = 0.0
                    sj = 0.0
                    for q in range(6):
                        si += Winv[r, q] * Hi[k, q, c]
                        sj += Winv[r, q] * Hj[k, q, c]
                    WHi[r, c] = si
                    WHj[r, c] = sj
            for r in range(6):
                yRy += y[k, r] * Wy[r]
            oi = 6 * observer[k]
            oj = 6 * target[k]
            for r in range(6):
                bi = 0.0
                bj = 0.0
                for q in range(6):
                    bi += Hi[k, q, r] * Wy[q]
                    bj += Hj[k, q, r] * Wy[q]
                b[oi + r] += bi
                b[oj + r] += bj
                for c in range(6):
                    sii = 0.0
                    sjj = 0.0
                    sij = 0.0
                    for q in range(6):
                        sii += Hi[k, q, r] * WHi[q, c]
                        sjj += Hj[k, q, r] * WHj[q, c]
                        sij += Hi[k, q, r] * WHj[q, c]
                    Lam[oi + r, oi + c] += sii
                    Lam[oj + r, oj + c] += sjj
                    Lam[oi + r, oj + c] += sij
                    Lam[oj + c, oi + r] += sij
        return Lam, b, yRy


if HAVE_NUMBA:

    @numba.njit(cache=True)
    def _split_observed(P, O, U):
        no, nu = O.size, U.size
        P_OO = np.empty((no, no))
        P_UU = np.empty((nu, nu))
        P_UO = np.empty((nu, no))  # returned transposed: P_OU in Fortran order, as BLAS takes it
        for a in range(no):
            r = O[a]
            for c in range(no):
                P_OO[a, c] = P[r, O[c]]
            for c in range(nu):
                P_UO[c, a] = P[r, U[c]]
        for a in range(nu):
            r = U[a]
            for c in range(nu):
                P_UU[a, c] = P[r, U[c]]
        return P_OO, P_UO.T, P_UU

    @numba.njit(cache=True)
    def _join_observed(A_OO, C_OU, A_UU, O, U):
        no, nu = O.size, U.size
        P = np.empty((no + nu, no + nu))
        for a in range(no):
            r = O[a]
            for c in range(a + 1):
                v = A_OO[a, c]
                P[r, O[c]] = v
                P[O[c], r] = v
            for c in range(nu):
                v = C_OU[a, c]
                P[r, U[c]] = v
                P[U[c], r] = v
        for a in range(nu):
            r = U[a]
            for c in range(a + 1):
                v = A_UU[a, c]
                P[r, U[c]] = v
                P[U[c], r] = v
        return P


def split_observed(P: np.ndarray, n: int):
    """``(P_OO, P_OU, P_UU)``: the observed/other blocks of a full covariance in one pass
    (``P_OU`` Fortran-ordered, as LAPACK and BLAS take it, so they need not copy it)."""
    if HAVE_NUMBA:
        O, U = _observed_split(n)
        return _split_observed(np.ascontiguousarray(P), O, U)
    return split_observed_numpy(P, n)


def join_observed(A_OO: np.ndarray, C_OU: np.ndarray, A_UU: np.ndarray, n: int) -> np.ndarray:
    """The full covariance in the state order from its blocks: the lower triangles of the
    symmetric ``A_OO`` and ``A_UU`` (mirrored: the result is exactly symmetric) and ``C_OU``."""
    if HAVE_NUMBA:
        O, U = _observed_split(n)
        return _join_observed(A_OO, C_OU, A_UU, O, U)
    return join_observed_numpy(A_OO, C_OU, A_UU, n)


def gate_d2(P_OO, observer, target, y, Hi, Hj, R) -> np.ndarray:
    """Squared Mahalanobis distance of every relative measurement against the prior."""
    if len(y) == 0:
        return np.zeros(0)
    if HAVE_NUMBA:
        return _gate_d2(
            np.ascontiguousarray(P_OO), np.ascontiguousarray(observer, dtype=np.int64), np.ascontiguousarray(target, dtype=np.int64),
            np.ascontiguousarray(y), np.ascontiguousarray(Hi), np.ascontiguousarray(Hj), np.ascontiguousarray(R),
        )
    return gate_d2_numpy(P_OO, observer, target, y, Hi, Hj, R)


def information(n, observer, target, y, Hi, Hj, R):
    """``(Λ, b, yᵀR⁻¹y)``: the information of the relative measurements in the 6n
    attitude/position subspace, ``Λ = Σ Hᵀ R⁻¹ H``, ``b = Σ Hᵀ R⁻¹ y``."""
    if len(y) == 0:
        return np.zeros((6 * n, 6 * n)), np.zeros(6 * n), 0.0
    if HAVE_NUMBA:
        return _information(
            n, np.ascontiguousarray(observer, dtype=np.int64), np.ascontiguousarray(target, dtype=np.int64),
            np.ascontiguousarray(y), np.ascontiguousarray(Hi), np.ascontiguousarray(Hj), np.ascontiguousarray(R),
        )
    return information_numpy(n, observer, target, y, Hi, Hj, R)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel now, on a two-satellite dummy,
    so that a process's first filter step is not also its compile step."""
    n = 2
    P = np.eye(6 * n)
    o, t = np.array([0]), np.array([1])
    y = np.zeros((1, 6))
    H = np.eye(6)[None].copy()
    gate_d2(P, o, t, y, H, -H, H)
    information(n, o, t, y, H, -H, H)
    P12 = np.eye(12 * n)
    A_OO, C_OU, A_UU = split_observed(P12, n)
    join_observed(A_OO, np.ascontiguousarray(C_OU), A_UU, n)  # the information form's blocks are C-ordered products
    # The attitude kernels too: a swarm's agents all reach their first predict at once, and
    # on a fresh checkout (no numba cache yet) 20 of them compiling there on 2 cores held
    # step 0 and 1 past the world's 10 s estimate timeout.
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
    w = np.zeros((n, 3))
    J = np.eye(3)
    rk4_free(q, w, J, J, 1.0, 1)
    rk4(q, w, J, J, 1.0, 1, np.zeros((1, n, 3)))
    relative_residuals(q, np.zeros((n, 3)), np.eye(3), o, t, q[:1], np.zeros((1, 3)))
    retract(q, w)
    propagate_constant_rate(q[0], w[0], 1.0)
    ci_det_weight(np.eye(12)[:6] * 0.5, np.zeros(6), True)  # the ci estimator's ω search


# --------------------------------------------------------------------------- attitude
# Written out with scalars (no temporaries): at n = 12 the vectorised numpy forms spend
# ~100 µs each in per-call overhead for what is a few hundred flops.

if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False, inline="always")
    def _qmul_s(a0, a1, a2, a3, b0, b1, b2, b3):
        """Shuster product a ⊗ b = [a4 b_v + b4 a_v − a_v × b_v, a4 b4 − a_v·b_v], scalars."""
        return (
            a3 * b0 + b3 * a0 - (a1 * b2 - a2 * b1),
            a3 * b1 + b3 * a1 - (a2 * b0 - a0 * b2),
            a3 * b2 + b3 * a2 - (a0 * b1 - a1 * b0),
            a3 * b3 - (a0 * b0 + a1 * b1 + a2 * b2),
        )

    @numba.njit(cache=True, fastmath=False, inline="always")
    def _att_rhs(q0, q1, q2, q3, w0, w1, w2, J, Ji, t0, t1, t2):
        # q̇ = ½ [ω; 0] ⊗ q (Shuster);  ω̇ = J⁻¹ (τ − ω × Jω)
        p0, p1, p2, p3 = _qmul_s(w0, w1, w2, 0.0, q0, q1, q2, q3)
        dq0, dq1, dq2, dq3 = 0.5 * p0, 0.5 * p1, 0.5 * p2, 0.5 * p3
        h0 = J[0, 0] * w0 + J[0, 1] * w1 + J[0, 2] * w2
        h1 = J[1, 0] * w0 + J[1, 1] * w1 + J[1, 2] * w2
        h2 = J[2, 0] * w0 + J[2, 1] * w1 + J[2, 2] * w2
        r0 = t0 - (w1 * h2 - w2 * h1)
        r1 = t1 - (w2 * h0 - w0 * h2)
        r2 = t2 - (w0 * h1 - w1 * h0)
        dw0 = Ji[0, 0] * r0 + Ji[0, 1] * r1 + Ji[0, 2] * r2
        dw1 = Ji[1, 0] * r0 + Ji[1, 1] * r1 + Ji[1, 2] * r2
        dw2 = Ji[2, 0] * r0 + Ji[2, 1] * r1 + Ji[2, 2] * r2
        return dq0, dq1, dq2, dq3, dw0, dw1, dw2

    @numba.njit(cache=True, fastmath=False)
    def _rk4(q, w, J, Ji, dt, substeps, torques):
        """RK4 of every satellite; ``torques`` (substeps, n, 3) held over each substep, or
        an empty array for none."""
        n = q.shape[0]
        qo = np.empty((n, 4))
        wo = np.empty((n, 3))
        h = dt / substeps
        torqued = torques.shape[0] > 0
        for s in range(n):
            a0, a1, a2, a3 = q[s, 0], q[s, 1], q[s, 2], q[s, 3]
            b0, b1, b2 = w[s, 0], w[s, 1], w[s, 2]
            for k in range(substeps):
                t0, t1, t2 = (torques[k, s, 0], torques[k, s, 1], torques[k, s, 2]) if torqued else (0.0, 0.0, 0.0)
                k1 = _att_rhs(a0, a1, a2, a3, b0, b1, b2, J, Ji, t0, t1, t2)
                k2 = _att_rhs(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2], a3 + 0.5 * h * k1[3],
                              b0 + 0.5 * h * k1[4], b1 + 0.5 * h * k1[5], b2 + 0.5 * h * k1[6], J, Ji, t0, t1, t2)
                k3 = _att_rhs(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2], a3 + 0.5 * h * k2[3],
                              b0 + 0.5 * h * k2[4], b1 + 0.5 * h * k2[5], b2 + 0.5 * h * k2[6], J, Ji, t0, t1, t2)
                k4 = _att_rhs(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2], a3 + h * k3[3],
                              b0 + h * k3[4], b1 + h * k3[5], b2 + h * k3[6], J, Ji, t0, t1, t2)
                c = h / 6.0
                a0 = a0 + c * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
                a1 = a1 + c * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
                a2 = a2 + c * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
                a3 = a3 + c * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3])
                b0 = b0 + c * (k1[4] + 2 * k2[4] + 2 * k3[4] + k4[4])
                b1 = b1 + c * (k1[5] + 2 * k2[5] + 2 * k3[5] + k4[5])
                b2 = b2 + c * (k1[6] + 2 * k2[6] + 2 * k3[6] + k4[6])
                nq = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3)
                a0, a1, a2, a3 = a0 / nq, a1 / nq, a2 / nq, a3 / nq
            sgn = -1.0 if a3 < 0.0 else 1.0  # canonical sign: non-negative scalar part
            qo[s, 0], qo[s, 1], qo[s, 2], qo[s, 3] = sgn * a0, sgn * a1, sgn * a2, sgn * a3
            wo[s, 0], wo[s, 1], wo[s, 2] = b0, b1, b2
        return qo, wo

    @numba.njit(cache=True, fastmath=False, inline="always")
    def _unit_canonical(r0, r1, r2, r3, out):
        """``out`` = the unit quaternion of (r0..r3) with non-negative scalar part."""
        nr = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
        if r3 < 0.0:
            nr = -nr
        out[0], out[1], out[2], out[3] = r0 / nr, r1 / nr, r2 / nr, r3 / nr

    @numba.njit(cache=True, fastmath=False, inline="always")
    def _att_matrix(q, T):
        """T(q) = (q4² − |e|²) I + 2 e eᵀ − 2 q4 [e×] into T (3×3)."""
        e0, e1, e2, w = q[0], q[1], q[2], q[3]
        d = w * w - (e0 * e0 + e1 * e1 + e2 * e2)
        T[0, 0] = d + 2 * e0 * e0
        T[1, 1] = d + 2 * e1 * e1
        T[2, 2] = d + 2 * e2 * e2
        T[0, 1] = 2 * e0 * e1 + 2 * w * e2
        T[1, 0] = 2 * e0 * e1 - 2 * w * e2
        T[0, 2] = 2 * e0 * e2 - 2 * w * e1
        T[2, 0] = 2 * e0 * e2 + 2 * w * e1
        T[1, 2] = 2 * e1 * e2 + 2 * w * e0
        T[2, 1] = 2 * e1 * e2 - 2 * w * e0

    @numba.njit(cache=True, fastmath=False)
    def _relative_residuals(q_BI, r_H, T_IH, observer, target, q_meas, r_meas):
        n = q_BI.shape[0]
        m = observer.shape[0]
        T = np.empty((n, 3, 3))
        C = np.empty((n, 3, 3))
        for s in range(n):
            _att_matrix(q_BI[s], T[s])
            for a in range(3):
                for b in range(3):
                    C[s, a, b] = T[s, a, 0] * T_IH[0, b] + T[s, a, 1] * T_IH[1, b] + T[s, a, 2] * T_IH[2, b]
        y = np.empty((m, 6))
        Hi = np.zeros((m, 6, 6))
        Hj = np.zeros((m, 6, 6))
        for k in range(m):
            i = observer[k]
            j = target[k]
            d0 = r_H[j, 0] - r_H[i, 0]
            d1 = r_H[j, 1] - r_H[i, 1]
            d2 = r_H[j, 2] - r_H[i, 2]
            rh0 = C[i, 0, 0] * d0 + C[i, 0, 1] * d1 + C[i, 0, 2] * d2
            rh1 = C[i, 1, 0] * d0 + C[i, 1, 1] * d1 + C[i, 1, 2] * d2
            rh2 = C[i, 2, 0] * d0 + C[i, 2, 1] * d1 + C[i, 2, 2] * d2
            # q̂ = q_j ⊗ q_i⁻¹;  δq = q̂⁻¹ ⊗ q_meas;  a = 2 vec(δq) / δq4
            h0, h1, h2, h3 = _qmul_s(q_BI[j, 0], q_BI[j, 1], q_BI[j, 2], q_BI[j, 3], -q_BI[i, 0], -q_BI[i, 1], -q_BI[i, 2], q_BI[i, 3])
            e0, e1, e2, e3 = _qmul_s(-h0, -h1, -h2, h3, q_meas[k, 0], q_meas[k, 1], q_meas[k, 2], q_meas[k, 3])
            y[k, 0] = 2.0 * e0 / e3
            y[k, 1] = 2.0 * e1 / e3
            y[k, 2] = 2.0 * e2 / e3
            y[k, 3] = r_meas[k, 0] - rh0
            y[k, 4] = r_meas[k, 1] - rh1
            y[k, 5] = r_meas[k, 2] - rh2
            for a in range(3):
                Hi[k, a, a] = -1.0
                for b in range(3):
                    Hj[k, a, b] = T[i, a, 0] * T[j, b, 0] + T[i, a, 1] * T[j, b, 1] + T[i, a, 2] * T[j, b, 2]
                    Hi[k, 3 + a, 3 + b] = -C[i, a, b]
                    Hj[k, 3 + a, 3 + b] = C[i, a, b]
            # ∂Δr/∂a_i = [r̂×] (rows Δr, columns a)
            Hi[k, 3, 1] = -rh2
            Hi[k, 3, 2] = rh1
            Hi[k, 4, 0] = rh2
            Hi[k, 4, 2] = -rh0
            Hi[k, 5, 0] = -rh1
            Hi[k, 5, 1] = rh0
        return y, Hi, Hj


_NO_TORQUE = np.zeros((0, 0, 3))


def rk4_free(q, w, J, J_inv, dt: float, substeps: int):
    """Torque-free RK4 of every satellite's attitude and rate (the filter's prediction of
    the others); ``None`` when numba is missing (the caller uses its numpy form)."""
    return rk4(q, w, J, J_inv, dt, substeps)


def rk4(q, w, J, J_inv, dt: float, substeps: int, torques=None):
    """RK4 of every satellite's attitude and rate (:func:`swarmcore.dynamics.rk4_attitude`,
    compiled): ``torques`` (substeps, n, 3) held over each substep (the truth's torque
    noise) or None; ``None`` when numba is missing (the caller uses its numpy form)."""
    if not HAVE_NUMBA:
        return None
    tq = _NO_TORQUE if torques is None else np.ascontiguousarray(torques, dtype=float)
    return _rk4(np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(J, dtype=float),
                np.ascontiguousarray(J_inv, dtype=float), float(dt), int(substeps), tq)


def relative_residuals(q_BI, r_H, T_IH, observer, target, q_meas, r_meas):
    """Compiled relative residuals and Jacobian blocks (see ``mekf.relative_residuals``);
    ``None`` when numba is missing."""
    if not HAVE_NUMBA:
        return None
    return _relative_residuals(
        np.ascontiguousarray(q_BI, dtype=float), np.ascontiguousarray(r_H, dtype=float), np.ascontiguousarray(T_IH, dtype=float),
        np.ascontiguousarray(observer, dtype=np.int64), np.ascontiguousarray(target, dtype=np.int64),
        np.ascontiguousarray(q_meas, dtype=float), np.ascontiguousarray(r_meas, dtype=float),
    )


if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False)
    def _retract(q_hat, a):
        n = q_hat.shape[0]
        out = np.empty((n, 4))
        for s in range(n):
            # δq(a) = normalise([a/2, 1]);  q = normalise(δq ⊗ q̂) with q4 ≥ 0
            d0, d1, d2 = 0.5 * a[s, 0], 0.5 * a[s, 1], 0.5 * a[s, 2]
            nd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + 1.0)
            r = _qmul_s(d0 / nd, d1 / nd, d2 / nd, 1.0 / nd, q_hat[s, 0], q_hat[s, 1], q_hat[s, 2], q_hat[s, 3])
            _unit_canonical(r[0], r[1], r[2], r[3], out[s])
        return out


def retract(q_hat, a):
    """Compiled ``quat.retract`` for (n, 4) and (n, 3) arrays; ``None`` without numba."""
    if not HAVE_NUMBA:
        return None
    return _retract(np.ascontiguousarray(q_hat, dtype=float), np.ascontiguousarray(a, dtype=float))


if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False)
    def _rotate_constant_rate(q, w, dt):
        t0, t1, t2 = w[0] * dt, w[1] * dt, w[2] * dt
        ang = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        # rotvec → quaternion, sin(x/2)/x by its series for tiny angles (as quat.rotvec_to_quat)
        k = 0.5 - ang * ang / 48.0 if ang < 1e-8 else np.sin(0.5 * ang) / ang
        r = _qmul_s(k * t0, k * t1, k * t2, np.cos(0.5 * ang), q[0], q[1], q[2], q[3])
        out = np.empty(4)
        _unit_canonical(r[0], r[1], r[2], r[3], out)
        return out


def propagate_constant_rate(q, omega_B, dt: float):
    """Compiled ``quat.propagate_constant_rate`` for one quaternion; ``None`` without numba."""
    if not HAVE_NUMBA:
        return None
    return _rotate_constant_rate(np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(omega_B, dtype=float), float(dt))


# --------------------------------------------------------------------------- CI weight
# The ``ci`` estimator chooses its ω by a bounded scalar search of a 12×12 log-det (about
# 30 evaluations a fusion). scipy's ``minimize_scalar(method="bounded")`` runs that loop in
# Python and each evaluation is a handful of numpy calls: ~45 µs an evaluation, a third of
# a ``ci`` step at n = 100, for a few thousand flops. Nothing in scipy compiles a scalar
# search around a compiled function, so the search (Brent's bounded method, step for step
# as scipy's: the Rust agent's ``brent.rs`` is the same transcription) and the cost are
# written out here. The numpy twin is the scipy path in ``swarmcore.estimators.ci``.

if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False)
    def _ci_det_cost(w, W, lam, split):
        """``−n log ω − log det(I + Ŵᵀ diag(d) Ŵ / ω)`` (``ci._logdet_cost``); NaN when the
        matrix is not positive-definite."""
        m, n = W.shape
        d = np.empty(m)
        for r in range(m):
            d[r] = (1.0 - w) / (1.0 - w + lam[r]) if split else 1.0 - w
        # S = I + Ŵᵀ diag(d) Ŵ / ω, lower triangle, by loops (no BLAS call: a 12×12 product
        # is cheaper than the call, and loops keep one summation order on every CPU).
        S = np.empty((n, n))
        for c1 in range(n):
            for c2 in range(c1 + 1):
                t = 0.0
                for r in range(m):
                    t += W[r, c1] * d[r] * W[r, c2]
                S[c1, c2] = t / w
            S[c1, c1] += 1.0
        # log det by Cholesky, in place over the lower triangle
        logdet = 0.0
        for c in range(n):
            s = S[c, c]
            for k in range(c):
                s -= S[c, k] * S[c, k]
            if not s > 0.0:
                return np.nan
            s = np.sqrt(s)
            S[c, c] = s
            logdet += np.log(s)
            for r in range(c + 1, n):
                t = S[r, c]
                for k in range(c):
                    t -= S[r, k] * S[c, k]
                S[r, c] = t / s
        return -n * np.log(w) - 2.0 * logdet

    @numba.njit(cache=True, fastmath=False)
    def _sign(v):
        return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)

    @numba.njit(cache=True, fastmath=False)
    def _ci_det_weight(W, lam, split, x1, x2, xatol, maxfun):
        """Brent's bounded minimisation of :func:`_ci_det_cost` over ``[x1, x2]`` (scipy's
        ``_minimize_scalar_bounded``, Forsythe–Malcolm–Moler's ``fmin``). Returns ``(ω,
        ok)``; ``ok`` False: a cost was not finite (a matrix not positive-definite)."""
        sqrt_eps = np.sqrt(2.2e-16)
        golden_mean = 0.5 * (3.0 - np.sqrt(5.0))
        a, b = x1, x2
        fulc = a + golden_mean * (b - a)
        nfc, xf = fulc, fulc
        rat = 0.0
        e = 0.0
        fx = _ci_det_cost(xf, W, lam, split)
        if not np.isfinite(fx):
            return xf, False
        num = 1
        ffulc = fnfc = fx
        xm = 0.5 * (a + b)
        tol1 = sqrt_eps * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        while abs(xf - xm) > (tol2 - 0.5 * (b - a)):
            golden = True
            if abs(e) > tol1:  # a parabolic step?
                golden = False
                r = (xf - nfc) * (fx - ffulc)
                q = (xf - fulc) * (fx - fnfc)
                p = (xf - fulc) * q - (xf - nfc) * r
                q = 2.0 * (q - r)
                if q > 0.0:
                    p = -p
                q = abs(q)
                r = e
                e = rat
                if abs(p) < abs(0.5 * q * r) and p > q * (a - xf) and p < q * (b - xf):
                    rat = (p + 0.0) / q
                    x = xf + rat
                    if (x - a) < tol2 or (b - x) < tol2:
                        si = _sign(xm - xf) + (1.0 if xm - xf == 0.0 else 0.0)
                        rat = tol1 * si
                else:
                    golden = True
            if golden:
                e = (a - xf) if xf >= xm else (b - xf)
                rat = golden_mean * e
            si = _sign(rat) + (1.0 if rat == 0.0 else 0.0)
            x = xf + si * max(abs(rat), tol1)
            fu = _ci_det_cost(x, W, lam, split)
            if not np.isfinite(fu):
                return x, False
            num += 1
            if fu <= fx:
                if x >= xf:
                    a = xf
                else:
                    b = xf
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = xf, fx
                xf, fx = x, fu
            else:
                if x < xf:
                    a = x
                else:
                    b = x
                if fu <= fnfc or nfc == xf:
                    fulc, ffulc = nfc, fnfc
                    nfc, fnfc = x, fu
                elif fu <= ffulc or fulc in (xf, nfc):
                    fulc, ffulc = x, fu
            xm = 0.5 * (a + b)
            tol1 = sqrt_eps * abs(xf) + xatol / 3.0
            tol2 = 2.0 * tol1
            if num >= maxfun:
                break
        return xf, True


def ci_det_weight(W: np.ndarray, lam: np.ndarray, split: bool, lo: float = 1e-4, hi: float = 1.0 - 1e-4,
                  xatol: float = 1e-6, maxfun: int = 500) -> float | None:
    """The ω in ``[lo, hi]`` minimising the CI log-det cost of whitened ``W`` (6m, 12) and
    eigenvalues ``lam`` (see ``swarmcore.estimators.ci._logdet_cost``), compiled; ``None``
    without numba (the caller then runs scipy's search). Raises ``LinAlgError`` when a
    matrix of the search is not positive-definite, as the numpy cost does."""
    if not HAVE_NUMBA:
        return None
    w, ok = _ci_det_weight(np.ascontiguousarray(W, dtype=float), np.ascontiguousarray(lam, dtype=float), bool(split),
                           float(lo), float(hi), float(xatol), int(maxfun))
    if not ok:
        raise np.linalg.LinAlgError("CI weight search: a fused covariance is not positive-definite")
    return float(w)
