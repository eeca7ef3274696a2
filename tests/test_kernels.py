"""Compiled per-measurement kernels equal their numpy twins; batched linear algebra equals scipy."""

import numpy as np
import pytest
import scipy.linalg as sl

from swarmcore import kernels
from swarmcore.linalg import chol, chol_solve, expm_batched, inv3, inv6_blocks, tri_solve


def _case(n=5, m=17, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6 * n, 6 * n))
    P = A @ A.T + 1e-3 * np.eye(6 * n)
    obs = rng.integers(0, n, m)
    tgt = (obs + rng.integers(1, n, m)) % n
    y = rng.normal(size=(m, 6))
    Hi, Hj = rng.normal(size=(2, m, 6, 6))
    B = rng.normal(size=(m, 6, 6))
    R = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(6)
    return n, P, obs, tgt, y, Hi, Hj, R


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: the numpy twins are in use")
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_kernels_equal_numpy_twins(seed):
    n, P, obs, tgt, y, Hi, Hj, R = _case(seed=seed)
    np.testing.assert_allclose(kernels.gate_d2(P, obs, tgt, y, Hi, Hj, R), kernels.gate_d2_numpy(P, obs, tgt, y, Hi, Hj, R), rtol=1e-10)
    a = kernels.information(n, obs, tgt, y, Hi, Hj, R)
    b = kernels.information_numpy(n, obs, tgt, y, Hi, Hj, R)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-10, atol=1e-10 * np.abs(b[0]).max())
    np.testing.assert_allclose(a[1], b[1], rtol=1e-10, atol=1e-10 * np.abs(b[1]).max())
    assert a[2] == pytest.approx(b[2], rel=1e-12)


def test_information_handles_repeated_pairs():
    # The same pair measured twice adds its information twice.
    n, P, obs, tgt, y, Hi, Hj, R = _case(m=1)
    one = kernels.information(n, obs, tgt, y, Hi, Hj, R)
    two = kernels.information(n, np.r_[obs, obs], np.r_[tgt, tgt], np.r_[y, y], np.r_[Hi, Hi], np.r_[Hj, Hj], np.r_[R, R])
    np.testing.assert_allclose(two[0], 2 * one[0], rtol=1e-12)


def test_expm_batched_matches_scipy():
    rng = np.random.default_rng(3)
    for scale in (1e-3, 0.3, 3.0):
        A = rng.normal(size=(7, 12, 12)) * scale
        ref = np.array([sl.expm(a) for a in A])
        np.testing.assert_allclose(expm_batched(A), ref, rtol=1e-12, atol=1e-13 * np.abs(ref).max())


def test_small_inverses_and_lapack_wrappers():
    rng = np.random.default_rng(4)
    M = rng.normal(size=(9, 6, 6))
    S = M @ np.swapaxes(M, 1, 2) + 0.5 * np.eye(6)
    np.testing.assert_allclose(inv6_blocks(S), np.linalg.inv(S), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(inv3(S[:, :3, :3]), np.linalg.inv(S[:, :3, :3]), rtol=1e-10)
    A = S[0]
    L = chol(A)
    np.testing.assert_allclose(L @ L.T, A, atol=1e-12)
    B = rng.normal(size=(6, 4))
    np.testing.assert_allclose(chol_solve(L, B), np.linalg.solve(A, B), rtol=1e-10)
    np.testing.assert_allclose(tri_solve(L, B), np.linalg.solve(L, B), rtol=1e-10)
    np.testing.assert_allclose(tri_solve(L, B, trans=True), np.linalg.solve(L.T, B), rtol=1e-10)
    with pytest.raises(np.linalg.LinAlgError):
        chol(-np.eye(3))
