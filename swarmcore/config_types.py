"""The value types every configuration model of the core is built from (pydantic v2):
the base model (unknown fields refused, assignments validated) and the constrained
numbers and vectors, each with the error message that names what is wrong."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

__all__ = ["ConfigModel", "PosFloat", "NonNegFloat", "CameraAxes", "Direction3",
           "TAG_FAMILY", "TAG_FAMILY_CODES", "MAX_TAGGED_SATELLITES"]

PosFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


def _three_axes(v: list[float]) -> list[float]:
    if len(v) != 3:
        raise ValueError(f"needs 3 values (camera x, y, z), got {len(v)}")
    return v


def _direction(v: list[float]) -> list[float]:
    if len(v) != 3 or float(np.linalg.norm(v)) == 0.0:
        raise ValueError("needs 3 components, not all zero")
    return v


#: One positive value per camera axis (x, y, z).
CameraAxes = Annotated[list[PosFloat], AfterValidator(_three_axes)]
#: A direction: three components, not all zero (normalised on use).
Direction3 = Annotated[list[float], AfterValidator(_direction)]

#: The fiducial family of the monocular pipeline: AprilTag 36h11 has 587 codes and every
#: satellite carries six (one per face), so at most 97 satellites have unique tags.
TAG_FAMILY = "36h11"
TAG_FAMILY_CODES = 587
MAX_TAGGED_SATELLITES = TAG_FAMILY_CODES // 6


class ConfigModel(BaseModel):
    """A configuration section: unknown fields are errors, assignments are validated, every
    number is finite (an infinite duration or a NaN inertia is a typo, never a scenario)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
