"""The scoring of a run (swarmcore.result.RunBuilder) on numbers no honest filter sends:
a diverged or damaged estimate is scored, never a numpy warning (the mcap fuzz harness
found an overflow in the error norm of a recording's estimate of 1e200 m)."""

from __future__ import annotations

import warnings

import numpy as np

from swarmcore.result import RunBuilder


def _builder(n: int = 3) -> RunBuilder:
    b = RunBuilder(2, n)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    r = np.arange(3 * n, dtype=float).reshape(n, 3) * 100.0
    b.truth_at(0, 0.0, q, np.zeros((n, 3)), r, np.zeros((n, 3)), np.zeros((n, 3)))
    return b


def test_a_diverged_estimate_scores_an_infinite_error_without_a_warning():
    n = 3
    b = _builder(n)
    ids = np.arange(n)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    r = np.full((n, 3), 1e200)
    r[0] = b.truth.r_H_m[0, 0]  # its own estimate exact, the peers' far beyond any orbit
    P_pose = np.tile(np.eye(6) * 1e-300, (n, 1, 1))
    P_pose[2] = 0.0  # and one claiming certainty: singular
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b.estimate_at(0, 0, ids, q, np.zeros((n, 3)), r, np.zeros((n, 3)), np.zeros(3), np.ones(12 * n), P_pose, P_pose)
    assert b.pos_err_m[0, 0, 0] == 0.0
    assert np.isinf(b.pos_err_m[0, 0, 1:]).all()
    assert np.isinf(b.rel_pos_err_m[0, 0, 1:]).all()
    assert not np.isfinite(b.nees[0, 0, 1:]).any()  # (LAPACK on a pivot of 1e-300: NaN)
    assert np.isinf(b.nees[0, 0, 2]) and np.isinf(b.rel_nees[0, 0, 2])  # a claimed certainty, wrong: inf


def test_an_estimate_with_nan_scores_nan_without_a_warning():
    n = 3
    b = _builder(n)
    ids = np.arange(n)
    q = np.tile([np.nan, 0.0, 0.0, 1.0], (n, 1))
    r = np.full((n, 3), np.nan)
    P_pose = np.tile(np.full((6, 6), np.nan), (n, 1, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b.estimate_at(0, 0, ids, q, np.zeros((n, 3)), r, np.zeros((n, 3)), np.zeros(3), np.ones(12 * n), P_pose, P_pose)
    assert np.isnan(b.pos_err_m[0, 0]).all()
