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
    n, _P, obs, tgt, y, Hi, Hj, R = _case(m=1)
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


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: the numpy twins are in use")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_attitude_kernels_equal_numpy_twins(seed):
    """Residuals and Jacobians, RK4 (torque-free, and the truth's with torques), retraction and the constant-rate step:
    the compiled forms the filter uses equal the vectorised numpy ones to round-off."""
    from swarmcore import dynamics, quat
    from swarmcore.agent import filter_params
    from swarmcore.dynamics import T_IH
    from swarmcore.mekf import RelativeMeasurements, relative_residuals, relative_residuals_numpy
    from swarmcore.scenario import Scenario
    from swarmcore.world import initial_estimate, initial_truth

    rng = np.random.default_rng(seed)
    n, m = 5, 11
    sc = Scenario(n_sats=n, seed=seed)
    est = initial_estimate(sc, initial_truth(sc), 0)
    params = filter_params(sc, 0)
    obs = rng.integers(0, n, m)
    tgt = (obs + rng.integers(1, n, m)) % n
    meas = RelativeMeasurements(obs, tgt, quat.random_quaternion(rng, m), rng.normal(size=(m, 3)), np.tile(np.eye(6), (m, 1, 1)))
    for a, b in zip(relative_residuals(est, params, meas), relative_residuals_numpy(est, params, meas), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    # The inputs really reach the kernel (not a pass-through of the numpy form).
    y, _, _ = kernels.relative_residuals(est.q_BI, est.r_H, T_IH(params.mean_motion, est.t), obs, tgt, meas.q_BjBi, meas.r_ij_Bi)
    np.testing.assert_allclose(y, relative_residuals_numpy(est, params, meas)[0], rtol=1e-12, atol=1e-12)

    q, w = quat.random_quaternion(rng, n), rng.normal(scale=0.1, size=(n, 3))
    J = np.diag([3.0, 4.0, 5.0]) + 0.1
    for sub in (1, 4):
        a = kernels.rk4_free(q, w, J, np.linalg.inv(J), 1.0, sub)
        b = dynamics.rk4_attitude(q, w, J, 1.0, sub)
        np.testing.assert_allclose(a[0], b[0], atol=1e-14)
        np.testing.assert_allclose(a[1], b[1], atol=1e-14)
        # The truth's: torque noise held over each substep.
        tau = rng.normal(scale=0.05, size=(sub, n, 3))
        a = kernels.rk4(q, w, J, np.linalg.inv(J), 1.0, sub, tau)
        b = dynamics.rk4_attitude(q, w, J, 1.0, sub, tau)
        np.testing.assert_allclose(a[0], b[0], atol=1e-14)
        np.testing.assert_allclose(a[1], b[1], atol=1e-14)
        assert not np.allclose(a[1], kernels.rk4_free(q, w, J, np.linalg.inv(J), 1.0, sub)[1], atol=1e-6), "the torques act"
    da = rng.normal(scale=0.05, size=(n, 3))
    np.testing.assert_allclose(kernels.retract(q, da), quat.retract(q, da), atol=1e-15)
    for scale in (0.0, 1e-10, 0.3):
        om = rng.normal(size=3) * scale
        np.testing.assert_allclose(kernels.propagate_constant_rate(q[0], om, 1.0), quat.propagate_constant_rate(q[0], om, 1.0), atol=1e-15)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: the numpy twins are in use")
def test_warm_up_compiles_every_kernel():
    """An agent calls warm_up() before it announces itself; a kernel left out compiles at
    the first step instead, in every agent at once (on a fresh checkout 20 agents held
    steps 0 and 1 past the world's 10 s timeout). Checked in a fresh interpreter."""
    import subprocess
    import sys

    code = (
        "import numba\n"
        "from swarmcore import kernels\n"
        "kernels.warm_up()\n"
        "d = {k: v for k, v in vars(kernels).items() if isinstance(v, numba.core.registry.CPUDispatcher)}\n"
        "assert len(d) >= 6, sorted(d)\n"
        "inner = {'_chol6', '_ci_det_cost', '_sign'}  # called only from inside other kernels, compiled with them\n"
        "cold = sorted(k for k, v in d.items() if v.targetoptions.get('inline') != 'always' and k not in inner and not v.signatures)\n"
        "print('cold', cold)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "cold []", out.stdout


@pytest.mark.parametrize("n", [1, 3, 7])
def test_split_and_join_observed_equal_fancy_indexing(n):
    """The information form's gather of a covariance into its observed/other blocks and
    the scatter back (compiled) equal numpy's fancy indexing, and join mirrors the lower
    triangles into an exactly symmetric matrix."""
    from swarmcore.mekf import observed_indices, unobserved_indices

    rng = np.random.default_rng(n)
    A = rng.normal(size=(12 * n, 12 * n))
    P = A @ A.T
    O, U = observed_indices(n), unobserved_indices(n)
    P_OO, P_OU, P_UU = kernels.split_observed(P, n)
    assert np.array_equal(P_OO, P[np.ix_(O, O)]) and np.array_equal(P_UU, P[np.ix_(U, U)])
    assert np.array_equal(P_OU, P[np.ix_(O, U)]) and P_OU.flags.f_contiguous
    for twin in (kernels.split_observed_numpy(P, n),):
        assert all(np.array_equal(a, b) for a, b in zip(twin, (P_OO, P_OU, P_UU), strict=True))
    # Upper triangles deliberately wrong: only the lower ones may be read.
    A_OO, A_UU = P_OO + np.triu(np.ones_like(P_OO), 1), P_UU + np.triu(np.ones_like(P_UU), 1)
    back = kernels.join_observed(A_OO, np.ascontiguousarray(P_OU), A_UU, n)
    assert np.array_equal(back, P) and np.array_equal(back, back.T)
    assert np.array_equal(kernels.join_observed_numpy(A_OO, P_OU, A_UU, n), P)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: the ci estimator runs scipy's search")
@pytest.mark.parametrize("split", [True, False])
def test_compiled_ci_weight_is_scipys_bounded_search(split):
    """The ci estimator's ω: the compiled search (kernels.ci_det_weight) lands where
    scipy's minimize_scalar(method="bounded") lands on the numpy cost, to the search's
    tolerance (the two costs differ at round-off, which may move a Brent step), and its
    cost there is scipy's minimum up to round-off; a matrix that is not positive-definite
    is refused as numpy's Cholesky refuses it."""
    from swarmcore.estimators.ci import _logdet_cost, _whitened, ci_weight

    rng = np.random.default_rng(7)
    gaps = []
    for _ in range(60):
        k = int(rng.integers(1, 5))
        A, B, C = rng.normal(size=(12, 12)), rng.normal(size=(6 * k, 6 * k)), rng.normal(size=(6 * k, 6 * k))
        P = A @ A.T * 10 ** rng.uniform(-4, 0) + 1e-6 * np.eye(12)
        R = B @ B.T * 10 ** rng.uniform(-4, 0) + 1e-6 * np.eye(6 * k)
        C_p = C @ C.T * 10 ** rng.uniform(-4, 1)
        W, lam = _whitened(P, rng.normal(size=(6 * k, 12)), R, C_p, split)
        cost = _logdet_cost(W, lam, split)
        w_c, w_s = kernels.ci_det_weight(W, lam, split), ci_weight(cost)
        assert 1e-4 <= w_c <= 1 - 1e-4
        gaps.append(abs(w_c - w_s))
        assert cost(w_c) <= cost(w_s) + 1e-9 * max(1.0, abs(cost(w_s)))
    assert max(gaps) < 1e-6, max(gaps)
    assert np.median(gaps) < 1e-9, np.median(gaps)
    with pytest.raises(np.linalg.LinAlgError):
        kernels.ci_det_weight(np.full((6, 12), np.nan), np.zeros(6), split)
