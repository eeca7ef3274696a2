from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Claim(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "token", "running", "password")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    RUNNING_FIELD_NUMBER: _ClassVar[int]
    PASSWORD_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    token: str
    running: bool
    password: str
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., token: _Optional[str] = ..., running: _Optional[bool] = ..., password: _Optional[str] = ...) -> None: ...
