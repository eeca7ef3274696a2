"""Typed configuration of the rendered cameras and the vision pipelines (chapter 5).

Pure pydantic v2 model, meant to sit in a scenario as ``vision: VisionConfig``. Every
field has a unit in its name or description; defaults keep CI fast (1024² face cameras,
the dissertation's 2000² is one ``--set`` away).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from .config_types import MAX_TAGGED_SATELLITES, TAG_FAMILY, TAG_FAMILY_CODES, CameraAxes, Direction3, NonNegFloat, PosFloat
from .config_types import ConfigModel as _Model

__all__ = [
    "VisionConfig",
    "MonoCameraConfig",
    "StereoCameraConfig",
    "LightingConfig",
    "NoiseConfig",
    "MonoConfig",
    "StereoConfig",
    "CovarianceConfig",
    "RenderConfig",
    "mono_tag_problem",
]


class MonoCameraConfig(_Model):
    """The six body-fixed face cameras (one per cube face, +z, +x, +y, −x, −y, −z)."""

    width_px: int = Field(1024, ge=32, le=8192)
    height_px: int = Field(1024, ge=32, le=8192)
    fov_deg: float = Field(
        90.0, gt=10, lt=170, description="horizontal field of view; 90° gives full-sphere coverage with six faces"
    )
    focal_px: float | None = Field(
        None, gt=0, description="override the focal length in pixels (default: from fov_deg); Table 5.1 "
        "is 14 mm on a 32 mm plane over 2000 px = 875 px"
    )


class StereoCameraConfig(_Model):
    """The tracking stereo camera of Table 5.1 (45 mm, 32 mm focal plane, 1024 px, 0.5 m baseline)."""

    width_px: int = Field(1024, ge=32, le=8192)
    height_px: int = Field(1024, ge=32, le=8192)
    focal_length_mm: PosFloat = 45.0
    focal_plane_mm: PosFloat = 32.0
    baseline_m: PosFloat = Field(0.5, description="Table 5.1 prints '0.5 mm'; 0.5 m is meant")

    @property
    def focal_px(self) -> float:
        return self.width_px * self.focal_length_mm / self.focal_plane_mm


class LightingConfig(_Model):
    sun_direction: Direction3 = Field(
        [1.0, 0.3, 0.2], description="unit vector pointing at the Sun (normalised on use)"
    )
    sun_frame: Literal["I", "H"] = Field(
        "I", description="frame of sun_direction: I (fixed in inertial space, the physical case over "
        "minutes) or H (fixed in the rotating Hill frame)"
    )
    sun_intensity: PosFloat = Field(4.0, description="pyrender directional light intensity")
    ambient: NonNegFloat = Field(
        0.0, description="ambient light level (0..1) standing in for global illumination (Earth albedo, "
        "scattered light); 0 = solar only"
    )
    shadows: bool = Field(True, description="directional shadow mapping (satellites shadow each other)")


class NoiseConfig(_Model):
    """Camera noise model applied to every rendered image (see :mod:`swarmvision.noise`)."""

    enabled: bool = True
    blur_sigma_px: NonNegFloat = Field(0.7, description="Gaussian point-spread σ (optics + motion), px")
    shot_noise: bool = Field(True, description="Poisson photon noise")
    full_well_e: PosFloat = Field(10000.0, description="electrons at full scale (255 DN)")
    read_noise_dn: NonNegFloat = Field(2.0, description="Gaussian read noise σ in DN (8-bit)")
    dark_offset_dn: NonNegFloat = Field(2.0, description="black level added before quantisation, DN")


class MonoConfig(_Model):
    """Monocular fiducial pipeline."""

    tag_size_m: PosFloat = Field(
        0.32, description="side of the tag's black square (8 cells of the 36h11 layout incl. the black "
        "border); the rest of the 40 cm face is the white quiet zone"
    )
    corner_refine: Literal["apriltag", "subpix", "contour", "none"] = Field(
        "apriltag", description="ArUco corner refinement; 'apriltag' is the most accurate (≈0.13 px RMS on "
        "warped synthetic tags vs ≈0.4 px for subpix), after removing its half-pixel offset"
    )
    ambiguity_ratio: float = Field(
        1.3, gt=1.0, description="a single-tag IPPE solution is trusted by reprojection error alone only when "
        "the other one's error is this many times larger; otherwise the prediction decides"
    )
    ambiguity_px: NonNegFloat = Field(
        0.3, description="…or when the two branches' RMS reprojection errors differ by less than this (px)"
    )
    min_white_black_diff_dn: int = Field(20, ge=1, le=255, description="AprilTag quad contrast threshold (DN)")
    min_tag_px: PosFloat = Field(12.0, description="ignore tags whose side is shorter than this (px)")
    combine: Literal["joint", "best_tag"] = Field(
        "joint", description="joint: one PnP over every corner of every visible tag of the target; "
        "best_tag: the single largest tag"
    )
    pixel_sigma_px: PosFloat = Field(
        0.5, description="corner noise σ floor used for the PnP covariance (px)"
    )


class StereoConfig(_Model):
    """Stereo pipeline: disparity → 3-D → crop → down-sample → point-to-plane ICP."""

    matcher: Literal["bm", "sgbm"] = Field("bm", description="OpenCV StereoBM (dissertation) or StereoSGBM")
    block_size: int = Field(15, ge=5, le=51, description="matching block (odd); the dissertation's 15")
    max_disparity: int = Field(
        512, ge=16, description="largest disparity searched (multiple of 16); the dissertation's 512"
    )
    adaptive_disparity: bool = Field(
        True, description="search only the disparities the predicted range allows (faster, fewer false matches)"
    )
    roi: bool = Field(True, description="match only the window around the predicted target (faster)")
    uniqueness_ratio: int = Field(10, ge=0, le=100, description="matcher uniqueness ratio (%)")
    min_intensity_dn: int = Field(12, ge=0, le=255, description="drop pixels darker than this (sky, deep shadow)")
    crop_margin_m: PosFloat = Field(1.0, description="keep points within the model radius + this of the prediction")
    downsample_fraction: float = Field(0.1, gt=0, le=1, description="random down-sampling (dissertation: 10 %)")
    max_points: int = Field(1500, ge=50, description="cap on the measured points after down-sampling")
    min_points: int = Field(80, ge=10, description="fewer points: no measurement")
    model_points: int = Field(7500, ge=500, description="Poisson-disk points of the reference cloud")
    icp_distances_m: list[PosFloat] = Field(
        [1.0, 0.3, 0.1], description="point-to-plane ICP correspondence distances, wide to tight"
    )
    icp_iterations: int = Field(30, ge=1, le=500, description="iterations per stage")
    min_fitness: float = Field(0.3, ge=0, le=1, description="ICP inlier fraction below this: no measurement")


class CovarianceConfig(_Model):
    """How each measurement's R is built.

    * ``fixed``: per camera-axis σ at ``reference_range_m``, scaled by
      ``(range/reference_range_m) ** range_exponent`` (the chapter-6 model), rotated into B_i.
    * ``pnp``: (mono only) first-order covariance of the PnP solution,
      ``σ_px² (JᵀJ)⁻¹`` with σ_px the larger of the corner residual RMS and ``mono.pixel_sigma_px``,
      times ``inflation``; falls back to ``fixed`` for stereo.
    * ``characterized``: variances per camera axis versus range and Sun angle from a
      ``swarm characterize`` JSON (``table``; the package ships defaults).
    * ``fitted``: variances per camera axis log-linear in what the agent knows when it
      measures (range, Sun angle, the target's apparent attitude, the pipeline's quality
      numbers), times the errors' autocorrelation time, fitted from a characterisation
      (``model``; ``swarm fit-noise`` refits, the package ships defaults).
    """

    source: Literal["fixed", "pnp", "characterized", "fitted"] = "characterized"
    table: str | None = Field(None, description="characterization JSON (default: the one shipped for the pipeline)")
    model: str | None = Field(
        None, description="fitted: error-model JSON (`swarm fit-noise`); a bare file name is looked up in "
        "swarmvision/data; default: the one shipped for the pipeline and camera"
    )
    sigma_pos_camera_m: CameraAxes = Field([0.02, 0.02, 0.06], description="fixed: σ along camera x, y, z")
    sigma_att_camera_rad: CameraAxes = Field([0.02, 0.02, 0.01], description="fixed: σ about camera x, y, z")
    reference_range_m: PosFloat = 5.0
    range_exponent: NonNegFloat = 2.0
    min_sigma_pos_m: PosFloat = Field(0.003, description="floor on every position σ")
    min_sigma_att_rad: PosFloat = Field(0.002, description="floor on every attitude σ")
    inflation: PosFloat = Field(1.0, description="multiply every variance by this")


class RenderConfig(_Model):
    platform: Literal["auto", "egl", "osmesa"] = Field(
        "auto", description="PyOpenGL platform; auto tries EGL then OSMesa. Must be decided before "
        "OpenGL is first imported in the process (PYOPENGL_PLATFORM wins if set)"
    )
    znear_m: PosFloat = 0.05
    zfar_m: PosFloat = 200.0
    texture_px_per_cell: int = Field(24, ge=4, le=128, description="tag texture resolution")


class VisionConfig(_Model):
    """Rendered cameras and the vision pipelines (``pipeline: none`` keeps the synthetic noise model)."""

    pipeline: Literal["none", "mono", "stereo"] = "none"
    mono_camera: MonoCameraConfig = MonoCameraConfig()
    stereo_camera: StereoCameraConfig = StereoCameraConfig()
    lighting: LightingConfig = LightingConfig()
    noise: NoiseConfig = NoiseConfig()
    mono: MonoConfig = MonoConfig()
    stereo: StereoConfig = StereoConfig()
    covariance: CovarianceConfig = CovarianceConfig()
    render: RenderConfig = RenderConfig()
    aim: Literal["truth", "predicted"] = Field(
        "truth", description="stereo: the tracking camera's boresight follows the true line of sight "
        "(dissertation's virtual frame) or the one the observer predicts"
    )

    def distributed_refusal(self) -> str | None:
        """Why this configuration cannot run distributed (`swarm run`, compose), or None."""
        if self.pipeline == "stereo" and self.aim == "predicted":
            return ("vision.aim: 'predicted' (tracking cameras pointed by each agent's prediction) runs "
                    "in-process only (`swarm sim`); distributed runs aim at the true line of sight: set vision.aim: truth")
        return None

    @model_validator(mode="after")
    def _checks(self):
        if self.stereo.block_size % 2 == 0:
            raise ValueError("stereo.block_size: must be odd")
        if self.stereo.max_disparity % 16:
            raise ValueError("stereo.max_disparity: must be a multiple of 16")
        return self


def mono_tag_problem(cfg: VisionConfig, n_sats: int, half_size_m: float) -> str | None:
    """Why the monocular pipeline cannot tag this swarm (naming the field), or None: every
    face needs a unique tag of the family, smaller than the face (a white quiet zone
    around the black square)."""
    if n_sats > MAX_TAGGED_SATELLITES:
        return (f"vision.pipeline: mono needs a unique AprilTag per face; {TAG_FAMILY} has {TAG_FAMILY_CODES} tags, "
                f"enough for {MAX_TAGGED_SATELLITES} satellites, not {n_sats}")
    if cfg.mono.tag_size_m >= 2 * half_size_m:
        return (f"vision.mono.tag_size_m: {cfg.mono.tag_size_m:g} m leaves no quiet zone on the {2 * half_size_m:g} m "
                "cube face (it must be smaller than 2 · spacecraft.half_size_m)")
    return None
