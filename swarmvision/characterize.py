"""Monte Carlo error characterisation of a pose pipeline (dissertation §5.4.3, Figure 5.7).

One observer camera at the origin of I (camera frame = I), the target on the boresight at
each range (3 to 33 m by default), in each of ``n_orient`` attitudes (viewing directions
spread over the sphere by a Fibonacci lattice, with a roll drawn from a stream), lit from
each of ``n_sun`` Sun directions (Fibonacci lattice), under each illumination: ``solar``
(the Sun alone) and ``global`` (the Sun plus an ambient term standing in for global
illumination). Every image goes through the same pipeline the agents run; each estimate is
compared with truth in the camera frame (``[a_C, e_C]``, see :mod:`swarmvision.covariance`).

The pipelines are seeded like in flight: the "prediction" (ambiguity resolution for the
monocular pipeline, ICP start for the stereo one) is the truth perturbed by
``pred_sigma_att_rad`` / ``pred_sigma_pos_m``.

Output: ``characterization.json`` (every sample, and per illumination the statistics per
range bin and per Sun-angle bin that :class:`swarmvision.covariance.CharacterizedNoise`
reads) and PNG plots (matplotlib, Agg).
"""

from __future__ import annotations

import itertools
import json
import time
from itertools import pairwise
from pathlib import Path
from typing import Any, Literal

import numpy as np

from swarmcore import quat
from swarmcore.streams import stream
from swarmcore.vision_config import VisionConfig

from .catalogue import camera_signature, model_name, table_name
from .error_model import camera_error

__all__ = ["fit_error_model", "plot_error_model", "flown_geometry", "characterize", "characterize_cell", "fibonacci_sphere", "summarize_samples", "plot", "write"]

