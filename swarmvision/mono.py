"""Monocular fiducial pipeline (dissertation §5.3): tags → target pose in the camera frame.

Per face-camera image:

1. detect AprilTag 36h11 markers (``cv2.aruco.ArucoDetector``); a tag id names the
   satellite and the face (``6 sat + face``);
2. per tag, both IPPE-square solutions (``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)``),
   each turned into a pose of the target body through the known tag placement
   (dissertation eq. 5.5: ``T_CBj = T_CT T_TBj``);
3. combine every visible tag of the same target: each candidate refined by
   Levenberg-Marquardt (``cv2.solvePnPRefineLM``) over all corners of all its tags; the
   lowest reprojection error wins, unless the choice is ambiguous (a single plane seen,
   the two IPPE branches within ``ambiguity_ratio`` or ``ambiguity_px`` of each other): then the candidate
   closest to the predicted relative attitude (the filter's, else the last tracked pose)
   is taken;
4. attach a covariance (see :mod:`swarmvision.covariance`), and convert to the filter's
   measurement, ``q_BjBi`` and ``r_ij_Bi`` in the observer body frame.

The dissertation refines the tag pose with a model-based edge tracker (ViSP); here the
refinement is the joint multi-tag LM, and tracking state only decides how ambiguities are
resolved and reports losing / regaining a target.

Camera-frame pose error convention, used for covariances and characterisation:
``R̃_CBj = exp([a_C×]) R_CBj`` and ``p̃_C = p_C + e_C``. The filter's attitude noise
(``q̃_BjBi = q_BjBi ⊗ δq(a)``, ``a`` in B_i) is then ``a = T_BC a_C`` (see :func:`to_body`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from swarmcore import quat
from swarmcore.cameras import BORESIGHT_B, Intrinsics
from swarmcore.vision_config import MonoConfig

from . import tags

__all__ = [
    "TagDetection",
    "CameraPose",
    "MonoPipeline",
    "to_body",
    "left_jacobian_rodrigues",
    "camera_pose_from_truth",
]


@dataclass(frozen=True)
class TagDetection:
    tag: int
    sat: int
    face: int
    corners_px: np.ndarray  # (4, 2) OpenCV marker order

    @property
    def side_px(self) -> float:
        c = self.corners_px
        return float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))


@dataclass
class CameraPose:
    """Pose of target ``target`` in camera ``camera`` of the observer (OpenCV frame)."""

    target: int
    camera: int
    R_CBj: np.ndarray  # (3, 3) maps B_j coordinates to C
    p_C: np.ndarray  # (3,) target origin in C (m)
    cov_C: np.ndarray  # (6, 6) first-order PnP covariance of [a_C, e_C]
    n_tags: int
    faces: tuple
    reproj_rms_px: float
    ambiguous: bool
    area_px: float
    info: dict = field(default_factory=dict)


def left_jacobian_rodrigues(rvec: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """``∂a_C/∂rvec`` with ``R(rvec + δ) R(rvec)ᵀ = exp([(J δ)×])`` (central differences
    through ``cv2.Rodrigues``; the closed form would be one more hand-written formula)."""
    R0, _ = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))
    J = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        Rp, _ = cv2.Rodrigues((rvec + d).reshape(3, 1))
        Rm, _ = cv2.Rodrigues((rvec - d).reshape(3, 1))
        wp, _ = cv2.Rodrigues(Rp @ R0.T)
        wm, _ = cv2.Rodrigues(Rm @ R0.T)
        J[:, k] = (wp.ravel() - wm.ravel()) / (2 * eps)
    return J


def to_body(R_CBj: np.ndarray, p_C: np.ndarray, T_CBi: np.ndarray, r_C_Bi: np.ndarray):
    """Camera-frame pose → the filter's ``(q_BjBi, r_ij_Bi)``.

    ``T(q_BjBi) = T_BjC T_CBi = R_CBjᵀ T_CBi``; ``r_ij_Bi = T_BiC p_C + r_C_Bi`` with
    ``r_C_Bi`` the camera centre in B_i.
    """
    T_BjBi = R_CBj.T @ T_CBi
    q = quat.from_attitude_matrix(T_BjBi)
    r = T_CBi.T @ p_C + r_C_Bi
    return q, r


def camera_pose_from_truth(q_BjBi: np.ndarray, r_ij_Bi: np.ndarray, T_CBi: np.ndarray, r_C_Bi: np.ndarray):
    """Inverse of :func:`to_body`: ``(R_CBj, p_C)`` of the true relative pose."""
    R_CBj = T_CBi @ quat.attitude_matrix(q_BjBi).T
    p_C = T_CBi @ (np.asarray(r_ij_Bi) - r_C_Bi)
    return R_CBj, p_C


def _rot_angle(Ra, Rb) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


class MonoPipeline:
    """Tag detection and pose solving for one camera model (shared by all face cameras)."""

    def __init__(self, cfg: MonoConfig, intr: Intrinsics, half_size_m: float, n_sats: int | None = None):
        self.cfg = cfg
        self.intr = intr
        self.K = intr.K()
        self.dist = np.zeros(5)
        self.half = half_size_m
        self.n_sats = n_sats
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = {
            "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
            "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
            "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
            "none": cv2.aruco.CORNER_REFINE_NONE,
        }[cfg.corner_refine]
        # Sensor noise on the dark background makes AprilTag's quad search chase thousands of
        # tiny segments (≈300 ms per 1024² frame at 2 DN read noise); requiring a real
        # black/white contrast keeps it at ≈15 ms without losing tags.
        params.aprilTagMinWhiteBlackDiff = int(cfg.min_white_black_diff_dn)
        self.detector = cv2.aruco.ArucoDetector(tags.dictionary(), params)
        # OpenCV's port of the AprilTag quad fit reports corners with pixel CORNERS at
        # integer coordinates (AprilTag's convention) while the rest of OpenCV puts pixel
        # CENTRES there: measured +0.46 px in x and y on warped synthetic tags
        # (tests/test_vision_mono.py pins it). Shift back to OpenCV's convention.
        self.corner_offset_px = 0.5 if cfg.corner_refine == "apriltag" else 0.0
        self.obj_T = tags.tag_corners_T(cfg.tag_size_m)
        self.obj_B = np.stack([tags.tag_corners_B(f, cfg.tag_size_m, half_size_m) for f in range(6)])
        # Tracking state per (observer, target): last step seen and last pose in B_i.
        self.tracks: dict[tuple[int, int], dict] = {}
        self.events: list[tuple[int, int, int, str]] = []  # (step, observer, target, "lost"|"regained"|"acquired")

    # ------------------------------------------------------------------ detection
    def detect(self, gray: np.ndarray) -> list[TagDetection]:
        corners, ids, _rej = self.detector.detectMarkers(gray)
        out = []
        if ids is None:
            return out
        for c, i in zip(corners, ids.ravel()):
            sat, face = tags.sat_face(int(i))
            if self.n_sats is not None and sat >= self.n_sats:
                continue  # a decode of a code no satellite carries: a false positive
            det = TagDetection(int(i), int(sat), int(face), c.reshape(4, 2).astype(float) - self.corner_offset_px)
            if det.side_px >= self.cfg.min_tag_px:
                out.append(det)
        return out

    # ------------------------------------------------------------------ pose
    def _candidates(self, dets: list[TagDetection]):
        """Target poses (rvec, tvec of B_j in C) from each tag's two IPPE solutions."""
        cands = []
        for d in dets:
            n, rvecs, tvecs, _errs = cv2.solvePnPGeneric(
                self.obj_T, d.corners_px, self.K, self.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            for rv, tv in zip(rvecs[:n], tvecs[:n]):
                R_CT, _ = cv2.Rodrigues(rv)
                R_CB = R_CT @ tags.T_TB[d.face]
                t = tv.ravel() - R_CB @ (self.half * BORESIGHT_B[d.face])
                rvB, _ = cv2.Rodrigues(R_CB)
                cands.append((rvB.ravel(), t))
        return cands

    def solve(self, dets: list[TagDetection], camera: int, predicted_R_CBj: np.ndarray | None = None) -> CameraPose | None:
        """One pose of one target from all its tags in one image (None if nothing usable)."""
        if not dets:
            return None
        obj = np.concatenate([self.obj_B[d.face] for d in dets])
        img = np.concatenate([d.corners_px for d in dets])
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-10)
        sols = []
        for rv, tv in self._candidates(dets):
            if tv[2] <= 0:
                continue
            rv = rv.reshape(3, 1).copy()
            tv = tv.reshape(3, 1).copy()
            if len(dets) > 1 and self.cfg.combine == "joint":
                rv, tv = cv2.solvePnPRefineLM(obj, img, self.K, self.dist, rv, tv, crit)
            proj, _ = cv2.projectPoints(obj, rv, tv, self.K, self.dist)
            rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
            R, _ = cv2.Rodrigues(rv)
            sols.append((rms, rv.ravel(), tv.ravel(), R))
        if not sols:
            return None
        sols.sort(key=lambda s: s[0])
        best = sols[0]
        # Distinct alternatives (a different branch, not the same pose reached twice).
        alts = [s for s in sols[1:] if _rot_angle(s[3], best[3]) > np.radians(5.0)]
        # A branch is a real contender if its error is within a factor of the best one's
        # or within ``ambiguity_px`` of it: with 4 corners and ~0.15 px of corner noise,
        # 0.07 px against 0.18 px (measured on a 30 px tag at 10 m, the wrong branch
        # winning) says nothing, although the ratio is 2.5.
        tol = max(self.cfg.ambiguity_ratio * max(best[0], 0.05), best[0] + self.cfg.ambiguity_px)
        ambiguous = bool(alts) and alts[0][0] < tol
        chosen_by = "reprojection"
        if ambiguous and predicted_R_CBj is not None:
            pool = [best] + [s for s in alts if s[0] < tol]
            best = min(pool, key=lambda s: _rot_angle(s[3], predicted_R_CBj))
            chosen_by = "prediction"
        rms, rv, tv, R = best
        # First-order covariance σ² (JᵀJ)⁻¹ of (rvec, tvec), σ from the residual with a floor.
        _, J = cv2.projectPoints(obj, rv, tv, self.K, self.dist)
        J6 = J[:, :6]
        sigma = max(rms * np.sqrt(2 * len(obj) / max(2 * len(obj) - 6, 1)), self.cfg.pixel_sigma_px)
        try:
            cov_rt = sigma**2 * np.linalg.inv(J6.T @ J6)
        except np.linalg.LinAlgError:
            return None
        G = np.zeros((6, 6))
        G[:3, :3] = left_jacobian_rodrigues(rv)
        G[3:, 3:] = np.eye(3)
        cov_C = G @ cov_rt @ G.T
        area = float(sum(cv2.contourArea(d.corners_px.astype(np.float32)) for d in dets))
        return CameraPose(
            target=dets[0].sat,
            camera=camera,
            R_CBj=R,
            p_C=tv,
            cov_C=0.5 * (cov_C + cov_C.T),
            n_tags=len(dets),
            faces=tuple(d.face for d in dets),
            reproj_rms_px=rms,
            ambiguous=ambiguous,
            area_px=area,
            info={"chosen_by": chosen_by, "candidates": len(sols)},
        )

    def poses_in_image(self, gray: np.ndarray, camera: int, observer: int | None = None, predicted=None) -> dict[int, CameraPose]:
        """Every target decoded in one camera image → its pose (``predicted``: target → R_CBj)."""
        dets = self.detect(gray)
        by_target: dict[int, list[TagDetection]] = {}
        for d in dets:
            if observer is not None and d.sat == observer:
                continue
            by_target.setdefault(d.sat, []).append(d)
        out = {}
        for tgt, ds in by_target.items():
            if self.cfg.combine == "best_tag":
                ds = [max(ds, key=lambda d: d.side_px)]
            pred = None if predicted is None else predicted.get(tgt)
            pose = self.solve(ds, camera, pred)
            if pose is not None:
                out[tgt] = pose
        return out

    # ------------------------------------------------------------------ tracking
    def update_tracks(self, step: int, observer: int, seen: dict[int, tuple], expected: set[int] | None = None) -> None:
        """Record which targets ``observer`` measured at ``step`` (``seen``: target → (q, r)).

        A target measured after a gap is "regained" (its ambiguity is then resolved by the
        filter's prediction alone, never by the stale track); a tracked target that is
        not measured (or not expected any more) is "lost".
        """
        for tgt, pose in seen.items():
            tr = self.tracks.get((observer, tgt))
            if tr is None:
                self.events.append((step, observer, tgt, "acquired"))
            elif not tr["tracking"]:
                self.events.append((step, observer, tgt, "regained"))
            self.tracks[(observer, tgt)] = {"step": step, "pose": pose, "tracking": True}
        for (obs, tgt), tr in self.tracks.items():
            if obs == observer and tgt not in seen and tr["tracking"]:
                tr["tracking"] = False
                self.events.append((step, observer, tgt, "lost"))

    def tracked_pose(self, observer: int, target: int, step: int):
        """The last pose (q_BjBi, r_ij_Bi) if the target was measured at the previous step."""
        tr = self.tracks.get((observer, target))
        if tr is None or not tr["tracking"] or tr["step"] != step - 1:
            return None
        return tr["pose"]
