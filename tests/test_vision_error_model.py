"""The fitted measurement-noise model (swarmvision.error_model): the fit recovers a known
law, its autocorrelation inflation makes a filter of correlated measurements consistent,
and the pose estimator attaches what the model says. No rendering: fast."""

from __future__ import annotations

import json

import numpy as np
import pytest

from swarmvision.error_model import (
    CHI2_1_MEDIAN,
    FEATURES,
    ErrorModel,
    autocorrelation,
    feature_matrix,
    fit,
    fit_from_samples,
    load_model,
    quantities,
)


def _random_quantities(rng, n):
    los = rng.normal(size=(n, 3))
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    cols = zip(rng.uniform(8, 34, n), rng.uniform(-1, 1, n), los.tolist(), rng.uniform(0.4, 1.0, n),
               rng.uniform(0.005, 0.05, n), rng.integers(100, 1500, n))
    return [{"range_m": float(r), "cos_sun": float(c), "los_Bj": u, "fitness": float(f), "rmse_m": float(e), "n_points": float(p)}
            for r, c, u, f, e, p in cols]


def test_fit_recovers_known_coefficients():
    rng = np.random.default_rng(1)
    names = FEATURES["stereo"]
    qs = _random_quantities(rng, 30000)
    X = feature_matrix(names, qs)
    true = rng.normal(0, 0.5, size=(6, len(names)))
    true[:, 0] = np.log([1e-4, 1e-4, 4e-5, 1e-4, 1e-4, 9e-4])
    sig = np.sqrt(np.exp(X @ true.T))
    E = sig * rng.standard_normal(sig.shape)
    coef, diag = fit(X, E, ridge=0.0, calibrate="harvey")
    # log e² = log σ² + log z², var(log z²) = π²/2: each coefficient's standard error is
    # sqrt(π²/2 · (XᵀX)⁻¹_kk); every one of the 72 comes back within 4 of them.
    se = np.sqrt(np.pi**2 / 2 * np.diag(np.linalg.inv(X.T @ X)))
    assert np.all(np.abs(coef - true) < 4 * se[None, :]), (np.abs(coef - true) / se).max()
    assert se.max() < 0.1
    assert np.max(np.abs(coef - true)) > 0  # a real fit, not an echo
    for ax in diag["axes"].values():
        assert 0.85 < ax["mean_z2"] < 1.15
    coef_m, diag_m = fit(X, E, ridge=0.0, calibrate="median")
    for ax in diag_m["axes"].values():
        assert ax["median_z2"] == pytest.approx(CHI2_1_MEDIAN, rel=1e-9)
    np.testing.assert_allclose(coef_m[:, 1:], coef[:, 1:])  # calibration moves the intercept only


def test_fit_from_samples_leaves_gross_failures_out_and_round_trips(tmp_path):
    rng = np.random.default_rng(2)
    names = FEATURES["stereo"]
    qs = _random_quantities(rng, 5000)
    X = feature_matrix(names, qs)
    true = np.zeros((6, len(names)))
    true[:, 0] = np.log(1e-4)
    true[:, 1] = 2.0  # σ ∝ range
    E = np.sqrt(np.exp(X @ true.T)) * rng.standard_normal((5000, 6))
    bad = rng.choice(5000, 100, replace=False)
    E[bad] = rng.normal(0, 1.0, (100, 6))  # ICP to the wrong pose: errors of ~1 rad, ~1 m
    samples = [{"ok": True, "q": q, "err": e.tolist(), "illumination": "solar"} for q, e in zip(qs, E)]
    samples.append({"ok": False, "err": [float("nan")] * 6, "illumination": "solar"})
    m = fit_from_samples(samples, "stereo", {"width_px": 1024, "height_px": 1024, "focal_px": 1440.0})
    assert m.meta["outliers"] >= 95
    np.testing.assert_allclose(m.coef[:, 1], 2.0, atol=0.3)
    np.testing.assert_allclose(m.coef[:, 0], np.log(1e-4), atol=0.3)
    m.temporal_inflation = np.array([2.0, 2, 2, 3, 3, 3])
    p = m.write(tmp_path / "m.json")
    m2 = load_model(p)
    q = qs[0]
    np.testing.assert_allclose(m2.var_C(q), m.var_C(q))
    np.testing.assert_allclose(m2.var_C(q) / m2.var_C_single(q), [2, 2, 2, 3, 3, 3])
    d = json.loads(p.read_text())
    d["features"] = [*d["features"][:-1], "bogus"]
    with pytest.raises(ValueError, match="bogus"):
        ErrorModel.from_json(d)
    d = json.loads(p.read_text())
    d["temporal_inflation"] = 0.5
    with pytest.raises(ValueError, match="temporal_inflation"):
        ErrorModel.from_json(d)


