from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Sensors(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "gyro_rate_B_rad_s", "q_BI_star", "r_H_gps_m", "sigma_star_rad", "sigma_gps_m")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    GYRO_RATE_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    Q_BI_STAR_FIELD_NUMBER: _ClassVar[int]
    R_H_GPS_M_FIELD_NUMBER: _ClassVar[int]
    SIGMA_STAR_RAD_FIELD_NUMBER: _ClassVar[int]
    SIGMA_GPS_M_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    gyro_rate_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    q_BI_star: _containers.RepeatedScalarFieldContainer[float]
    r_H_gps_m: _containers.RepeatedScalarFieldContainer[float]
    sigma_star_rad: float
    sigma_gps_m: float
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., gyro_rate_B_rad_s: _Optional[_Iterable[float]] = ..., q_BI_star: _Optional[_Iterable[float]] = ..., r_H_gps_m: _Optional[_Iterable[float]] = ..., sigma_star_rad: _Optional[float] = ..., sigma_gps_m: _Optional[float] = ...) -> None: ...

class Detection(_message.Message):
    __slots__ = ("target", "camera", "q_BjBi", "r_ij_Bi_m")
    TARGET_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    Q_BJBI_FIELD_NUMBER: _ClassVar[int]
    R_IJ_BI_M_FIELD_NUMBER: _ClassVar[int]
    target: int
    camera: int
    q_BjBi: _containers.RepeatedScalarFieldContainer[float]
    r_ij_Bi_m: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, target: _Optional[int] = ..., camera: _Optional[int] = ..., q_BjBi: _Optional[_Iterable[float]] = ..., r_ij_Bi_m: _Optional[_Iterable[float]] = ...) -> None: ...

class CameraOutput(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "detections", "cameras_off")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    DETECTIONS_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_OFF_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    detections: _containers.RepeatedCompositeFieldContainer[Detection]
    cameras_off: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., detections: _Optional[_Iterable[_Union[Detection, _Mapping]]] = ..., cameras_off: _Optional[_Iterable[int]] = ...) -> None: ...
