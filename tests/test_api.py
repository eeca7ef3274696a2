"""The Python API (``import swarm``): cheap to import, the same numbers as the CLI, results as
DataFrames, studies; ``swarm.run`` read from the recording equals ``swarm.simulate``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_swarm_is_cheap_and_tunes_the_process_first():
    """``import swarm`` loads no numpy (nor the API) yet chooses the numeric kernels; the
    API's names come when first used, and ``__all__`` lists them."""
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "OPENBLAS_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    code = ("import sys, os, swarm; loaded = [m for m in ('numpy', 'pandas', 'swarm.api') if m in sys.modules]; "
            "names = sorted(n for n in swarm.__all__ if n != '__version__'); ok = all(callable(getattr(swarm, n)) for n in names); "
            "import json; print(json.dumps({'loaded': loaded, 'threads': os.environ.get('OPENBLAS_NUM_THREADS'), 'ok': ok, "
            "'names': names, 'dir': all(n in dir(swarm) for n in names)}))")
    out = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout)
    assert out["loaded"] == [] and out["threads"] == "1" and out["ok"] and out["dir"]
    assert out["names"] == sorted(["Comparison", "MonteCarlo", "Result", "Scenario", "compare", "load_scenario", "monte_carlo",
                                   "run", "simulate"])
    import swarm

    with pytest.raises(AttributeError):
        _ = swarm.no_such_name  # type: ignore[attr-defined]


def test_load_scenario_takes_files_mappings_and_overrides():
    import swarm
    from swarmrt.scenario_files import ScenarioError

    a = swarm.load_scenario(ROOT / "scenarios" / "demo.yaml", duration_s=10, overrides={"estimator.kind": "ci"}, seed=9)
    assert (a.n_sats, a.duration_s, a.estimator.kind, a.seed) == (4, 10, "ci", 9)
    b = swarm.load_scenario(a.model_dump(mode="json"), overrides=["n_sats=6"])
    assert b.n_sats == 6 and b.estimator.kind == "ci"
    assert swarm.load_scenario(a) == a
    with pytest.raises(ScenarioError, match="n_sats"):
        swarm.load_scenario(None, n_sats=0)
    with pytest.raises(ValueError, match=r"estimator\.kind"):
        swarm.load_scenario(None, overrides={"estimator.kind": "kalmanish"})


def test_simulate_gives_the_simulators_numbers_as_dataframes(tmp_path):
    import swarm

    sc = swarm.load_scenario(ROOT / "scenarios" / "demo.yaml", duration_s=8)
    res = swarm.simulate(sc, out=tmp_path / "sim")
    r = res.sim
    assert r is not None
    K, F, n = r.att_err_rad.shape
    e = res.errors.set_index(["k", "filter", "sat"]).sort_index()
    assert len(e) == K * F * n  # the full estimator tracks everyone
    np.testing.assert_array_equal(e["pos_err_m"].to_numpy().reshape(K, F, n), r.pos_err_m)
    np.testing.assert_array_equal(e["att_err_rad"].to_numpy().reshape(K, F, n), r.att_err_rad)
    nees = res.nees.set_index(["k", "filter", "sat"]).sort_index()["nees"].to_numpy().reshape(K, F, n)
    np.testing.assert_array_equal(nees, r.nees)
    # The 1σ columns are the square roots of the covariance frame's variances.
    cov = res.covariances.set_index(["k", "filter", "sat"]).sort_index()
    np.testing.assert_allclose(e["pos_sigma_y_m"] ** 2, cov["pos_var_y_m2"], rtol=1e-14)
    assert list(res.rms.index) == ["full run", "second half"]
    assert res.rms.loc["full run", "others_pos_m"] == res.summary["rms"]["others"]["pos_m"]
    # The folder: summary.json, the arrays and the 3-D scene; read back, the same tables.
    assert {p.name for p in (tmp_path / "sim").iterdir()} >= {"summary.json", "truth.npz", "estimates.npz", "scene.mcap", "scenario.yaml"}
    back = swarm.Result.load(tmp_path / "sim")
    assert back.summary == json.loads(json.dumps(res.summary))
    np.testing.assert_array_equal(back.errors.to_numpy(), res.errors.to_numpy())
    # Overrides as keywords; an estimator that tracks only its own satellite has rows for it alone.
    ci = swarm.simulate(sc, **{"estimator.kind": "ci"})
    assert ci.summary["estimator"] == "ci" and set(ci.errors["sat"]) <= set(range(n))
    fig = res.plot_errors(filter=0, sat=1)
    assert len(fig.axes) == 6
    # The Cramér–Rao bound of the run under the ±3σ band (dashed), on every axis.
    assert all(any(line.get_label() == "±3√bound" for line in ax.get_lines()) for ax in fig.axes)


