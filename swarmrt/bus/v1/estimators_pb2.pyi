from swarmrt.bus.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class CiState(_message.Message):
    __slots__ = ("q_BI", "omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "P_pose")
    Q_BI_FIELD_NUMBER: _ClassVar[int]
    OMEGA_BI_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    R_H_M_FIELD_NUMBER: _ClassVar[int]
    V_H_M_S_FIELD_NUMBER: _ClassVar[int]
    P_POSE_FIELD_NUMBER: _ClassVar[int]
    q_BI: _containers.RepeatedScalarFieldContainer[float]
    omega_BI_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    r_H_m: _containers.RepeatedScalarFieldContainer[float]
    v_H_m_s: _containers.RepeatedScalarFieldContainer[float]
    P_pose: _common_pb2.Matrix
    def __init__(self, q_BI: _Optional[_Iterable[float]] = ..., omega_BI_B_rad_s: _Optional[_Iterable[float]] = ..., r_H_m: _Optional[_Iterable[float]] = ..., v_H_m_s: _Optional[_Iterable[float]] = ..., P_pose: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ...) -> None: ...

class PairwiseState(_message.Message):
    __slots__ = ("q_BI", "omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "bias_B_rad_s", "P", "partners", "sigma")
    Q_BI_FIELD_NUMBER: _ClassVar[int]
    OMEGA_BI_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    R_H_M_FIELD_NUMBER: _ClassVar[int]
    V_H_M_S_FIELD_NUMBER: _ClassVar[int]
    BIAS_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    P_FIELD_NUMBER: _ClassVar[int]
    PARTNERS_FIELD_NUMBER: _ClassVar[int]
    SIGMA_FIELD_NUMBER: _ClassVar[int]
    q_BI: _containers.RepeatedScalarFieldContainer[float]
    omega_BI_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    r_H_m: _containers.RepeatedScalarFieldContainer[float]
    v_H_m_s: _containers.RepeatedScalarFieldContainer[float]
    bias_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    P: _common_pb2.Matrix
    partners: _containers.RepeatedScalarFieldContainer[int]
    sigma: _common_pb2.Matrix
    def __init__(self, q_BI: _Optional[_Iterable[float]] = ..., omega_BI_B_rad_s: _Optional[_Iterable[float]] = ..., r_H_m: _Optional[_Iterable[float]] = ..., v_H_m_s: _Optional[_Iterable[float]] = ..., bias_B_rad_s: _Optional[_Iterable[float]] = ..., P: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., partners: _Optional[_Iterable[int]] = ..., sigma: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ...) -> None: ...

class EstimatorMessage(_message.Message):
    __slots__ = ("kind", "version", "ci", "pairwise", "opaque")
    KIND_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CI_FIELD_NUMBER: _ClassVar[int]
    PAIRWISE_FIELD_NUMBER: _ClassVar[int]
    OPAQUE_FIELD_NUMBER: _ClassVar[int]
    kind: str
    version: int
    ci: CiState
    pairwise: PairwiseState
    opaque: bytes
    def __init__(self, kind: _Optional[str] = ..., version: _Optional[int] = ..., ci: _Optional[_Union[CiState, _Mapping]] = ..., pairwise: _Optional[_Union[PairwiseState, _Mapping]] = ..., opaque: _Optional[bytes] = ...) -> None: ...
