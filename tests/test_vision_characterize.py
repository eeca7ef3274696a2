"""Error characterisation (Monte Carlo over range, attitude, Sun) and R built from it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def test_fibonacci_sphere_is_spread_out():
    from swarmvision.characterize import fibonacci_sphere

    d = fibonacci_sphere(20)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.linalg.norm(d.mean(axis=0)) < 0.1  # no preferred direction
    dots = d @ d.T - 2 * np.eye(20)
    assert np.degrees(np.arccos(dots.max())) > 25  # no two within 25°


def _table(ranges, var_pos, var_att, sun_factor=None):
    n = len(ranges)
    return {
        "pipeline": "mono",
        "camera": {"width_px": 1024, "height_px": 1024, "focal_px": 512.0},
        "illuminations": {
            "solar": {
                "by_range": {"range_m": list(ranges), "count": [10] * n,
                             "mse_trimmed": [list(a) + list(p) for a, p in zip(var_att, var_pos, strict=True)]},
                "by_sun": {"sun_deg": [45.0, 135.0], "factor": sun_factor or [[1.0] * 6, [1.0] * 6]},
            }
        },
    }


def test_characterized_noise_interpolates_range_and_sun():
    from swarmcore.vision_config import CovarianceConfig
    from swarmvision.covariance import CharacterizedNoise

    tab = _table([3.0, 6.0], [[1e-4, 1e-4, 4e-4], [4e-4, 4e-4, 16e-4]], [[1e-4] * 3, [4e-4] * 3],
                 sun_factor=[[4.0] * 6, [1.0] * 6])
    cfg = CovarianceConfig(min_sigma_pos_m=1e-6, min_sigma_att_rad=1e-6)
    cn = CharacterizedNoise(tab, cfg, "solar", {"width_px": 1024, "height_px": 1024, "focal_px": 512.0})
    c = cn.cov_C(4.5, None)
    assert c[5, 5] == pytest.approx(10e-4)  # linear between 3 m and 6 m
    assert cn.cov_C(12.0, None)[5, 5] == pytest.approx(16e-4 * 4)  # beyond the table: ∝ range²
    assert cn.cov_C(3.0, 45.0)[3, 3] == pytest.approx(4e-4)  # backlit bin ×4
    assert cn.cov_C(3.0, 135.0)[3, 3] == pytest.approx(1e-4)
    # An empty Sun bin takes its nearest populated neighbour's factor, not a neutral 1.
    tab2 = _table([3.0, 6.0], [[1e-4, 1e-4, 4e-4], [4e-4, 4e-4, 16e-4]], [[1e-4] * 3, [4e-4] * 3],
                  sun_factor=[[float("nan")] * 6, [4.0] * 6])
    tab2["illuminations"]["solar"]["by_sun"]["sun_deg"] = [15.0, 45.0]
    assert CharacterizedNoise(tab2, cfg).cov_C(3.0, 10.0)[3, 3] == pytest.approx(4e-4)
    with pytest.raises(ValueError, match="characterize"):
        CharacterizedNoise(tab, cfg, "solar", {"width_px": 2000, "height_px": 2000, "focal_px": 875.0})


@pytest.mark.render
def test_small_characterization_writes_statistics_and_plots(tmp_path):
    """A 2-range × 2-attitude × 3-Sun monocular run: JSON with per-axis statistics per range
    and Sun bin, the Figure 5.7 plots, and errors that grow with range."""
    from swarmcore.vision_config import CovarianceConfig
    from swarmvision.characterize import run_cli
    from swarmvision.covariance import CharacterizedNoise

    files = run_cli("mono", tmp_path, ranges=[3.0, 6.0], orientations=2, suns=3, illuminations=("global",),
                    ambient_global=0.3, log=lambda s: None)
    res = json.loads(Path(files["json"]).read_text())
    st = res["illuminations"]["global"]
    assert st["by_range"]["range_m"] == [3.0, 6.0]
    assert all(c >= 5 for c in st["by_range"]["count"])  # ≥ 5 of 6 images give a pose
    mse = np.array(st["by_range"]["mse_trimmed"])
    assert np.all(np.isfinite(mse)) and mse.shape == (2, 6)
    assert mse[1, 5] > mse[0, 5]  # line-of-sight error grows with range
    assert len(res["samples"]) == 2 * 2 * 3
    for p in files["plots"]:
        assert Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    cn = CharacterizedNoise(res, CovarianceConfig(), "global", res["camera"])
    assert cn.cov_C(6.0)[5, 5] > cn.cov_C(3.0)[5, 5]


def test_missing_table_fails_early_with_a_hint():
    from swarmcore.vision_config import VisionConfig
    from swarmvision.pose_estimator import VisionPoseEstimator

    cfg = VisionConfig.model_validate({"pipeline": "mono", "mono_camera": {"width_px": 640, "height_px": 480}})
    with pytest.raises(ValueError, match="swarm characterize"):
        VisionPoseEstimator(cfg, 3, 0.2, 0, 1.08e-3)
    VisionPoseEstimator(VisionConfig.model_validate({"pipeline": "mono"}), 3, 0.2, 0, 1.08e-3)  # shipped table
    VisionPoseEstimator(VisionConfig.model_validate({"pipeline": "stereo"}), 3, 0.2, 0, 1.08e-3)
