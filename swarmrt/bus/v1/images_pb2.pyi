from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class CameraView(_message.Message):
    __slots__ = ("camera", "T_CB", "r_C_B_m", "width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "target", "baseline_m", "images_mono8")
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    T_CB_FIELD_NUMBER: _ClassVar[int]
    R_C_B_M_FIELD_NUMBER: _ClassVar[int]
    WIDTH_PX_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_PX_FIELD_NUMBER: _ClassVar[int]
    FX_PX_FIELD_NUMBER: _ClassVar[int]
    FY_PX_FIELD_NUMBER: _ClassVar[int]
    CX_PX_FIELD_NUMBER: _ClassVar[int]
    CY_PX_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    BASELINE_M_FIELD_NUMBER: _ClassVar[int]
    IMAGES_MONO8_FIELD_NUMBER: _ClassVar[int]
    camera: int
    T_CB: _containers.RepeatedScalarFieldContainer[float]
    r_C_B_m: _containers.RepeatedScalarFieldContainer[float]
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    target: int
    baseline_m: float
    images_mono8: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, camera: _Optional[int] = ..., T_CB: _Optional[_Iterable[float]] = ..., r_C_B_m: _Optional[_Iterable[float]] = ..., width_px: _Optional[int] = ..., height_px: _Optional[int] = ..., fx_px: _Optional[float] = ..., fy_px: _Optional[float] = ..., cx_px: _Optional[float] = ..., cy_px: _Optional[float] = ..., target: _Optional[int] = ..., baseline_m: _Optional[float] = ..., images_mono8: _Optional[_Iterable[bytes]] = ...) -> None: ...

class Images(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "targets", "views")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    TARGETS_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    targets: _containers.RepeatedScalarFieldContainer[int]
    views: _containers.RepeatedCompositeFieldContainer[CameraView]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., targets: _Optional[_Iterable[int]] = ..., views: _Optional[_Iterable[_Union[CameraView, _Mapping]]] = ...) -> None: ...
