from swarmrt.bus.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Estimate(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "own", "phase", "q_BI", "omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "bias_B_rad_s", "P_pose", "P_diag", "gate_accepted", "gate_rejected", "nis", "nis_dof", "iterations", "step_ms", "batches_used", "batches_missing", "batches_late", "step_cpu_ms", "codec_cpu_ms", "late_used", "late_dropped", "replayed_steps", "ids", "P_rel_pose", "estimator", "bytes_sent")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    OWN_FIELD_NUMBER: _ClassVar[int]
    PHASE_FIELD_NUMBER: _ClassVar[int]
    Q_BI_FIELD_NUMBER: _ClassVar[int]
    OMEGA_BI_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    R_H_M_FIELD_NUMBER: _ClassVar[int]
    V_H_M_S_FIELD_NUMBER: _ClassVar[int]
    BIAS_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    P_POSE_FIELD_NUMBER: _ClassVar[int]
    P_DIAG_FIELD_NUMBER: _ClassVar[int]
    GATE_ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    GATE_REJECTED_FIELD_NUMBER: _ClassVar[int]
    NIS_FIELD_NUMBER: _ClassVar[int]
    NIS_DOF_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    STEP_MS_FIELD_NUMBER: _ClassVar[int]
    BATCHES_USED_FIELD_NUMBER: _ClassVar[int]
    BATCHES_MISSING_FIELD_NUMBER: _ClassVar[int]
    BATCHES_LATE_FIELD_NUMBER: _ClassVar[int]
    STEP_CPU_MS_FIELD_NUMBER: _ClassVar[int]
    CODEC_CPU_MS_FIELD_NUMBER: _ClassVar[int]
    LATE_USED_FIELD_NUMBER: _ClassVar[int]
    LATE_DROPPED_FIELD_NUMBER: _ClassVar[int]
    REPLAYED_STEPS_FIELD_NUMBER: _ClassVar[int]
    IDS_FIELD_NUMBER: _ClassVar[int]
    P_REL_POSE_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    BYTES_SENT_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    own: int
    phase: str
    q_BI: _containers.RepeatedScalarFieldContainer[float]
    omega_BI_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    r_H_m: _containers.RepeatedScalarFieldContainer[float]
    v_H_m_s: _containers.RepeatedScalarFieldContainer[float]
    bias_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    P_pose: _common_pb2.Matrix
    P_diag: _common_pb2.Matrix
    gate_accepted: int
    gate_rejected: int
    nis: float
    nis_dof: int
    iterations: int
    step_ms: float
    batches_used: _containers.RepeatedScalarFieldContainer[int]
    batches_missing: _containers.RepeatedScalarFieldContainer[int]
    batches_late: int
    step_cpu_ms: float
    codec_cpu_ms: float
    late_used: int
    late_dropped: int
    replayed_steps: int
    ids: _containers.RepeatedScalarFieldContainer[int]
    P_rel_pose: _common_pb2.Matrix
    estimator: str
    bytes_sent: int
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., own: _Optional[int] = ..., phase: _Optional[str] = ..., q_BI: _Optional[_Iterable[float]] = ..., omega_BI_B_rad_s: _Optional[_Iterable[float]] = ..., r_H_m: _Optional[_Iterable[float]] = ..., v_H_m_s: _Optional[_Iterable[float]] = ..., bias_B_rad_s: _Optional[_Iterable[float]] = ..., P_pose: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., P_diag: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., gate_accepted: _Optional[int] = ..., gate_rejected: _Optional[int] = ..., nis: _Optional[float] = ..., nis_dof: _Optional[int] = ..., iterations: _Optional[int] = ..., step_ms: _Optional[float] = ..., batches_used: _Optional[_Iterable[int]] = ..., batches_missing: _Optional[_Iterable[int]] = ..., batches_late: _Optional[int] = ..., step_cpu_ms: _Optional[float] = ..., codec_cpu_ms: _Optional[float] = ..., late_used: _Optional[int] = ..., late_dropped: _Optional[int] = ..., replayed_steps: _Optional[int] = ..., ids: _Optional[_Iterable[int]] = ..., P_rel_pose: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., estimator: _Optional[str] = ..., bytes_sent: _Optional[int] = ...) -> None: ...

class FullEstimate(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "own", "q_BI", "omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "bias_B_rad_s", "P", "ids")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    OWN_FIELD_NUMBER: _ClassVar[int]
    Q_BI_FIELD_NUMBER: _ClassVar[int]
    OMEGA_BI_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    R_H_M_FIELD_NUMBER: _ClassVar[int]
    V_H_M_S_FIELD_NUMBER: _ClassVar[int]
    BIAS_B_RAD_S_FIELD_NUMBER: _ClassVar[int]
    P_FIELD_NUMBER: _ClassVar[int]
    IDS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    own: int
    q_BI: _containers.RepeatedScalarFieldContainer[float]
    omega_BI_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    r_H_m: _containers.RepeatedScalarFieldContainer[float]
    v_H_m_s: _containers.RepeatedScalarFieldContainer[float]
    bias_B_rad_s: _containers.RepeatedScalarFieldContainer[float]
    P: _common_pb2.Matrix
    ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., own: _Optional[int] = ..., q_BI: _Optional[_Iterable[float]] = ..., omega_BI_B_rad_s: _Optional[_Iterable[float]] = ..., r_H_m: _Optional[_Iterable[float]] = ..., v_H_m_s: _Optional[_Iterable[float]] = ..., bias_B_rad_s: _Optional[_Iterable[float]] = ..., P: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., ids: _Optional[_Iterable[int]] = ...) -> None: ...
