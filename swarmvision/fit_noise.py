"""Fit a pose pipeline's measurement-noise model (``swarm fit-noise``): the log-linear
per-axis σ model from characterisation samples, optionally re-centred on errors seen in
flight, and its temporal inflation τ from runs' residuals.

* **Fit** (:func:`swarmvision.characterize.fit_error_model`): log σ² linear in what the
  agent knows when it measures, from the samples of one illumination.
* **Flight scale** (:func:`recentre_on_flight`): characterisation and flight differ (the
  target's motion, the predicted pose seeding ICP); each axis's intercept is shifted so
  that the median of the runs' normalised squared errors (e/σ)² is the χ²₁ median,
  keeping the model's dependence on the features.
* **Temporal inflation** (:func:`temporal_inflation`): errors persist from step to step,
  so a filter averaging W of them is overconfident by the variance factor of their mean;
  τ per axis from the autocorrelation of the normalised errors
  (:func:`swarmvision.error_model.autocorrelation`), at least 1.
"""

from __future__ import annotations

import gzip
import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from .error_model import CHI2_1_MEDIAN, ErrorModel, autocorrelation
from .residuals import normalised_series, read_residuals, summarize_residuals

__all__ = ["load_samples", "recentre_on_flight", "temporal_inflation", "fit_noise"]


def load_samples(table: Path) -> dict:
    """A characterisation JSON (``.json`` or ``.json.gz``) that carries its samples."""
    raw = Path(table).read_bytes()
    if Path(table).suffix == ".gz":
        raw = gzip.decompress(raw)
    res = json.loads(raw)
    if "samples" not in res:
        raise ValueError(f"{table}: no samples (a shipped statistics-only table?): run swarm characterize")
    return res


def recentre_on_flight(m: ErrorModel, runs: Sequence[dict], names: Sequence[str]) -> np.ndarray:
    """Shift each axis's log-variance intercept so that the median (e/σ)² of the runs'
    errors is the χ²₁ median; returns the variance factor per axis (and records it in
    ``m.meta["flight_scale"]``)."""
    E = np.concatenate([rr["err"] for rr in runs])
    V = np.concatenate([m.var_C_single(rr["q"]) for rr in runs])
    z2 = E**2 / V
    ok = np.all(np.isfinite(z2), axis=1)
    shift = np.log(np.median(z2[ok], axis=0) / CHI2_1_MEDIAN)
    m.coef[:, 0] += shift
    m.min_var = m.min_var * np.exp(shift)
    m.max_var = m.max_var * np.exp(shift)
    factor = np.exp(shift)
    m.meta["flight_scale"] = {"runs": list(names), "var_factor": factor.tolist()}
    return factor


def temporal_inflation(m: ErrorModel, runs: Sequence[dict], names: Sequence[str], max_lag: int = 10,
                       window: int | None = None) -> dict:
    """Set ``m.temporal_inflation`` (τ per axis, ≥ 1) from the autocorrelation of the runs'
    errors normalised by the model's σ of one measurement; returns the per-run statistics
    and the autocorrelation (also recorded in ``m.meta["temporal"]``)."""
    series: list[np.ndarray] = []
    per_run = []
    for name, rr in zip(names, runs, strict=True):
        v = m.var_C_single(rr["q"])
        series += normalised_series(rr, v)
        st = summarize_residuals(rr, v, max_lag)
        per_run.append({"run": str(name), "n": st["n"], "mean_z2": st["mean_z2"], "median_z2": st["median_z2"],
                        "lag1": st["lag1"], "tau": st["tau"]})
    ac = autocorrelation(series, max_lag, window)
    m.temporal_inflation = np.maximum(np.asarray(ac["tau"]), 1.0)
    m.meta["temporal"] = {"runs": per_run, "lag1": ac["lag1"], "tau": ac["tau"], "max_lag": max_lag, "window": window, "rho": ac["rho"]}
    return {"runs": per_run, **ac}


def fit_noise(table: Path, out: Path, residuals: Sequence[Path] = (), illumination: str | None = None, max_lag: int = 10,
              window: int | None = None, flight_scale: bool = False, log: Callable[[str], None] = print) -> tuple[ErrorModel, list[Path]]:
    """The whole of ``swarm fit-noise``: fit, optionally re-centre and inflate, write the
    model to ``out`` and its plots beside it. Raises OSError / ValueError / KeyError on a
    table it cannot use."""
    from .characterize import fit_error_model, plot_error_model

    res = load_samples(table)
    m = fit_error_model(res, illumination, log=log)
    ss = [s for s in res["samples"] if s.get("ok") and s.get("q") and s["illumination"] == m.meta["illumination"]]
    plots = [plot_error_model(m, [s["q"] for s in ss], np.array([s["err"] for s in ss]), out.with_name(out.stem + "-fit.png"),
                              f"{m.pipeline}: fitted error model vs characterisation errors ({len(ss)} samples)")]
    if residuals:
        runs = [read_residuals(p) for p in residuals]
        names = [str(p) for p in residuals]
        if flight_scale:
            factor = recentre_on_flight(m, runs, names)
            log(f"re-centred on the runs' errors: variance × {'/'.join(f'{x:.3g}' for x in factor)}")
        ac = temporal_inflation(m, runs, names, max_lag, window)
        log("in flight, normalised by the fitted σ (one measurement alone): " + "; ".join(
            f"{r['run']}: n {r['n']}, mean (e/σ)² {'/'.join(f'{x:.2f}' for x in r['mean_z2'])}" for r in ac["runs"]))
        log(f"lag-1 autocorrelation {'/'.join(f'{x:.2f}' for x in ac['lag1'])} → temporal inflation τ "
            f"{'/'.join(f'{x:.2f}' for x in m.temporal_inflation)}")
        V = np.concatenate([m.var_C_single(rr["q"]) for rr in runs])
        plots.append(plot_error_model(m, [q for rr in runs for q in rr["q"]], np.concatenate([rr["err"] for rr in runs]),
                                      out.with_name(out.stem + "-flight.png"),
                                      f"{m.pipeline}: fitted error model (one measurement) vs errors in flight", var=V))
    m.write(out)
    return m, plots
