"""AprilTag ids: one unique 36h11 tag per face, decoded back to (satellite, face)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from swarmcore import quat
from swarmcore.cameras import T_CB, Intrinsics


def test_tag_id_roundtrip_and_capacity():
    from swarmvision import tags

    sats, faces = np.meshgrid(np.arange(tags.max_satellites()), np.arange(6), indexing="ij")
    ids = tags.tag_id(sats, faces)
    assert len(np.unique(ids)) == ids.size  # unique per (sat, face)
    s, f = tags.sat_face(ids)
    np.testing.assert_array_equal(s, sats)
    np.testing.assert_array_equal(f, faces)
    assert tags.max_satellites() == 97  # 587 codes in 36h11
    with pytest.raises(ValueError):
        tags.tag_image(tags.N_CODES)


def test_tag_image_has_quiet_zone_and_decodes():
    from swarmvision import tags

    img = tags.face_texture(3, 4, tag_size_m=0.32, face_size_m=0.4, px_per_cell=10)
    assert img.shape == (100, 100)
    assert (img[:10] == 255).all() and (img[:, -10:] == 255).all()  # one white cell all round
    assert (img[10:20, 10:90] == 0).all()  # black border
    canvas = np.pad(img, 40, constant_values=0)  # on a black sky
    det = cv2.aruco.ArucoDetector(tags.dictionary(), cv2.aruco.DetectorParameters())
    _c, ids, _r = det.detectMarkers(canvas)
    assert ids is not None and ids.ravel().tolist() == [6 * 3 + 4]


def test_tag_corners_follow_the_face_frames():
    """Tag corners lie on their face (outward normal = camera boresight), in OpenCV marker
    order: x_T right, y_T up, right-handed with z_T out of the face."""
    from swarmvision import tags

    for f in range(6):
        c = tags.tag_corners_B(f, 0.32, 0.2)
        n = T_CB[f, 2]
        np.testing.assert_allclose(c @ n, 0.2)
        e1, e2 = c[1] - c[0], c[3] - c[0]  # TL→TR (x_T), TL→BL (−y_T)
        np.testing.assert_allclose(np.cross(e1, -e2) / np.linalg.norm(np.cross(e1, e2)), n, atol=1e-12)


@pytest.mark.render
def test_rendered_tag_decodes_to_the_right_satellite_and_face():
    """Every face of two satellites (of a 9-satellite swarm), turned towards a camera 3 m
    away, decodes to tag 6·sat + face, with the four corners where the tag geometry
    projects (< 1 px: the face texture is laid out the right way round)."""
    from swarmcore.vision_config import MonoConfig
    from swarmvision import tags
    from swarmvision.models import cube_satellite
    from swarmvision.mono import MonoPipeline
    from swarmvision.render import SceneRenderer

    n = 9
    intr = Intrinsics.from_fov(640, 640, 60)
    r = SceneRenderer([cube_satellite(i) for i in range(n)], ambient=0.3)
    r.set_sun([0.2, -0.3, -1.0])
    mp = MonoPipeline(MonoConfig(), intr, 0.2, n)
    far = np.array([[100.0 + 10 * i, 0, 0] for i in range(n)])
    for sat in (2, 7):
        for face in range(6):
            # Attitude with face `face` pointing at the camera (−z of I) and a 20° tilt.
            T_BI = T_CB[face].T @ np.diag([1.0, -1.0, -1.0])  # boresight_B(face) ↦ −z_I
            tilt = quat.attitude_matrix(quat.rotvec_to_quat(np.radians([12.0, -15.0, 30.0])))
            q = quat.from_attitude_matrix(T_BI @ tilt)
            r_I = far.copy()
            r_I[sat] = [0.1, -0.05, 3.0]
            q_all = np.tile(quat.IDENTITY, (n, 1))
            q_all[sat] = q
            r.set_bodies(q_all, r_I)
            img = r.render(np.eye(3), np.zeros(3), intr)
            dets = mp.detect(img)
            assert [(d.sat, d.face) for d in dets if d.face == face] == [(sat, face)], [(d.sat, d.face) for d in dets]
            d = next(d for d in dets if d.face == face)
            X = tags.tag_corners_B(face, 0.32, 0.2) @ quat.attitude_matrix(q) + r_I[sat]
            uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), intr.K(), None)
            assert np.abs(d.corners_px - uv.reshape(4, 2)).max() < 1.0
    r.close()
