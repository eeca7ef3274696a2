from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Clock(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "live_agents", "mode", "done", "malformed", "key_mismatch", "recorder_waited_steps", "recorder_waited_s")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    LIVE_AGENTS_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    MALFORMED_FIELD_NUMBER: _ClassVar[int]
    KEY_MISMATCH_FIELD_NUMBER: _ClassVar[int]
    RECORDER_WAITED_STEPS_FIELD_NUMBER: _ClassVar[int]
    RECORDER_WAITED_S_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    live_agents: _containers.RepeatedScalarFieldContainer[int]
    mode: str
    done: bool
    malformed: int
    key_mismatch: int
    recorder_waited_steps: int
    recorder_waited_s: float
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., live_agents: _Optional[_Iterable[int]] = ..., mode: _Optional[str] = ..., done: _Optional[bool] = ..., malformed: _Optional[int] = ..., key_mismatch: _Optional[int] = ..., recorder_waited_steps: _Optional[int] = ..., recorder_waited_s: _Optional[float] = ...) -> None: ...

class Recorded(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ...) -> None: ...