def test_quantities_are_what_the_agent_knows():
    # Target 10 m ahead on the boresight, body axes = camera axes, Sun behind the observer.
    q = quantities(np.eye(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, -1.0]), fitness=0.9, rmse_m=0.01, n_points=500)
    assert q["range_m"] == pytest.approx(10.0)
    assert q["cos_sun"] == pytest.approx(-1.0)  # 180°: fully lit
    np.testing.assert_allclose(q["los_Bj"], [0, 0, -1])  # the observer sits on the target's −z side
    X = feature_matrix(FEATURES["stereo"], [q])
    assert X[0, FEATURES["stereo"].index("log_range")] == pytest.approx(0.0)
    assert quantities(np.eye(3), np.array([0.0, 0.0, 10.0]), None)["cos_sun"] is None


def test_autocorrelation_inflation_makes_a_filter_of_correlated_errors_consistent():
    """A constant observed through AR(1) errors (ρ = 0.8): a Kalman filter taking them as
    independent is overconfident (NEES ≫ 1); with R × τ from :func:`autocorrelation` of the
    errors it is consistent."""
    rng = np.random.default_rng(3)
    rho, T, runs = 0.8, 300, 400
    e = np.zeros((runs, T))
    e[:, 0] = rng.standard_normal(runs)
    for t in range(1, T):
        e[:, t] = rho * e[:, t - 1] + np.sqrt(1 - rho**2) * rng.standard_normal(runs)
    ac = autocorrelation([np.repeat(x[:, None], 6, axis=1) for x in e[:50]], max_lag=40)
    assert ac["lag1"][0] == pytest.approx(rho, abs=0.05)
    tau = ac["tau"][0]
    assert tau == pytest.approx((1 + rho) / (1 - rho), rel=0.25)

    def nees(R):
        # x constant, prior N(0, 100); measurements y = x + e; final NEES over the runs.
        x = rng.normal(0, 10, runs)
        xh, P = np.zeros(runs), 100.0
        for t in range(T):
            K = P / (P + R)
            xh = xh + K * (x + e[:, t] - xh)
            P = (1 - K) * P
        return np.mean((x - xh) ** 2 / P)

    assert nees(1.0) > 4.0
    assert 0.7 < nees(tau) < 1.5


def test_windowed_inflation_of_a_persistent_bias():
    """Errors that are half a per-pair bias, half white noise: ρ_l ≈ 0.5 at every lag,
    the positive-sequence sum would grow without bound, the W-step factor is 1 + 0.5 (W − 1)
    — the variance of a W-step mean of such errors, checked directly."""
    rng = np.random.default_rng(4)
    pairs, T, c, W = 400, 60, 0.5, 20
    z = np.sqrt(c) * rng.standard_normal((pairs, 1, 6)) + np.sqrt(1 - c) * rng.standard_normal((pairs, T, 6))
    ac = autocorrelation(list(z), max_lag=30, window=W)
    np.testing.assert_allclose(np.array(ac["rho"])[1:20].mean(0), c, atol=0.05)
    np.testing.assert_allclose(ac["tau"], 1 + c * (W - 1), rtol=0.1)
    var_of_mean = z[:, :W].mean(axis=1).var(axis=0) * W  # in units of one error's variance
    np.testing.assert_allclose(ac["tau"], var_of_mean, rtol=0.2)


def test_pose_estimator_attaches_the_fitted_model(tmp_path):
    from swarmcore.vision_config import VisionConfig
    from swarmvision.catalogue import camera_signature
    from swarmvision.covariance import floor_cov
    from swarmvision.pose_estimator import VisionPoseEstimator

    cfg = VisionConfig(pipeline="stereo")
    names = FEATURES["stereo"]
    coef = np.zeros((6, len(names)))
    coef[:, 0] = np.log([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4])
    coef[:, names.index("log_range")] = 2.0
    m = ErrorModel("stereo", camera_signature(cfg, "stereo"), names, coef, np.full(6, 4.0))
    path = m.write(tmp_path / "model.json")
    cfg.covariance = cfg.covariance.model_copy(update={"source": "fitted", "model": str(path)})
    est = VisionPoseEstimator(cfg, 4, 0.2, 0, 1e-3)
    q = quantities(np.eye(3), np.array([0.0, 0.0, 20.0]), np.array([1.0, 0, 0]), fitness=0.9, rmse_m=0.01, n_points=500)
    got = est._cov_C(20.0, 90.0, None, q)
    want = np.diag([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4]) * 4.0 * 4.0  # (20/10)² × τ 4
    np.testing.assert_allclose(got, floor_cov(want, cfg.covariance))
    # A model for another camera is refused, naming the fix.
    m.camera = {"width_px": 2000, "height_px": 2000, "focal_px": 875.0, "baseline_m": 0.5}
    m.write(tmp_path / "other.json")
    cfg.covariance = cfg.covariance.model_copy(update={"model": str(tmp_path / "other.json")})
    with pytest.raises(ValueError, match="characterize"):
        VisionPoseEstimator(cfg, 4, 0.2, 0, 1e-3)
    cfg.covariance = cfg.covariance.model_copy(update={"model": str(tmp_path / "missing.json")})
    with pytest.raises(ValueError, match="no error model"):
        VisionPoseEstimator(cfg, 4, 0.2, 0, 1e-3)


