from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Health(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "camera_ok", "malformed", "batches_missing", "batches_late", "drop_rate", "host", "key_mismatch")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    CAMERA_OK_FIELD_NUMBER: _ClassVar[int]
    MALFORMED_FIELD_NUMBER: _ClassVar[int]
    BATCHES_MISSING_FIELD_NUMBER: _ClassVar[int]
    BATCHES_LATE_FIELD_NUMBER: _ClassVar[int]
    DROP_RATE_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    KEY_MISMATCH_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    camera_ok: _containers.RepeatedScalarFieldContainer[bool]
    malformed: int
    batches_missing: int
    batches_late: int
    drop_rate: float
    host: str
    key_mismatch: int
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., camera_ok: _Optional[_Iterable[bool]] = ..., malformed: _Optional[int] = ..., batches_missing: _Optional[int] = ..., batches_late: _Optional[int] = ..., drop_rate: _Optional[float] = ..., host: _Optional[str] = ..., key_mismatch: _Optional[int] = ...) -> None: ...
