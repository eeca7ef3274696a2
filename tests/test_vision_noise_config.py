"""Camera noise model and the VisionConfig schema."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from swarmcore.streams import stream


def test_noise_statistics_match_the_model():
    """Flat 100 DN field: mean 100 + black level, σ² = 100·255/full_well + read² (shot +
    read), to 2 %; blur alone leaves a flat field flat; every term switches off."""
    from swarmvision.config import NoiseConfig
    from swarmvision.noise import apply_noise

    img = np.full((400, 400), 100, np.uint8)
    cfg = NoiseConfig(blur_sigma_px=0.0)
    out = apply_noise(img, cfg, np.random.default_rng(0)).astype(float)
    assert out.mean() == pytest.approx(100 + cfg.dark_offset_dn, abs=0.05)
    expect = np.sqrt(100 * 255 / cfg.full_well_e + cfg.read_noise_dn**2)
    assert out.std() == pytest.approx(expect, rel=0.02)
    no_shot = apply_noise(img, NoiseConfig(blur_sigma_px=0.0, shot_noise=False), np.random.default_rng(0)).astype(float)
    assert no_shot.std() == pytest.approx(cfg.read_noise_dn, rel=0.03)
    off = NoiseConfig(enabled=False)
    assert apply_noise(img, off, np.random.default_rng(0)) is img
    quiet = NoiseConfig(shot_noise=False, read_noise_dn=0.0, dark_offset_dn=0.0, blur_sigma_px=1.0)
    assert np.array_equal(apply_noise(img, quiet, np.random.default_rng(0)), img)


def test_blur_spreads_an_edge():
    from swarmvision.config import NoiseConfig
    from swarmvision.noise import apply_noise

    img = np.zeros((64, 64), np.uint8)
    img[:, 32:] = 200
    cfg = NoiseConfig(shot_noise=False, read_noise_dn=0.0, dark_offset_dn=0.0, blur_sigma_px=1.5)
    out = apply_noise(img, cfg, np.random.default_rng(0))
    row = out[10].astype(int)
    assert 0 < row[31] < 100 < row[32] < 200  # the step is now a ramp


def test_noise_is_a_deterministic_function_of_the_stream():
    from swarmvision.config import NoiseConfig
    from swarmvision.noise import apply_noise

    img = np.random.default_rng(1).integers(0, 255, (120, 160), dtype=np.uint8)
    a = apply_noise(img, NoiseConfig(), stream(4, "camera", 10, 2, 3))
    b = apply_noise(img, NoiseConfig(), stream(4, "camera", 10, 2, 3))
    c = apply_noise(img, NoiseConfig(), stream(4, "camera", 10, 2, 4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_vision_config_validates():
    from swarmvision.config import VisionConfig

    cfg = VisionConfig()
    assert cfg.pipeline == "none" and cfg.mono_camera.width_px == 1024
    assert VisionConfig.model_validate(cfg.model_dump()) == cfg
    with pytest.raises(ValidationError):
        VisionConfig.model_validate({"pipeline": "mono", "camera_typo": 1})  # extra="forbid"
    with pytest.raises(ValidationError):
        VisionConfig.model_validate({"stereo": {"block_size": 14}})
    with pytest.raises(ValidationError):
        VisionConfig.model_validate({"lighting": {"sun_direction": [0, 0, 0]}})
    assert VisionConfig().stereo_camera.focal_px == pytest.approx(1024 * 45 / 32)  # Table 5.1


def test_view_bytes_roundtrip():
    from swarmcore.cameras import T_CB, Intrinsics
    from swarmvision.pipeline import View, decode_view, encode_view

    ims = (np.arange(12, dtype=np.uint8).reshape(3, 4), np.full((3, 4), 7, np.uint8))
    v = View(2, 8, 5, 5.0, ims, T_CB[1], np.array([0.0, 0, 0]), Intrinsics(4, 3, 2.0, 2.0, 1.5, 1.0), target=2, baseline_m=0.5)
    w = decode_view(encode_view(v))
    assert (w.observer, w.camera, w.step, w.target, w.baseline_m) == (2, 8, 5, 2, 0.5)
    assert len(w.images) == len(v.images) == 2
    assert all(np.array_equal(a, b) for a, b in zip(v.images, w.images, strict=True))
    np.testing.assert_array_equal(w.T_CB, T_CB[1])
    assert w.intrinsics == v.intrinsics