def test_fit_noise_command_fits_sets_tau_from_residuals_and_plots(tmp_path):
    """`swarm fit-noise`: samples → model; a run's residuals (bias + white noise) → τ over
    the window; the plots of the model against both."""
    from typer.testing import CliRunner

    from swarm.cli import app
    from swarmvision.residuals import write_residuals

    rng = np.random.default_rng(5)
    names = FEATURES["stereo"]
    qs = _random_quantities(rng, 600)
    true = np.zeros((6, len(names)))
    true[:, 0] = np.log(1e-4)
    true[:, 1] = 2.0
    sig = np.sqrt(np.exp(feature_matrix(names, qs) @ true.T))
    cam = {"width_px": 1024, "height_px": 1024, "focal_px": 1440.0, "baseline_m": 0.5}
    samples = [{"ok": True, "q": q, "err": (s_ * rng.standard_normal(6)).tolist(), "illumination": "solar"}
               for q, s_ in zip(qs, sig, strict=True)]
    table = tmp_path / "char.json"
    table.write_text(json.dumps({"pipeline": "stereo", "camera": cam, "design": {"illuminations": ["solar"]},
                                 "samples": samples}))
    # A run: 6 pairs × 40 steps, errors half a per-pair bias, half white noise.
    T, P = 40, 6
    run_q = _random_quantities(rng, T * P)
    s_run = np.sqrt(np.exp(feature_matrix(names, run_q) @ true.T))
    z = np.sqrt(0.5) * rng.standard_normal((P, 1, 6)) + np.sqrt(0.5) * rng.standard_normal((P, T, 6))
    err = (z.reshape(P * T, 6)) * s_run
    res = {"step": np.tile(np.arange(T), P), "observer": np.repeat(np.arange(P), T), "target": np.full(P * T, 7),
           "err": err, "var": s_run**2, "q": run_q}
    write_residuals(res, tmp_path / "measurements.npz")
    out = tmp_path / "model.json"
    r = CliRunner().invoke(app, ["fit-noise", str(table), "--residuals", str(tmp_path / "measurements.npz"),
                                 "--window", "10", "--out", str(out)])
    assert r.exit_code == 0, r.output
    m = load_model(out)
    np.testing.assert_allclose(m.coef[:, 1], 2.0, atol=1.0)  # 600 samples, 12 features: a loose check
    assert np.all(np.asarray(m.temporal_inflation) > 2.5) and np.all(np.asarray(m.temporal_inflation) < 9.0)  # 1 + 0.5·9 = 5.5
    for png in ("model-fit.png", "model-flight.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = tmp_path / "stats-only.json"
    bad.write_text(json.dumps({"pipeline": "stereo", "camera": cam}))
    r = CliRunner().invoke(app, ["fit-noise", str(bad), "--out", str(tmp_path / "x.json")])
    assert r.exit_code == 2 and "no samples" in " ".join(r.output.split())  # the console wraps long paths


@pytest.mark.render
@pytest.mark.slow
def test_rendered_stereo_run_attaches_the_model_and_its_errors_fit_it():
    """stereo-4sat-short cut to 3 satellites and 4 steps: every stereo measurement is
    recorded with the R the shipped model attaches (× τ), and its error against the truth,
    in units of the σ of one measurement alone, is neither far above nor far below 1."""
    from pathlib import Path

    from swarm.simulation import simulate_scenario
    from swarmrt.scenario_files import load_scenario
    from swarmvision.covariance import floor_cov, resolve_model_path
    from swarmvision.residuals import residuals, summarize_residuals

    root = Path(__file__).resolve().parents[1]
    sc = load_scenario(root / "scenarios" / "stereo-4sat-short.yaml", ["n_sats=3", "duration_s=4"])
    records: list = []
    res = simulate_scenario(sc, measurements=records)
    assert len(records) >= 0.8 * int(res.schedule.sum())
    cam = records[0]["q"]
    m = load_model(resolve_model_path(sc.vision.covariance.model, "stereo", {"width_px": 1024, "height_px": 1024,
                                                                          "focal_px": 1440.0, "baseline_m": 0.5}))
    want = np.array([np.diag(floor_cov(np.diag(m.var_C(rc["q"])), sc.vision.covariance)) for rc in records])
    np.testing.assert_allclose([rc["var_C"] for rc in records], want)
    assert cam["fitness"] > 0 and cam["n_points"] >= sc.vision.stereo.min_points
    rr = residuals(records, res.truth, res.t_s, sc.orbit.mean_motion_rad_s)
    assert np.nanmax(np.abs(rr["err"][:, 3:])) < 1.0  # metres: the truth residuals are in the right frame
    st = summarize_residuals(rr, m.var_C_single(rr["q"]))
    for x in st["mean_z2_clipped"]:
        assert 0.05 < x < 5.0
