from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Fault(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "action", "phase", "target", "camera", "state", "rate", "detail", "netem", "down_s", "peer", "delay_s")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    PHASE_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    RATE_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    NETEM_FIELD_NUMBER: _ClassVar[int]
    DOWN_S_FIELD_NUMBER: _ClassVar[int]
    PEER_FIELD_NUMBER: _ClassVar[int]
    DELAY_S_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    action: str
    phase: str
    target: int
    camera: int
    state: str
    rate: float
    detail: str
    netem: str
    down_s: float
    peer: int
    delay_s: float
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., action: _Optional[str] = ..., phase: _Optional[str] = ..., target: _Optional[int] = ..., camera: _Optional[int] = ..., state: _Optional[str] = ..., rate: _Optional[float] = ..., detail: _Optional[str] = ..., netem: _Optional[str] = ..., down_s: _Optional[float] = ..., peer: _Optional[int] = ..., delay_s: _Optional[float] = ...) -> None: ...