def test_compare_and_monte_carlo(tmp_path):
    import swarm

    sc = swarm.load_scenario(None, n_sats=3, duration_s=4, seed=5)
    cmp = swarm.compare(sc, estimators=["full", "ci"], runs=2, workers=1, out=tmp_path / "cmp")
    assert cmp.variants == ["full", "ci"] and cmp.doc["seeds"] == [5, 6]
    assert list(cmp.summary.index) == ["full", "ci"] and "rms.others.pos_m mean" in cmp.summary.columns
    per = cmp.per_run
    assert sorted(zip(per["variant"], per["seed"])) == sorted((v, s) for v in ("full", "ci") for s in (5, 6))
    # A run of a variant is the simulation of that variant (the same numbers).
    full5 = per[(per["variant"] == "full") & (per["seed"] == 5)].iloc[0]
    assert full5["rms.others.pos_m"] == swarm.simulate(sc).summary["rms"]["others"]["pos_m"]
    with pytest.raises(ValueError, match="exactly one"):
        swarm.compare(sc, estimators=["full"], strategies=["random"])  # refused before it makes a folder
    mc = swarm.monte_carlo(sc, 2, workers=1, out=tmp_path / "mc")
    assert list(mc.per_run["seed"]) == [5, 6] and "rms.others.pos_m" in mc.stats.index
    assert (tmp_path / "mc" / "mc.json").exists()


@pytest.mark.integration
def test_run_reads_the_recording_into_the_same_result(tmp_path):
    """``swarm.run`` (distributed, lockstep) gives the same tables as ``swarm.simulate``, bit
    for bit, read from its recording. Asked for a live view on a port already taken, it says
    so and runs without it: nothing waits for the view."""
    import socket

    import swarm

    sc = swarm.load_scenario(None, name="api", n_sats=3, duration_s=6, seed=7, overrides={"emulator.step_timeout_s": 20.0})
    said: list[str] = []
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        dist = swarm.run(sc, out=tmp_path / "run", live=f"127.0.0.1:{taken.getsockname()[1]}", log=said.append)
    assert dist.outcome is not None and dist.outcome.exit_code == 0 and dist.source == "run"
    assert any("live view: not serving" in s for s in said), said
    # The run's processes went with it, its agents' fork server too (the standard library
    # would otherwise keep it for the life of this process). Not counted: multiprocessing's
    # resource tracker, which is this process's own (it unlinks what the process leaks).
    import psutil

    left = [c for p in psutil.Process().children(recursive=True) if p.is_running() and p.status() != psutil.STATUS_ZOMBIE
            and "multiprocessing.resource_tracker" not in " ".join(c := p.cmdline())]
    assert not left, left
    sim = swarm.simulate(sc)
    for name in ("errors", "covariances", "nees"):
        a, b = getattr(dist, name), getattr(sim, name)
        assert list(a.columns) == list(b.columns)
        np.testing.assert_array_equal(a.to_numpy(), b.to_numpy(), err_msg=name)
    assert dist.summary["rms"] == sim.summary["rms"]
    again = swarm.Result.load(tmp_path / "run")
    np.testing.assert_array_equal(again.errors.to_numpy(), dist.errors.to_numpy())
