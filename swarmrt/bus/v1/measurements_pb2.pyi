from swarmrt.bus.v1 import common_pb2 as _common_pb2
from swarmrt.bus.v1 import estimators_pb2 as _estimators_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MeasBatch(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "observer", "target", "camera", "q_BjBi", "r_ij_Bi_m", "R_Bi", "estimator")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    OBSERVER_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    Q_BJBI_FIELD_NUMBER: _ClassVar[int]
    R_IJ_BI_M_FIELD_NUMBER: _ClassVar[int]
    R_BI_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    observer: int
    target: _containers.RepeatedScalarFieldContainer[int]
    camera: _containers.RepeatedScalarFieldContainer[int]
    q_BjBi: _containers.RepeatedScalarFieldContainer[float]
    r_ij_Bi_m: _containers.RepeatedScalarFieldContainer[float]
    R_Bi: _common_pb2.Matrix
    estimator: _estimators_pb2.EstimatorMessage
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., observer: _Optional[int] = ..., target: _Optional[_Iterable[int]] = ..., camera: _Optional[_Iterable[int]] = ..., q_BjBi: _Optional[_Iterable[float]] = ..., r_ij_Bi_m: _Optional[_Iterable[float]] = ..., R_Bi: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., estimator: _Optional[_Union[_estimators_pb2.EstimatorMessage, _Mapping]] = ...) -> None: ...

class StepBatches(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "observers", "counts", "target", "camera", "q_BjBi", "r_ij_Bi_m", "R_Bi", "estimators")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    OBSERVERS_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    Q_BJBI_FIELD_NUMBER: _ClassVar[int]
    R_IJ_BI_M_FIELD_NUMBER: _ClassVar[int]
    R_BI_FIELD_NUMBER: _ClassVar[int]
    ESTIMATORS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    observers: _containers.RepeatedScalarFieldContainer[int]
    counts: _containers.RepeatedScalarFieldContainer[int]
    target: _containers.RepeatedScalarFieldContainer[int]
    camera: _containers.RepeatedScalarFieldContainer[int]
    q_BjBi: _containers.RepeatedScalarFieldContainer[float]
    r_ij_Bi_m: _containers.RepeatedScalarFieldContainer[float]
    R_Bi: _common_pb2.Matrix
    estimators: _containers.RepeatedCompositeFieldContainer[_estimators_pb2.EstimatorMessage]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., observers: _Optional[_Iterable[int]] = ..., counts: _Optional[_Iterable[int]] = ..., target: _Optional[_Iterable[int]] = ..., camera: _Optional[_Iterable[int]] = ..., q_BjBi: _Optional[_Iterable[float]] = ..., r_ij_Bi_m: _Optional[_Iterable[float]] = ..., R_Bi: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., estimators: _Optional[_Iterable[_Union[_estimators_pb2.EstimatorMessage, _Mapping]]] = ...) -> None: ...
