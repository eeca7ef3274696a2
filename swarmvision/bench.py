"""Vision benchmarks: ms per rendered frame, per monocular detection + pose, per stereo pair.

Each timing is the median over ``repeats`` frames after a warm-up (the first frame
compiles shaders). Thread counts are recorded with the numbers: llvmpipe's
``LP_NUM_THREADS`` and OpenCV's ``cv2.getNumThreads()``.
"""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import numpy as np

from swarmcore import quat
from swarmcore.vision_config import VisionConfig

__all__ = ["bench_vision", "scenario_rtf"]


def _median_ms(f, repeats: int, warmup: int = 1) -> tuple[float, list]:
    for _ in range(warmup):
        f()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        ts.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(ts)), ts


def bench_vision(cfg: VisionConfig | None = None, repeats: int = 10, log=None) -> dict:
    """Time the pieces at the configured (default) resolutions; returns a JSON-ready dict."""
    import cv2

    from .models import cube_satellite, model_radius, reference_cloud, spacecraft_model
    from .mono import MonoPipeline
    from .noise import apply_noise
    from .render import SceneRenderer
    from .stereo import StereoPipeline
    from .views import face_intrinsics, pair_intrinsics

    cfg = cfg or VisionConfig()
    say = log or (lambda s: None)
    rng = np.random.default_rng(0)
    out: dict[str, Any] = {
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"), "opencv_threads": cv2.getNumThreads(),
                    "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")},
        "repeats": repeats,
    }
    # Monocular: 5 tagged cubes 3-6 m in front of a face camera.
    intr = face_intrinsics(cfg)
    L = cfg.lighting
    r = SceneRenderer([cube_satellite(i) for i in range(5)], ambient=max(L.ambient, 0.1), sun_intensity=L.sun_intensity, shadows=L.shadows)
    out["platform"] = r.platform
    q = quat.random_quaternion(rng, 5)
    pos = np.c_[rng.uniform(-1.5, 1.5, (5, 2)), rng.uniform(3, 6, 5)]
    r.set_bodies(q, pos)
    r.set_sun([0.3, 0.4, -1.0])
    t_render, _ = _median_ms(lambda: r.render(np.eye(3), np.zeros(3), intr), repeats)
    img = r.render(np.eye(3), np.zeros(3), intr)
    t_noise, _ = _median_ms(lambda: apply_noise(img, cfg.noise, rng), repeats)
    noisy = apply_noise(img, cfg.noise, rng)
    mp = MonoPipeline(cfg.mono, intr, 0.2, 5)
    n_poses = len(mp.poses_in_image(noisy, 0))
    t_mono, _ = _median_ms(lambda: mp.poses_in_image(noisy, 0), repeats)
    r.shadows = False
    t_render_ns, _ = _median_ms(lambda: r.render(np.eye(3), np.zeros(3), intr), repeats)
    r.close()
    out["mono"] = {"resolution": [intr.width, intr.height], "focal_px": intr.fx, "render_ms": t_render,
                   "render_no_shadows_ms": t_render_ns, "noise_ms": t_noise, "detect_pose_ms": t_mono,
                   "targets_in_frame": n_poses, "shadows": L.shadows}
    say(f"mono {intr.width}x{intr.height}: render {t_render:.1f} ms (no shadows {t_render_ns:.1f}), noise {t_noise:.1f} ms, "
        f"detection + pose of {n_poses} targets {t_mono:.1f} ms")
    # Stereo: the spacecraft at 10 m and 20 m.
    s = cfg.stereo_camera
    sintr = pair_intrinsics(cfg)
    parts = list(spacecraft_model(0))
    pts, nrm = reference_cloud(cfg.stereo.model_points)
    sp = StereoPipeline(cfg.stereo, sintr, s.baseline_m, pts, nrm, model_radius(parts))
    r = SceneRenderer([parts], ambient=L.ambient, sun_intensity=L.sun_intensity, shadows=L.shadows)
    out["stereo"] = {"resolution": [sintr.width, sintr.height], "focal_px": sintr.fx, "baseline_m": s.baseline_m,
                     "matcher": cfg.stereo.matcher, "by_range": []}
    for dist in (10.0, 20.0):
        qs = quat.random_quaternion(rng)
        p = np.array([0.1, -0.2, dist])
        r.set_bodies(qs[None, :], p[None, :])
        r.set_sun([0.4, 0.6, -1.0])

        def pair():
            left = r.render(np.eye(3), np.zeros(3), sintr)
            right = r.render(np.eye(3), np.array([s.baseline_m, 0, 0]), sintr)
            return apply_noise(left, cfg.noise, rng), apply_noise(right, cfg.noise, rng)

        t_pair_render, _ = _median_ms(pair, max(3, repeats // 2))
        left, right = pair()
        R_true = quat.attitude_matrix(qs).T
        infos: list[dict] = []

        def proc(left=left, right=right, R_true=R_true, p=p, infos=infos):
            res = sp.measure(left, right, R_true, p + 0.05, np.random.default_rng(1))
            infos.append(res.info if res is not None else {})

        t_proc, _ = _median_ms(proc, max(3, repeats // 2))
        parts_ms = {k: float(np.median([i[k] for i in infos if k in i])) for k in ("ms_disparity", "ms_cloud", "ms_icp") if any(k in i for i in infos)}
        out["stereo"]["by_range"].append({"range_m": dist, "render_pair_ms": t_pair_render, "process_pair_ms": t_proc, **parts_ms})
        say(f"stereo {sintr.width}x{sintr.height} at {dist:.0f} m: render pair {t_pair_render:.1f} ms, "
            f"disparity + cloud + ICP {t_proc:.1f} ms ({parts_ms})")
    r.close()
    return out


def scenario_rtf(scenarios, steps: int = 10, log=None) -> list[dict]:
    """Real-time factor (simulated s per wall s) of rendered scenarios: the first ``steps``
    steps of each through :func:`swarmcore.sim.simulate` (render + pipelines + every
    filter), not counting step 0 (shader compilation, the model cloud). ``scenarios``:
    (path, Scenario) pairs, each cut to ``steps`` steps here."""
    import time

    from swarmcore.sim import simulate

    from . import measurement_model

    rows = []
    for path, sc in scenarios:
        sc = sc.model_copy(update={"duration_s": steps * sc.dt_s})
        stamps: list[float] = []

        def tick(_k: int, _K: int, stamps: list[float] = stamps) -> None:
            stamps.append(time.perf_counter())

        simulate(sc, measurement_model(sc), progress=tick)
        wall = stamps[-1] - stamps[0]  # steps 1..K (step 0 excluded)
        step_s = np.diff(stamps)
        row = {
            "scenario": sc.name,
            "path": str(path),
            "n_sats": sc.n_sats,
            "steps_timed": len(step_s),
            "wall_s": float(wall),
            "real_time_factor": float(len(step_s) * sc.dt_s / wall) if wall > 0 else None,
            "step_wall_s_median": float(np.median(step_s)) if len(step_s) else None,
        }
        rows.append(row)
        if log:
            log(f"{sc.name}: real-time factor {row['real_time_factor']:.3f} over {len(step_s)} steps")
    return rows
