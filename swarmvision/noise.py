"""Camera noise model: what turns a clean render into a plausible sensor image.

Applied to an 8-bit linear render (DN 0..255), in order:

1. blur — Gaussian point-spread function of σ ``blur_sigma_px`` (optics, residual
   jitter), by ``cv2.GaussianBlur``;
2. shot noise — photon statistics of the signal in electrons, ``DN / 255 · full_well_e``;
3. black level ``dark_offset_dn`` and Gaussian read noise ``read_noise_dn``;
4. rounding and clipping to uint8 (quantisation, saturation).

Shot and read noise are drawn together as one Gaussian per pixel with variance
``DN / g + read²`` (g = electrons per DN): the Gaussian limit of the Poisson count, exact
to well under a DN here because one DN is already ``full_well_e / 255`` ≈ 39 electrons at
the default; it halves the cost of a 2000² frame against a Poisson draw plus a normal one.

The per-pixel normals come from ``cv2.randn`` (about 4× faster than NumPy's generator on
a 2000² frame), seeded from the caller's generator, so the image is still a deterministic
function of that generator.

Every random draw comes from the generator the caller passes (in the simulator:
``swarmcore.streams.stream(seed, "camera", step, observer, camera)``), so images are
reproducible. Each term can be switched off in :class:`swarmvision.config.NoiseConfig`.
"""

from __future__ import annotations

import numpy as np

from swarmcore.vision_config import NoiseConfig

__all__ = ["apply_noise"]


def apply_noise(img: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Noisy uint8 copy of the uint8 image ``img`` (any shape; 2-D for the blur)."""
    if not cfg.enabled:
        return img
    import cv2

    x: np.ndarray = img.astype(np.float32)
    if cfg.blur_sigma_px > 0:
        x = cv2.GaussianBlur(x, (0, 0), cfg.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    var = None
    if cfg.shot_noise:
        var = np.clip(x, 0, None) * np.float32(255.0 / cfg.full_well_e)
    if cfg.read_noise_dn > 0:
        var = (var if var is not None else np.zeros_like(x)) + np.float32(cfg.read_noise_dn**2)
    x = x + np.float32(cfg.dark_offset_dn)
    if var is not None:
        z = np.empty(x.shape, np.float32)
        cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
        # OpenCV's stubs type mean and stddev as arrays only; cv2.randn takes scalars (a cv::Scalar).
        cv2.randn(z, 0.0, 1.0)  # type: ignore[call-overload]
        x = x + np.sqrt(var) * z
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)
