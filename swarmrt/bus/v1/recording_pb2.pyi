from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Liveliness(_message.Message):
    __slots__ = ("key", "role", "id", "alive")
    KEY_FIELD_NUMBER: _ClassVar[int]
    ROLE_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    ALIVE_FIELD_NUMBER: _ClassVar[int]
    key: str
    role: str
    id: str
    alive: bool
    def __init__(self, key: _Optional[str] = ..., role: _Optional[str] = ..., id: _Optional[str] = ..., alive: _Optional[bool] = ...) -> None: ...

class Malformed(_message.Message):
    __slots__ = ("key", "error", "payload")
    KEY_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    key: str
    error: str
    payload: bytes
    def __init__(self, key: _Optional[str] = ..., error: _Optional[str] = ..., payload: _Optional[bytes] = ...) -> None: ...

class BusGap(_message.Message):
    __slots__ = ("observer", "down_unix_ns", "up_unix_ns", "last_step_before", "first_step_after")
    OBSERVER_FIELD_NUMBER: _ClassVar[int]
    DOWN_UNIX_NS_FIELD_NUMBER: _ClassVar[int]
    UP_UNIX_NS_FIELD_NUMBER: _ClassVar[int]
    LAST_STEP_BEFORE_FIELD_NUMBER: _ClassVar[int]
    FIRST_STEP_AFTER_FIELD_NUMBER: _ClassVar[int]
    observer: str
    down_unix_ns: int
    up_unix_ns: int
    last_step_before: int
    first_step_after: int
    def __init__(self, observer: _Optional[str] = ..., down_unix_ns: _Optional[int] = ..., up_unix_ns: _Optional[int] = ..., last_step_before: _Optional[int] = ..., first_step_after: _Optional[int] = ...) -> None: ...
