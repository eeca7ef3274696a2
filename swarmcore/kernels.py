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

import os

import numpy as np

__all__ = ["gate_d2", "information", "warm_up", "HAVE_NUMBA"]

try:  # pragma: no cover - exercised by whichever is installed
    if os.environ.get("SWARM_NO_NUMBA"):
        raise ImportError("disabled by SWARM_NO_NUMBA")
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    numba = None
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
