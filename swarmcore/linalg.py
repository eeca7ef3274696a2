"""Small dense linear algebra the filter needs, batched or with little overhead.

* :func:`expm_batched` — the matrix exponential of a stack of matrices in one pass.
  ``scipy.linalg.expm`` accepts a stack but works through it one matrix at a time in
  Python; the Van Loan step needs one 12×12 exponential per satellite per step, so a
  vectorised scaling-and-squaring with a Taylor polynomial is written here (the norms
  are small: |ω| Δt ≪ 1 plus a unit coupling block). Held to scipy by the tests.
* :func:`chol` / :func:`chol_solve` / :func:`tri_solve` — LAPACK's potrf / potrs / trtrs
  called directly (``numpy.linalg`` and ``scipy.linalg`` wrappers cost more than the
  factorisation itself at 72×72).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

__all__ = ["expm_batched", "chol", "chol_solve", "tri_solve", "inv3", "inv6_blocks"]

_TAYLOR_DEGREE = 12
_INV_FACT = [1.0 / np.prod(np.arange(1, k + 1, dtype=float)) for k in range(_TAYLOR_DEGREE + 1)]


def expm_batched(A: np.ndarray) -> np.ndarray:
    """``exp(A)`` for ``A`` of shape (..., m, m): scale to ‖A/2^s‖₁ ≤ 1/4, Taylor of degree
    12 (truncation below 3e-16 relative), square s times."""
    A = np.asarray(A, dtype=float)
    norm = np.max(np.sum(np.abs(A), axis=-2)) if A.size else 0.0
    s = max(0, int(np.ceil(np.log2(norm / 0.25)))) if norm > 0.25 else 0
    X = A / (2.0**s)
    m = A.shape[-1]
    eye = np.eye(m)
    # Horner: I + X (1 + X/2 (1 + X/3 (...)))
    E = eye + X * _INV_FACT[_TAYLOR_DEGREE] / _INV_FACT[_TAYLOR_DEGREE - 1]
    for k in range(_TAYLOR_DEGREE - 1, 0, -1):
        E = eye + (X @ E) / k
    for _ in range(s):
        E = E @ E
    return E


def chol(A: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """Lower Cholesky factor of a symmetric positive-definite matrix (LAPACK potrf; only
    the lower triangle of ``A`` is read; ``overwrite``: ``A`` may be used as the workspace)."""
    L, info = lapack.dpotrf(A, lower=1, clean=1, overwrite_a=1 if overwrite else 0)
    if info != 0:
        raise np.linalg.LinAlgError(f"matrix is not positive definite (potrf info {info})")
    return L


def chol_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A⁻¹ B`` from the lower Cholesky factor ``L`` of ``A`` (LAPACK potrs)."""
    X, info = lapack.dpotrs(L, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"potrs info {info}")
    return X


def tri_solve(L: np.ndarray, B: np.ndarray, trans: bool = False) -> np.ndarray:
    """``L⁻¹ B`` (or ``L⁻ᵀ B``) for lower-triangular ``L`` (LAPACK trtrs)."""
    X, info = lapack.dtrtrs(L, B, lower=1, trans=1 if trans else 0)
    if info != 0:
        raise np.linalg.LinAlgError(f"trtrs info {info}")
    return X


def inv3(M: np.ndarray) -> np.ndarray:
    """Inverse of a stack of 3×3 matrices by the adjugate: rows a, b, c give columns
    b×c, c×a, a×b over a·(b×c). A handful of array operations for the whole stack, where
    ``numpy.linalg.inv`` calls LAPACK once per matrix."""
    from .quat import cross

    a, b, c = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    c0, c1, c2 = cross(b, c), cross(c, a), cross(a, b)
    det = np.sum(a * c0, axis=-1)
    return np.stack([c0, c1, c2], axis=-1) / det[..., None, None]


def inv6_blocks(M: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric 6×6 matrices by 3×3 blocks (Schur complement).

    ``[[A, B], [Bᵀ, D]]⁻¹`` with ``S = D − Bᵀ A⁻¹ B``: used for measurement noise and
    innovation covariances, which are well conditioned per block.
    """
    A, B, D = M[..., :3, :3], M[..., :3, 3:], M[..., 3:, 3:]
    Ai = inv3(A)
    AiB = Ai @ B
    Si = inv3(D - np.swapaxes(B, -1, -2) @ AiB)
    top_right = -AiB @ Si
    out = np.empty(M.shape)
    out[..., :3, :3] = Ai - top_right @ np.swapaxes(AiB, -1, -2)
    out[..., :3, 3:] = top_right
    out[..., 3:, :3] = np.swapaxes(top_right, -1, -2)
    out[..., 3:, 3:] = Si
    return out
