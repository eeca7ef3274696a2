"""The centralized reference (``estimator: {kind: full, central: true}``): every anchor's
absolute reading applied by every filter; the update forms agree with peers' readings;
without peers' readings it is today's ``full`` to the bit; a distributed run takes it;
over a Monte Carlo it meets the Cramér–Rao bound of what it hears."""

import dataclasses

import numpy as np
import pytest
from test_update_forms import _close, _setup

from swarmcore.mekf import update
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate
from swarmcore.world import absolute_measurements, world_params


@pytest.mark.parametrize("steps", [0, 5], ids=["first-update", "converged"])
def test_update_forms_agree_with_peers_absolute_readings(steps):
    """Stacked (the dissertation's form), sequential and information updates with the own
    reading and two peers' readings as ``{sat: reading}``: the same posterior and NIS, and
    peers' readings shrink those peers' pose variances."""
    est, p, ab, rel = _setup(5, "chain", steps=steps)
    sc = Scenario(n_sats=5, seed=3, graph={"kind": "chain"})
    others = absolute_measurements(world_params(sc), _truth_like(est))
    readings = {p.own: ab, 0: others[0], 3: others[3]}
    out = {m: update(est, p, readings, rel, method=m) for m in ("stacked", "sequential", "information")}
    ref, rep_ref = out["stacked"]
    assert rep_ref.nis_dof == 6 * len(rel) + 18
    for m in ("sequential", "information"):
        e, rep = out[m]
        assert _close(e.P, ref.P, ref.P) < 1e-9, m
        assert rep.nis == pytest.approx(rep_ref.nis, rel=1e-8) and rep.nis_dof == rep_ref.nis_dof
        np.testing.assert_allclose(e.r_H, ref.r_H, rtol=0, atol=1e-12)
    plain, _ = update(est, p, ab, rel, method="information")
    for sat in (0, 3):
        b = 12 * sat
        assert np.trace(ref.P[b + 6 : b + 9, b + 6 : b + 9]) < 0.5 * np.trace(plain.P[b + 6 : b + 9, b + 6 : b + 9])


def _truth_like(est):
    """A truth-shaped state at the estimate (only its positions and attitudes are read)."""
    from swarmcore.world import TruthState

    return TruthState(est.step, est.t, est.q_BI, est.omega_BI_B, est.r_H, est.v_H, np.zeros((est.n, 3)))


def _arrays(r):
    for f in dataclasses.fields(r):
        v = getattr(r, f.name)
        if isinstance(v, np.ndarray) and f.name not in ("step_ms", "cpu_ms"):
            yield f.name, v
    for name in ("q_BI", "r_H_m", "P_diag"):
        yield "est." + name, getattr(r.est, name)


def test_central_without_peer_readings_is_full_to_the_bit():
    """No anchor but satellite 0: filter 0 of the centralized reference hears nothing more
    than `full`'s (its own reading), the others hear satellite 0's too. With no anchor at
    all every filter is `full`'s, array for array."""
    base = {"n_sats": 4, "seed": 11, "duration_s": 12, "graph": {"kind": "chain", "absolute": "none"}}
    full = simulate(Scenario(**base))
    central = simulate(Scenario(**base, estimator={"kind": "full", "central": True}))
    for name, a in _arrays(full):
        b = dict(_arrays(central))[name]
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
    one = {**base, "graph": {"kind": "chain", "absolute": [0]}}
    full = simulate(Scenario(**one))
    central = simulate(Scenario(**one, estimator={"kind": "full", "central": True}))
    np.testing.assert_array_equal(full.est.r_H_m[:, 0], central.est.r_H_m[:, 0])
    np.testing.assert_array_equal(full.est.P_diag[:, 0], central.est.P_diag[:, 0])
    # Filter 3 hears satellite 0's GPS through the centralized reference: it knows satellite 0 better.
    assert np.mean(central.pos_err_m[6:, 3, 0] ** 2) < np.mean(full.pos_err_m[6:, 3, 0] ** 2)
    assert np.all(central.est.P_diag[2:, 3, 6:9] < full.est.P_diag[2:, 3, 6:9])


@pytest.mark.parametrize("est", [{"kind": "full", "central": True}, {"kind": "central"}])
def test_distributed_run_takes_central(tmp_path, est):
    """The peers' readings travel on the radio now (tests/test_central_swarm.py flies it):
    a distributed run no longer refuses the centralized reference."""
    from swarm.supervise.launch import LocalSwarm

    sc = Scenario(n_sats=3, duration_s=5, estimator=est)
    LocalSwarm(sc, tmp_path / "run")


def test_kind_central_is_full_with_central_true():
    base = {"n_sats": 4, "seed": 12, "duration_s": 8, "graph": {"kind": "complete", "absolute": [1, 2]}}
    a = simulate(Scenario(**base, estimator={"kind": "central"}))
    b = simulate(Scenario(**base, estimator={"kind": "full", "central": True}))
    assert a.estimator == "central"
    for name, x in _arrays(a):
        assert np.array_equal(x, dict(_arrays(b))[name], equal_nan=x.dtype.kind == "f"), name


@pytest.mark.slow
def test_central_meets_its_bound_over_monte_carlo():
    """The dissertation's baseline (scenarios/baseline.yaml: 10 satellites, complete graph,
    every one anchored), 60 s, 8 seeds: filter 0 of the centralized reference against the
    bound of what it hears (``bound.filter: 0``: its own gyro, every anchor, every relative
    measurement), second half. Measured 2026-12-06: own position 0.973× √bound, own
    attitude 1.078×, every satellite's position 1.028× (per seed 0.60–1.56: the band is
    wider than the issue's 10 %; 14 s CPU). (The others' attitudes are not compared: their
    gyros never reach filter 0, and the bound's model of them is the torque disturbance.)"""
    from pathlib import Path

    from swarm.api import load_scenario

    path = Path(__file__).resolve().parents[1] / "scenarios" / "baseline.yaml"
    err: dict[str, list] = {"pos": [], "opos": [], "att": []}
    bnd: dict[str, list] = {"pos": [], "opos": [], "att": []}
    for s in range(8):
        sc = load_scenario(path, seed=700 + s, duration_s=60, overrides={"estimator.kind": "central", "bound.filter": 0})
        r = simulate(sc)
        b = r.bound
        assert b is not None and b.kind == "filter 0" and r.estimator == "central"
        h = sc.steps // 2
        err["pos"].append(r.pos_err_m[h:, 0, 0] ** 2)
        bnd["pos"].append(b.pos_m2[h:, 0])
        err["att"].append(r.att_err_rad[h:, 0, 0] ** 2)
        bnd["att"].append(b.att_rad2[h:, 0])
        err["opos"].append(r.pos_err_m[h:, 0, :] ** 2)
        bnd["opos"].append(b.pos_m2[h:, :])
    ratios = {k: float(np.sqrt(np.mean(err[k]) / np.mean(bnd[k]))) for k in err}
    print("central filter 0, baseline, RMS / sqrt(bound), 8 seeds x 60 s, 2nd half:", ratios)
    for k in ("pos", "opos", "att"):
        assert 0.85 < ratios[k] < 1.15, (k, ratios[k])
