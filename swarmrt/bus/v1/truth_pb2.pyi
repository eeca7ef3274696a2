from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Truth(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "q_BI", "omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "gyro_bias_B_rad_s")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    Q_BI_FIELD_NUMBER: _ClassVar[int]
    OMEGA_BI_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    R_H_M_FIELD_NUMBER: _ClassVar[int]
    V_H_M_S_FIELD_NUMBER: _ClassVar[int]
    GYRO_BIAS_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    q_BI: _containers.RepeatedScalarFieldContainer[float]
    omega_BI_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    r_H_m: _containers.RepeatedScalarFieldContainer[float]
    v_H_m_s: _containers.RepeatedScalarFieldContainer[float]
    gyro_bias_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., q_BI: _Optional[_Iterable[float]] = ..., omega_BI_B_rad_s: _Optional[_Iterable[float]] = ..., r_H_m: _Optional[_Iterable[float]] = ..., v_H_m_s: _Optional[_Iterable[float]] = ..., gyro_bias_B_rad_s: _Optional[_Iterable[float]] = ...) -> None: ...
