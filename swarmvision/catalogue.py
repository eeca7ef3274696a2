"""Names of the vision data: camera signatures and the file names of characterisation
tables and fitted error models, and where the shipped ones live.

Both sides need them (the world-side characterisation writes these files, the flight-side
pose estimator reads them) and neither side's modules may import the other's, so they
live here, importing only the camera geometry (:mod:`swarmvision.views`,
:mod:`swarmvision.stereo` intrinsics).
"""

from __future__ import annotations

from pathlib import Path

from swarmcore.vision_config import VisionConfig

__all__ = ["DATA", "camera_signature", "table_name", "model_name", "default_table_path"]

#: The shipped characterisation tables and fitted error models.
DATA = Path(__file__).parent / "data"


def camera_signature(cfg: VisionConfig, pipeline: str) -> dict:
    """What a table or model was made for: image size and focal length (and the stereo baseline)."""
    from .views import face_intrinsics, pair_intrinsics

    if pipeline == "mono":
        k = face_intrinsics(cfg)
        return {"width_px": k.width, "height_px": k.height, "focal_px": round(float(k.fx), 3)}
    k = pair_intrinsics(cfg)
    return {"width_px": k.width, "height_px": k.height, "focal_px": round(float(k.fx), 3), "baseline_m": cfg.stereo_camera.baseline_m}


def table_name(pipeline: str, cam: dict) -> str:
    """File name of a characterization table: pipeline and camera (size, focal length)."""
    return f"characterization-{pipeline}-{cam['width_px']}x{cam['height_px']}-f{cam['focal_px']:g}.json"


def model_name(pipeline: str, cam: dict) -> str:
    """File name of a fitted error model: pipeline and camera (size, focal length)."""
    return f"error-model-{pipeline}-{cam['width_px']}x{cam['height_px']}-f{cam['focal_px']:g}.json"


def default_table_path(pipeline: str, camera: dict) -> Path:
    """The shipped table for this pipeline and camera (see ``swarmvision/data``)."""
    return DATA / table_name(pipeline, camera)
