"""The numeric checks of a measurement batch in one compiled pass.

Every agent validates every peer's batch every step (at n = 40: 39 batches of 39
measurements each, 1,521 covariances). The numpy form of the checks
(:func:`check_batch_numpy`: finite, unit quaternions, symmetric, Cholesky) costs about
twenty numpy calls per batch, whose per-call overhead, not arithmetic, is most of an
agent's message handling. numba (already loaded by every agent for the filter's kernels)
compiles the same checks into one loop; numpy has no single call that does them. The two
are held to the same verdicts by ``tests/test_messages.py``; the numpy form is used when
numba is missing or disabled (``SWARM_NO_NUMBA``).
"""

from __future__ import annotations

import numpy as np

# Whether numba is there (and not disabled by SWARM_NO_NUMBA) is decided once, by the core.
from swarmcore.kernels import HAVE_NUMBA

__all__ = ["check_batch", "check_batch_numpy", "warm_up", "REASONS", "HAVE_NUMBA"]

# Verdict codes → the reason a MessageError gives.
REASONS = {
    1: "q_BjBi: not finite (NaN or infinity)",
    2: "q_BjBi: not a unit quaternion",
    3: "r_ij_Bi_m: not finite (NaN or infinity)",
    4: "R_Bi: not finite (NaN or infinity)",
    5: "R_Bi: not symmetric",
    6: "R_Bi: not positive-definite",
}


def check_batch_numpy(q: np.ndarray, r: np.ndarray, R: np.ndarray, quat_tol2: float, sym_tol: float) -> int:
    """0 if the batch is sound, else the code of the first defect found (see :data:`REASONS`).

    ``q`` (m, 4), ``r`` (m', 3), ``R`` (m'', 6, 6) (a batch has m = m' = m''; an estimate
    checked with the same pass has 3m + 1 rows of rates and positions); a quaternion passes with
    ``|‖q‖² − 1| ≤ quat_tol2``, a covariance is symmetric when every
    ``|R_ij − R_ji| ≤ sym_tol · max |R|`` (its own largest entry) and positive-definite
    when its Cholesky factorisation succeeds."""
    if len(q) == 0 and len(r) == 0 and len(R) == 0:
        return 0
    if not np.isfinite(q).all():
        return 1
    if not (np.abs(np.einsum("ij,ij->i", q, q) - 1.0) <= quat_tol2).all():
        return 2
    if not np.isfinite(r).all():
        return 3
    scale = np.abs(R).max(axis=(1, 2))
    if not np.isfinite(scale).all():
        return 4
    if not (np.abs(R - R.transpose(0, 2, 1)).max(axis=(1, 2)) <= sym_tol * scale).all():
        return 5
    try:
        np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        return 6
    return 0


if HAVE_NUMBA:
    import numba

    @numba.njit(cache=True, fastmath=False)
    def _check_batch(q, r, R, quat_tol2, sym_tol):  # pragma: no cover - compiled
        m = q.shape[0]
        mr = r.shape[0]  # as many rows as q in a batch; an estimate's rates, positions, velocities and bias: 3n + 1
        mR = R.shape[0]
        L = np.empty((6, 6))
        for k in range(m):  # the checks in check_batch_numpy's order
            for c in range(4):
                if not np.isfinite(q[k, c]):
                    return 1
        for k in range(m):
            s = 0.0
            for c in range(4):
                s += q[k, c] * q[k, c]
            if not abs(s - 1.0) <= quat_tol2:
                return 2
        for k in range(mr):
            for c in range(3):
                if not np.isfinite(r[k, c]):
                    return 3
        for k in range(mR):
            for i in range(6):
                for j in range(6):
                    if not np.isfinite(R[k, i, j]):
                        return 4
        for k in range(mR):
            scale = 0.0
            for i in range(6):
                for j in range(6):
                    scale = max(scale, abs(R[k, i, j]))
            for i in range(6):
                for j in range(i):
                    if not abs(R[k, i, j] - R[k, j, i]) <= sym_tol * scale:
                        return 5
        for k in range(mR):
            # Cholesky–Banachiewicz on the lower triangle, as LAPACK's potrf reads it.
            for i in range(6):
                for j in range(i + 1):
                    s = R[k, i, j]
                    for p in range(j):
                        s -= L[i, p] * L[j, p]
                    if i == j:
                        if not s > 0.0:
                            return 6
                        L[i, i] = np.sqrt(s)
                    else:
                        L[i, j] = s / L[j, j]
        return 0


def warm_up() -> None:
    """Compile (or load from numba's cache) the compiled check now."""
    check_batch(np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros((1, 3)), np.eye(6)[None], 1e-6, 1e-9)


def check_batch(q: np.ndarray, r: np.ndarray, R: np.ndarray, quat_tol2: float, sym_tol: float) -> int:
    """:func:`check_batch_numpy`, compiled when numba is there."""
    if HAVE_NUMBA:
        return int(_check_batch(q, r, R, quat_tol2, sym_tol))
    return check_batch_numpy(q, r, R, quat_tol2, sym_tol)
