"""Stereo pipeline (dissertation §5.4): disparity → 3-D points → crop → down-sample →
point-to-plane ICP against the model cloud, started from the predicted relative pose.

The rig is the tracking camera of Table 5.1: two identical, parallel (already rectified)
pinhole cameras, the right one ``baseline`` along +x of the left; the measurement is the
pose of the target body B_j in the LEFT camera frame C (OpenCV axes).

Library calls do the work: ``cv2.StereoBM`` / ``cv2.StereoSGBM`` for disparity,
``cv2.stereoRectify`` for the reprojection matrix Q (eq. 5.6), ``cv2.reprojectImageTo3D``
(eq. 5.7), Open3D ``registration_icp`` with ``TransformationEstimationPointToPlane`` and a
Tukey robust kernel, run from a wide to a tight correspondence distance.

Two practical additions, both driven by the prediction: the disparity search covers only
the disparities the predicted range (± the model radius) allows, and both images are
padded on the left so that OpenCV's invalid left band (``minDisparity + numDisparities``
columns) falls in the padding rather than on the target. Pixels darker than
``min_intensity_dn`` (space, deep shadow) are dropped before reprojection: the sensor noise
on a black sky would otherwise match at random.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from swarmcore.cameras import Intrinsics
from swarmcore.vision_config import StereoConfig

from .views import stereo_intrinsics  # the cameras' intrinsics live with the views; kept importable here

__all__ = ["StereoPipeline", "StereoResult", "tracking_camera_T_CB", "stereo_intrinsics"]


def tracking_camera_T_CB(r_B: np.ndarray) -> np.ndarray:
    """Body → camera attitude of the target-tracking camera (dissertation eq. 5.1):
    the shortest-arc rotation carrying body ẑ onto the line of sight ``r_B``."""
    r = np.asarray(r_B, float)
    r = r / np.linalg.norm(r)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, r)
    s = np.linalg.norm(axis)
    c = float(np.dot(z, r))
    if s < 1e-12:
        R_act = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # 180° about x
    else:
        R_act, _ = cv2.Rodrigues(axis / s * np.arctan2(s, c))
    # R_act carries body axes onto camera axes (columns = camera axes in B); T_CB = R_actᵀ.
    return np.ascontiguousarray(R_act.T)  # C order: results must not depend on layout (bus copies are C)


@dataclass
class StereoResult:
    R_CBj: np.ndarray  # (3, 3) B_j → left camera
    p_C: np.ndarray  # (3,) target origin in the left camera (m)
    fitness: float  # ICP inlier fraction at the tightest distance
    rmse_m: float
    n_points: int
    info: dict = field(default_factory=dict)


def _pose(R, t):
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = t
    return M


class StereoPipeline:
    def __init__(self, cfg: StereoConfig, intr: Intrinsics, baseline_m: float, model_points: np.ndarray,
                 model_normals: np.ndarray, model_radius_m: float):
        import open3d as o3d

        self.cfg = cfg
        self.intr = intr
        self.b = float(baseline_m)
        self.f = float(intr.fx)
        self.radius = float(model_radius_m)
        K = intr.K()
        size = (intr.width, intr.height)
        T = np.array([[-self.b], [0.0], [0.0]])  # OpenCV: X_right = X_left + T (shape (3, 1), stack notes)
        _R1, _R2, _P1, _P2, Q, _r1, _r2 = cv2.stereoRectify(
            K, np.zeros(5), K, np.zeros(5), size, np.eye(3), T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0
        )
        self.Q = Q
        self._o3d = o3d
        # Open3D parallelises ICP's sums with TBB (OMP_NUM_THREADS does not reach it), and
        # a parallel sum's order varies run to run: one thread keeps a seed's numbers the
        # same in-process, across processes and in containers.
        o3d.utility.set_max_threads(1)
        self.target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(model_points, float)))
        self.target.normals = o3d.utility.Vector3dVector(np.asarray(model_normals, float))
        self.min_intensity_dn = cfg.min_intensity_dn

    # ------------------------------------------------------------------ disparity
    def disparity_range(self, predicted_range_m: float | None) -> tuple[int, int]:
        """(minDisparity, numDisparities) for a target centred ``predicted_range_m`` away."""
        cfg = self.cfg
        if not cfg.adaptive_disparity or predicted_range_m is None:
            return 0, cfg.max_disparity
        fb = self.f * self.b
        z_far = predicted_range_m + self.radius + cfg.crop_margin_m
        z_near = max(predicted_range_m - self.radius - cfg.crop_margin_m, 0.5)
        d_min = max(int(np.floor(fb / z_far)) - 2, 0)
        d_max = int(np.ceil(fb / z_near)) + 2
        num = int(16 * np.ceil(max(d_max - d_min, 16) / 16.0))
        return d_min, min(num, cfg.max_disparity)

    def roi(self, p_C_pred: np.ndarray | None, d_max: int) -> tuple[int, int, int, int]:
        """(u0, u1, v0, v1) window of the left image holding the predicted target sphere,
        widened left by ``d_max`` so the right image's matches stay inside it."""
        W, H = self.intr.width, self.intr.height
        if p_C_pred is None or p_C_pred[2] <= self.radius + 0.5:
            return 0, W, 0, H
        rad = self.radius + self.cfg.crop_margin_m
        z = p_C_pred[2] - rad if p_C_pred[2] - rad > 0.5 else 0.5
        u = self.f * p_C_pred[0] / p_C_pred[2] + self.intr.cx
        v = self.f * p_C_pred[1] / p_C_pred[2] + self.intr.cy
        half = self.f * rad / z
        u0 = int(max(0, np.floor(u - half - d_max)))
        u1 = int(min(W, np.ceil(u + half) + 1))
        v0 = int(max(0, np.floor(v - half)))
        v1 = int(min(H, np.ceil(v + half) + 1))
        if u1 - u0 < 32 or v1 - v0 < 32:
            return 0, W, 0, H
        return u0, u1, v0, v1

    def disparity(self, left: np.ndarray, right: np.ndarray, predicted_range_m: float | None = None,
                  roi: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Disparity (px, float32) of the left image (or of its ``roi`` window); NaN where invalid."""
        cfg = self.cfg
        dmin, num = self.disparity_range(predicted_range_m)
        if roi is not None:
            u0, u1, v0, v1 = roi
            left = left[v0:v1, u0:u1]
            right = right[v0:v1, u0:u1]
        pad = dmin + num
        L = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        R = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        m: cv2.StereoMatcher
        if cfg.matcher == "bm":
            m = cv2.StereoBM.create(numDisparities=num, blockSize=cfg.block_size)
            m.setMinDisparity(dmin)
            m.setUniquenessRatio(cfg.uniqueness_ratio)
            m.setSpeckleWindowSize(100)
            m.setSpeckleRange(2)
            m.setTextureThreshold(10)
        else:
            bs = cfg.block_size if cfg.block_size <= 11 else 7
            m = cv2.StereoSGBM.create(
                minDisparity=dmin,
                numDisparities=num,
                blockSize=bs,
                P1=8 * bs * bs,
                P2=32 * bs * bs,
                uniquenessRatio=cfg.uniqueness_ratio,
                speckleWindowSize=100,
                speckleRange=2,
                mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
            )
        d16 = m.compute(L, R)[:, pad:]
        disp = d16.astype(np.float32) / 16.0
        bad = d16 < (dmin * 16)
        if self.min_intensity_dn > 0:
            bad |= left < self.min_intensity_dn
        disp[bad] = np.nan
        return disp

    # ------------------------------------------------------------------ cloud
    def cloud(self, disp: np.ndarray, p_C_pred: np.ndarray | None, rng: np.random.Generator,
              roi: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Disparity → points in the left camera frame, cropped and down-sampled (N, 3)."""
        cfg = self.cfg
        Q = self.Q.copy()
        if roi is not None:  # pixel (u, v) of the window is (u + u0, v + v0) of the image
            Q[0, 3] += Q[0, 0] * roi[0]
            Q[1, 3] += Q[1, 1] * roi[2]
        valid = np.isfinite(disp)
        d = np.where(valid, disp, 0.0).astype(np.float32)
        xyz = cv2.reprojectImageTo3D(d, Q)[valid]
        xyz = xyz[np.isfinite(xyz).all(axis=1) & (xyz[:, 2] > 0)]
        if p_C_pred is not None:
            keep = np.linalg.norm(xyz - p_C_pred, axis=1) <= self.radius + cfg.crop_margin_m
            xyz = xyz[keep]
        n = xyz.shape[0]
        k = min(int(np.ceil(cfg.downsample_fraction * n)), cfg.max_points)
        if k < n:
            xyz = xyz[rng.choice(n, size=k, replace=False)]
        return xyz.astype(float)

    # ------------------------------------------------------------------ registration
    def register(self, xyz_C: np.ndarray, R_CBj_pred: np.ndarray, p_C_pred: np.ndarray):
        """Point-to-plane ICP of the measured cloud onto the model, from the prediction."""
        o3d = self._o3d
        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz_C))
        # Transformation sought: camera → body j (source in C onto the model in B_j).
        T = np.linalg.inv(_pose(R_CBj_pred, p_C_pred))
        res = None
        crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=self.cfg.icp_iterations)
        for dist in self.cfg.icp_distances_m:
            est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=dist))
            res = reg.registration_icp(src, self.target, dist, T, est, crit)
            T = res.transformation
        if res is None:
            raise ValueError("stereo.icp_distances_m is empty: no ICP pass to run")
        T_CBj = np.linalg.inv(T)
        return T_CBj[:3, :3].copy(), T_CBj[:3, 3].copy(), float(res.fitness), float(res.inlier_rmse)

    def measure(self, left: np.ndarray, right: np.ndarray, R_CBj_pred: np.ndarray, p_C_pred: np.ndarray,
                rng: np.random.Generator) -> StereoResult | None:
        """Pose of the target in the left camera, or None (too few points, poor fit)."""
        import time

        t0 = time.perf_counter()
        rng_pred = float(np.linalg.norm(p_C_pred))
        dmin, num = self.disparity_range(rng_pred)
        roi = self.roi(p_C_pred, dmin + num) if self.cfg.roi else None
        disp = self.disparity(left, right, rng_pred, roi)
        t1 = time.perf_counter()
        xyz = self.cloud(disp, p_C_pred, rng, roi)
        t2 = time.perf_counter()
        if xyz.shape[0] < self.cfg.min_points:
            return None
        R, p, fit, rmse = self.register(xyz, R_CBj_pred, p_C_pred)
        t3 = time.perf_counter()
        info = {"ms_disparity": 1e3 * (t1 - t0), "ms_cloud": 1e3 * (t2 - t1), "ms_icp": 1e3 * (t3 - t2)}
        if fit < self.cfg.min_fitness:
            return None
        return StereoResult(R, p, fit, rmse, int(xyz.shape[0]), info)