AXES = ["att_x", "att_y", "att_z", "pos_x", "pos_y", "pos_z"]


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) nearly uniform unit vectors (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _attitudes(n: int, seed: int) -> np.ndarray:
    """n target attitudes q_BI: a tilt taking body +z onto each Fibonacci direction, then a
    random roll (stream ``characterize_roll``) — spread over all viewing aspects."""
    rng = stream(seed, "characterize_roll")
    z = np.array([0.0, 0.0, 1.0])
    out = []
    for d in fibonacci_sphere(n):
        ax = np.cross(z, d)
        s = np.linalg.norm(ax)
        tilt = np.array([np.pi, 0.0, 0.0]) if s < 1e-12 and d[2] < 0 else (np.zeros(3) if s < 1e-12 else ax / s * np.arctan2(s, d @ z))
        roll = rng.uniform(-np.pi, np.pi)
        out.append(quat.normalize(quat.qmul(quat.rotvec_to_quat(roll * z), quat.rotvec_to_quat(tilt))))
    return np.array(out)


def _sequential(fn, jobs: dict, progress=None) -> dict:
    """The default mapper: every cell in this process, in order."""
    out = {}
    for key, args in jobs.items():
        out[key] = fn(*args)
        if progress is not None:
            progress(len(out), len(jobs))
    return out


def characterize_cell(pipeline: str, cfg_data: dict, illum: str, amb: float, ir: int, rng_m: float, atts, suns,
                      seed: int, pred_sigma_att_rad: float, pred_sigma_pos_m: float) -> list[dict]:
    """One cell of the design — one illumination at one range, every attitude × Sun — as a
    task: plain values in (``cfg_data`` is a :class:`VisionConfig` as a dict), the samples
    out. Every draw comes from ``stream(seed, "characterize", ir, io, isn, illumination)``,
    so a cell gives the same samples in any process and in any order."""
    from .error_model import quantities
    from .mono import MonoPipeline
    from .noise import apply_noise
    from .render import SceneRenderer
    from .views import face_intrinsics, pair_intrinsics

    cfg = VisionConfig.model_validate(cfg_data)
    atts, suns = np.asarray(atts, float), np.asarray(suns, float)
    half = 0.2
    if pipeline == "mono":
        from .models import cube_satellite

        bodies = [cube_satellite(0, half, cfg.mono.tag_size_m, cfg.render.texture_px_per_cell)]
        intr = face_intrinsics(cfg)
        mp = MonoPipeline(cfg.mono, intr, half, 1)
    elif pipeline == "stereo":
        from .models import model_radius, reference_cloud, spacecraft_model
        from .stereo import StereoPipeline

        parts = list(spacecraft_model(0))
        bodies = [parts]
        intr = pair_intrinsics(cfg)
        pts, nrm = reference_cloud(cfg.stereo.model_points)
        sp = StereoPipeline(cfg.stereo, intr, cfg.stereo_camera.baseline_m, pts, nrm, model_radius(parts))
    else:
        raise ValueError(f"pipeline must be mono or stereo, got {pipeline!r}")
    L = cfg.lighting
    rend = SceneRenderer(bodies, ambient=amb, sun_intensity=L.sun_intensity, shadows=L.shadows,
                         znear=cfg.render.znear_m, zfar=cfg.render.zfar_m, platform=cfg.render.platform)
    samples = []
    try:
        for io, q in enumerate(atts):
            for isn, sun in enumerate(suns):
                rng = stream(seed, "characterize", ir, io, isn, 0 if illum == "solar" else 1)
                p_true = np.array([0.0, 0.0, rng_m])
                R_true = quat.attitude_matrix(q).T  # B_j → I = C
                rend.set_bodies(q[None, :], p_true[None, :])
                rend.set_sun(sun)
                # Prediction: truth perturbed like a converged filter's prior.
                dR = quat.attitude_matrix(quat.rotvec_to_quat(rng.normal(0, pred_sigma_att_rad, 3))).T
                R_pred = dR @ R_true
                p_pred = p_true + rng.normal(0, pred_sigma_pos_m, 3)
                ok, err, extra = False, np.full(6, np.nan), {}
                if pipeline == "mono":
                    img = apply_noise(rend.render(np.eye(3), np.zeros(3), intr), cfg.noise, rng)
                    poses = mp.poses_in_image(img, 0, None, {0: R_pred})
                    if 0 in poses:
                        P = poses[0]
                        ok, err = True, camera_error(P.R_CBj, P.p_C, R_true, p_true)
                        extra = {"tags": P.n_tags, "rms_px": P.reproj_rms_px, "ambiguous": P.ambiguous,
                                 "q": quantities(P.R_CBj, P.p_C, sun, rms_px=P.reproj_rms_px, n_tags=P.n_tags)}
                else:
                    left = apply_noise(rend.render(np.eye(3), np.zeros(3), intr), cfg.noise, rng)
                    right = apply_noise(rend.render(np.eye(3), np.array([cfg.stereo_camera.baseline_m, 0, 0]), intr), cfg.noise, rng)
                    res = sp.measure(left, right, R_pred, p_pred, rng)
                    if res is not None:
                        ok, err = True, camera_error(res.R_CBj, res.p_C, R_true, p_true)
                        extra = {"fitness": res.fitness, "points": res.n_points, "rmse_m": res.rmse_m,
                                 "q": quantities(res.R_CBj, res.p_C, sun, fitness=res.fitness, rmse_m=res.rmse_m,
                                                 n_points=res.n_points)}
                sun_deg = float(np.degrees(np.arccos(np.clip(sun[2], -1, 1))))  # LOS is +z
                samples.append({"illumination": illum, "range_m": float(rng_m), "orientation": io, "sun": isn,
                                "sun_deg": sun_deg, "ok": ok, "err": [float(x) for x in err], **extra})
    finally:
        rend.close()
    return samples


def characterize(pipeline: str, cfg: VisionConfig | None = None, ranges=None, n_orient: int = 6, n_sun: int = 6,
                 illuminations=("solar", "global"), ambient_global: float = 0.25, seed: int = 0,
                 pred_sigma_att_rad: float = 0.03, pred_sigma_pos_m: float = 0.1, log=None, progress=None,
                 mapper=None) -> dict:
    """Run the Monte Carlo; return the JSON-ready result (samples and statistics).

    The design is cut into cells (:func:`characterize_cell`: one illumination at one range)
    that ``mapper(fn, jobs, progress)`` runs — ``jobs`` maps a cell's key to its arguments;
    the mapper returns results by key and calls ``progress(cells done, cells)``. The default
    runs them here in order; the application injects a process pool or a Dask cluster
    (:mod:`swarm.studies.executor`). A cell missing from the mapper's answer (it failed) is listed
    under ``missing_cells``. ``progress(done, total)`` counts samples."""
    cfg = (cfg or VisionConfig()).model_copy(deep=True)
    cfg.pipeline = _camera_pipeline(pipeline)
    ranges = np.linspace(3.0, 33.0, 11) if ranges is None else np.asarray(ranges, float)
    atts = _attitudes(n_orient, seed)
    suns = fibonacci_sphere(n_sun)
    cfg_data = cfg.model_dump(mode="json")
    jobs = {}
    for illum in illuminations:
        amb = 0.0 if illum == "solar" else ambient_global
        for ir, rng_m in enumerate(ranges):
            jobs[f"{illum}@{ir}"] = (pipeline, cfg_data, illum, float(amb), ir, float(rng_m), atts, suns, seed,
                                     pred_sigma_att_rad, pred_sigma_pos_m)
    per_cell = len(atts) * len(suns)
    t_start = time.perf_counter()
    cell_progress = None if progress is None else (lambda k, K: progress(k * per_cell, K * per_cell))
    cells = (mapper or _sequential)(characterize_cell, jobs, cell_progress)
    samples = [s_ for key in jobs if key in cells for s_ in cells[key]]
    if log:
        for key, (_, _, illum, _, _, rng_m, *_) in jobs.items():
            if key in cells:
                okn = sum(1 for s_ in cells[key] if s_["ok"])
                log(f"{pipeline} {illum} range {rng_m:.1f} m: {okn}/{len(cells[key])} ok")
            else:
                log(f"{pipeline} {illum} range {rng_m:.1f} m: failed, no samples")
    out: dict[str, Any] = {
        "pipeline": pipeline,
        "camera": camera_signature(cfg, pipeline),
        "axes": AXES,
        "frame": "camera (OpenCV): a_C rotation vector of R_est R_trueᵀ (rad), e_C = p_est − p_true (m)",
        "design": {"ranges_m": ranges.tolist(), "n_orient": n_orient, "n_sun": n_sun, "illuminations": list(illuminations),
                   "ambient_global": ambient_global, "seed": seed, "pred_sigma_att_rad": pred_sigma_att_rad,
                   "pred_sigma_pos_m": pred_sigma_pos_m},
        "config": cfg.model_dump(mode="json"),
        "wall_s": time.perf_counter() - t_start,
        "illuminations": {},
        "missing_cells": [key for key in jobs if key not in cells],
        "samples": samples,
    }
    for illum in illuminations:
        out["illuminations"][illum] = summarize_samples([s for s in samples if s["illumination"] == illum], ranges)
    return out


def _trimmed_mse(E: np.ndarray, k: float = 5.0):
    """Per column: mean square of the errors within k robust σ (1.4826·MAD) of the median,
    and the fraction beyond (outliers the gate must handle, not R)."""
    if E.shape[0] == 0:
        return np.full(E.shape[1], np.nan), np.full(E.shape[1], np.nan)
    med = np.median(E, axis=0)
    mad = 1.4826 * np.median(np.abs(E - med), axis=0)
    inl = np.abs(E - med) <= k * np.maximum(mad, 1e-9)
    mse = np.array([np.mean(E[inl[:, c], c] ** 2) if inl[:, c].any() else np.nan for c in range(E.shape[1])])
    return mse, 1.0 - inl.mean(axis=0)


SUN_EDGES_DEG = np.arange(0, 181, 30)


def summarize_samples(samples: list, ranges, sun_edges=SUN_EDGES_DEG) -> dict:
    """Statistics per range bin and per Sun-angle bin (what the filter's R is built from)."""
    rows: dict[str, list[Any]] = {"range_m": [], "count": [], "success_rate": [], "mean": [], "var": [], "mse": [], "mse_trimmed": [], "outlier_frac": []}
    mse_by_range = {}
    for r in ranges:
        ss = [s for s in samples if s["range_m"] == float(r)]
        E = np.array([s["err"] for s in ss if s["ok"]], float).reshape(-1, 6)
        mt, of = _trimmed_mse(E)
        mse_by_range[float(r)] = mt
        rows["range_m"].append(float(r))
        rows["count"].append(int(E.shape[0]))
        rows["success_rate"].append(float(E.shape[0] / max(1, len(ss))))
        rows["mean"].append((E.mean(0) if len(E) else np.full(6, np.nan)).tolist())
        rows["var"].append((E.var(0) if len(E) > 1 else np.full(6, np.nan)).tolist())
        rows["mse"].append(((E**2).mean(0) if len(E) else np.full(6, np.nan)).tolist())
        rows["mse_trimmed"].append(mt.tolist())
        rows["outlier_frac"].append(of.tolist())
    # Sun-angle factor: each sample's squared error relative to its range bin's trimmed MSE,
    # averaged per Sun bin (trimmed the same way), so the range mix does not leak in.
    centers = 0.5 * (sun_edges[1:] + sun_edges[:-1])
    sun = {"sun_deg": centers.tolist(), "edges_deg": list(map(float, sun_edges)), "count": [], "success_rate": [],
           "factor": [], "mse_trimmed": []}
    for lo, hi in itertools.pairwise(sun_edges):
        ss = [s for s in samples if lo <= s["sun_deg"] < hi or (hi == sun_edges[-1] and s["sun_deg"] == hi)]
        ok = [s for s in ss if s["ok"] and np.all(np.isfinite(mse_by_range[s["range_m"]]))]
        sun["count"].append(len(ok))
        sun["success_rate"].append(float(len(ok) / max(1, len(ss))) if ss else float("nan"))
        if ok:
            E = np.array([s["err"] for s in ok])
            Z = E / np.sqrt(np.array([mse_by_range[s["range_m"]] for s in ok]))
            fz, _ = _trimmed_mse(Z)
            mt, _ = _trimmed_mse(E)
            sun["factor"].append(fz.tolist())
            sun["mse_trimmed"].append(mt.tolist())
        else:
            sun["factor"].append([float("nan")] * 6)
            sun["mse_trimmed"].append([float("nan")] * 6)
    return {"by_range": rows, "by_sun": sun}


def plot(result: dict, out_dir: Path) -> list[Path]:
    """Figure 5.7-style plots: error variance per camera axis versus range and Sun angle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    styles = {"solar": "-", "global": "--"}
    colors = ["tab:red", "tab:green", "tab:blue"]
    fig, axs = plt.subplots(2, 2, figsize=(12, 8))
    for illum, st in result["illuminations"].items():
        ls = styles.get(illum, ":")
        rb, sb = st["by_range"], st["by_sun"]
        r = np.array(rb["range_m"])
        V = np.array(rb["mse_trimmed"], float)
        V[np.array(rb["count"]) < 3] = np.nan  # too few poses for a variance
        S = np.array(sb["mse_trimmed"], float)
        S[np.array(sb["count"]) < 3] = np.nan
        sd = np.array(sb["sun_deg"])
        for k, name in enumerate("XYZ"):
            axs[0, 0].plot(r, V[:, 3 + k], ls, color=colors[k], marker="o", ms=3, label=f"{name} ({illum})")
            axs[0, 1].plot(r, V[:, k], ls, color=colors[k], marker="o", ms=3, label=f"q{k + 1} ({illum})")
            axs[1, 0].plot(sd, S[:, 3 + k], ls, color=colors[k], marker="o", ms=3, label=f"{name} ({illum})")
            axs[1, 1].plot(sd, S[:, k], ls, color=colors[k], marker="o", ms=3, label=f"q{k + 1} ({illum})")
    titles = [("Distance vs. position error variance", "Distance (m)", "Position error variance, camera frame (m²)"),
              ("Distance vs. orientation error variance", "Distance (m)", "Orientation error variance, camera frame (rad²)"),
              ("Sun angle vs. position error variance", "Sun angle (deg)", "Position error variance, camera frame (m²)"),
              ("Sun angle vs. orientation error variance", "Sun angle (deg)", "Orientation error variance, camera frame (rad²)")]
    for ax, (t, xl, yl) in zip(axs.ravel(), titles):
        ax.set_title(t)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.suptitle(f"{result['pipeline']} pipeline: relative pose error (outlier-trimmed MSE) by range and Sun angle")
    fig.tight_layout()
    p1 = out_dir / f"fig5_7_{result['pipeline']}.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    for illum, st in result["illuminations"].items():
        ax.plot(st["by_range"]["range_m"], st["by_range"]["success_rate"], styles.get(illum, ":"), marker="o", label=illum)
    ax.set_xlabel("Distance (m)")
    ax.set_ylabel("fraction of images with a pose")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(f"{result['pipeline']}: success rate vs range")
    fig.tight_layout()
    p2 = out_dir / f"success_{result['pipeline']}.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1, p2]


def stats_only(result: dict) -> dict:
    """The result without its per-sample list: what a filter needs (shipped in ``data/``)."""
    return {k: v for k, v in result.items() if k != "samples"}


def write(result: dict, out_dir: Path) -> dict:
    """Write ``characterization.json`` and the plots; return the file paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / table_name(result["pipeline"], result["camera"])
    path.write_text(json.dumps(result, indent=1, allow_nan=True) + "\n")
    pngs = plot(result, out_dir)
    return {"json": str(path), "plots": [str(p) for p in pngs]}


def vision_config_for(pipeline: str, vision: VisionConfig | None = None) -> VisionConfig:
    """The VisionConfig to characterize: a scenario's ``vision`` section or the defaults,
    with ``pipeline`` forced."""
    cfg = (vision or VisionConfig()).model_copy(deep=True)
    cfg.pipeline = _camera_pipeline(pipeline)
    return cfg


def _camera_pipeline(pipeline: str) -> Literal["mono", "stereo"]:
    """``pipeline`` as a VisionConfig pipeline with cameras (ValueError for any other)."""
    if pipeline == "mono":
        return "mono"
    if pipeline == "stereo":
        return "stereo"
    raise ValueError(f"pipeline must be mono or stereo, got {pipeline!r}")


def run_cli(pipeline: str, out: Path, vision: VisionConfig | None = None, ranges=None, orientations: int = 6,
            suns: int = 6, illuminations=("solar", "global"), ambient_global: float | None = None, seed: int = 0,
            log=print, progress=None, mapper=None) -> dict:
    """What ``swarm characterize`` does: run, write JSON + plots, print a summary table.
    ``vision``: the scenario's vision section to characterize (default: the defaults)."""
    cfg = vision_config_for(pipeline, vision)
    amb = ambient_global if ambient_global is not None else (cfg.lighting.ambient if cfg.lighting.ambient > 0 else 0.25)
    res = characterize(pipeline, cfg, ranges, orientations, suns, tuple(illuminations), amb, seed, log=log, progress=progress,
                       mapper=mapper)
    files = write(res, out)
    m = None
    if any(s_.get("q") for s_ in res["samples"]):
        from .error_model import TooFewSamples

        try:
            m = fit_error_model(res, log=log)
        except TooFewSamples as exc:
            log(f"no error model fitted: {exc} (characterise more ranges, orientations or Sun angles)")
    if m is not None:

        ss = [s_ for s_ in res["samples"] if s_.get("ok") and s_.get("q") and s_["illumination"] == m.meta["illumination"]]
        files["model"] = str(m.write(Path(out) / model_name(pipeline, res["camera"])))
        files["plots"].append(str(plot_error_model(m, [s_["q"] for s_ in ss], np.array([s_["err"] for s_ in ss]),
                                                   Path(out) / f"fit_{pipeline}.png",
                                                   f"{pipeline}: fitted error model vs characterisation errors "
                                                   f"({m.meta['illumination']}, {len(ss)} samples)")))
        log(f"wrote {files['model']} (refit: swarm fit-noise {files['json']} --out MODEL.json)")
    for illum, st in res["illuminations"].items():
        rb = st["by_range"]
        log(f"{pipeline} [{illum}] range → success, σ_pos camera x/y/z (m), σ_att x/y/z (rad), trimmed:")
        for r, ok, v in zip(rb["range_m"], rb["success_rate"], rb["mse_trimmed"]):
            sd = np.sqrt(np.asarray(v, float))
            log(f"  {r:5.1f} m  {ok:4.0%}  pos {sd[3]:.4f} {sd[4]:.4f} {sd[5]:.4f}  att {sd[0]:.4f} {sd[1]:.4f} {sd[2]:.4f}")
    log(f"wrote {files['json']} and {', '.join(files['plots'])}")
    return files


def flown_geometry(sc) -> dict:
    """The ranges and Sun angles a scenario's pairs fly (truth only, no rendering): what a
    characterisation must cover. Pairs of the scenario's graph, every step."""
    from swarmcore.graphs import scenario_graph
    from swarmcore.sensors import relative_pose
    from swarmcore.world import initial_truth, step_truth, world_params

    from .covariance import sun_angle_deg
    from .views import sun_direction_I

    wp = world_params(sc)
    G = scenario_graph(sc)
    obs, tgt = np.nonzero(G & ~np.eye(sc.n_sats, dtype=bool))
    truth = initial_truth(sc)
    rngs, suns = [], []
    for k in range(sc.steps):
        if k > 0:
            truth, _ = step_truth(wp, truth)
        _q, r = relative_pose(sc.orbit.mean_motion_rad_s, truth.t, truth.q_BI, truth.r_H, obs, tgt)
        s_I = sun_direction_I(sc.vision, sc.orbit.mean_motion_rad_s, truth.t)
        T = quat.attitude_matrix(truth.q_BI[obs])
        for m in range(obs.size):
            rngs.append(float(np.linalg.norm(r[m])))
            suns.append(sun_angle_deg(r[m], T[m] @ s_I))
    R, S = np.array(rngs), np.array(suns)
    return {"scenario": sc.name, "range_m": [float(R.min()), float(np.percentile(R, 50)), float(R.max())],
            "sun_deg": [float(S.min()), float(np.percentile(S, 50)), float(S.max())],
            "range_hist": np.histogram(R, bins=np.arange(0, 45, 3))[0].tolist(),
            "sun_hist": np.histogram(S, bins=np.arange(0, 181, 30))[0].tolist()}


def fit_error_model(result: dict, illumination: str | None = None, log=None):
    """The log-linear error model (:mod:`swarmvision.error_model`) of a characterisation's
    samples (one illumination: the one named, else the first)."""
    from .error_model import fit_from_samples

    ill = illumination or result["design"]["illuminations"][0]
    m = fit_from_samples(result["samples"], result["pipeline"], result["camera"], illumination=ill)
    m.meta["characterization"] = {"design": result["design"], "pipeline": result["pipeline"]}
    if log:
        d = m.meta["fit"]
        log(f"{result['pipeline']} [{ill}] error model: {m.meta['samples']} samples, {m.meta['outliers']} outliers "
            f"(z² > {m.meta['gate_z2']:g}); per axis mean/median (e/σ)² of the rest: "
            + ", ".join(f"{k} {v['mean_z2']:.2f}/{v['median_z2']:.2f}" for k, v in d["axes"].items()))
    return m


def plot_error_model(model, qs: list[dict], E: np.ndarray, out_path: Path, title: str, var: np.ndarray | None = None) -> Path:
    """The fitted model against measured errors: per axis, |e| against the predicted σ with
    the binned RMS (a calibration plot: on the diagonal when the model fits); the binned RMS
    and the model's σ against range and against the Sun angle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .error_model import AXES

    E = np.asarray(E, float)
    V = model.var_C_single(qs) if var is None else np.asarray(var, float)
    S = np.sqrt(V)
    rng_m = np.array([q["range_m"] for q in qs])
    sun = np.degrees(np.arccos(np.clip([0.0 if q.get("cos_sun") is None else q["cos_sun"] for q in qs], -1, 1)))
    units = ["rad"] * 3 + ["m"] * 3
    fig, axs = plt.subplots(3, 6, figsize=(22, 10))
    for k in range(6):
        ax = axs[0, k]
        ok = np.isfinite(E[:, k])
        ax.loglog(S[ok, k], np.abs(E[ok, k]) + 1e-9, ".", ms=2, alpha=0.4, color="tab:gray", label="|e| per sample")
        lo, hi = np.percentile(S[ok, k], [1, 99]) if ok.any() else (1e-4, 1.0)
        xs = np.geomspace(lo, hi, 10)
        ax.loglog(xs, xs, "k-", lw=1, label="1σ (model)")
        ax.loglog(xs, 3 * xs, "k:", lw=1, label="3σ")
        edges = np.quantile(S[ok, k], np.linspace(0, 1, 9)) if ok.sum() > 16 else np.array([lo, hi])
        cx, cy = [], []
        for a, b in pairwise(edges):
            m = ok & (S[:, k] >= a) & (S[:, k] <= b)
            e = E[m, k]
            e = e[e**2 <= 10.83 * V[m, k]] if m.any() else e
            if e.size >= 3:
                cx.append(np.sqrt(np.mean(V[m, k])))
                cy.append(np.sqrt(np.mean(e**2)))
        ax.loglog(cx, cy, "o-", color="tab:red", label="RMS per bin (gate-trimmed)")
        ax.set_title(f"{AXES[k]}: measured vs predicted")
        ax.set_xlabel(f"predicted σ ({units[k]})")
        ax.set_ylabel(f"|error| ({units[k]})")
        ax.grid(alpha=0.3, which="both")
        if k == 0:
            ax.legend(fontsize=7)
        for row, x, xl, edges_x in ((1, rng_m, "range (m)", np.unique(np.round(rng_m / 3.0) * 3.0)),
                                    (2, sun, "Sun angle to line of sight (deg)", np.arange(0, 181, 20))):
            ax = axs[row, k]
            centers: np.ndarray
            if row == 1:
                centers = edges_x
                idx = [ok & (np.abs(x - c) <= 1.5) for c in centers]
            else:
                centers = 0.5 * (edges_x[1:] + edges_x[:-1])
                idx = [ok & (x >= a) & (x < b) for a, b in pairwise(edges_x)]
            meas, pred, cc = [], [], []
            for c, m in zip(centers, idx):
                if m.sum() < 3:
                    continue
                e = E[m, k]
                e = e[e**2 <= 10.83 * V[m, k]]
                if e.size < 3:
                    continue
                cc.append(c)
                meas.append(np.sqrt(np.mean(e**2)))
                pred.append(np.sqrt(np.mean(V[m, k])))
            ax.semilogy(cc, meas, "o", color="tab:red", label="measured RMS (gate-trimmed)")
            ax.semilogy(cc, pred, "-", color="k", label="model RMS σ")
            ax.set_xlabel(xl)
            ax.set_ylabel(f"{AXES[k]} ({units[k]})")
            ax.grid(alpha=0.3, which="both")
            if k == 0:
                ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=90)
    plt.close(fig)
    return out_path
