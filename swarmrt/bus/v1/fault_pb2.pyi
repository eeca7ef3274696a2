from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class FaultAction(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FAULT_ACTION_UNSPECIFIED: _ClassVar[FaultAction]
    FAULT_ACTION_KILL_AGENT: _ClassVar[FaultAction]
    FAULT_ACTION_RESTART_AGENT: _ClassVar[FaultAction]
    FAULT_ACTION_STOP_AGENT: _ClassVar[FaultAction]
    FAULT_ACTION_CAMERA: _ClassVar[FaultAction]
    FAULT_ACTION_DROP: _ClassVar[FaultAction]
    FAULT_ACTION_PARTITION: _ClassVar[FaultAction]
    FAULT_ACTION_HEAL: _ClassVar[FaultAction]
    FAULT_ACTION_NETEM: _ClassVar[FaultAction]
    FAULT_ACTION_STALL_AGENT: _ClassVar[FaultAction]
    FAULT_ACTION_LINK: _ClassVar[FaultAction]
    FAULT_ACTION_KILL_SELECTOR: _ClassVar[FaultAction]
    FAULT_ACTION_RESTART_SELECTOR: _ClassVar[FaultAction]
    FAULT_ACTION_KILL_ROUTER: _ClassVar[FaultAction]
    FAULT_ACTION_RESTART_ROUTER: _ClassVar[FaultAction]
    FAULT_ACTION_STALL_WORLD: _ClassVar[FaultAction]
    FAULT_ACTION_STALL_SELECTOR: _ClassVar[FaultAction]
    FAULT_ACTION_STALL_RECORDER: _ClassVar[FaultAction]
    FAULT_ACTION_STALL_ROUTER: _ClassVar[FaultAction]
    FAULT_ACTION_KILL_NODE: _ClassVar[FaultAction]
    FAULT_ACTION_PARTITION_NODES: _ClassVar[FaultAction]

class FaultPhase(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FAULT_PHASE_UNSPECIFIED: _ClassVar[FaultPhase]
    FAULT_PHASE_COMMAND: _ClassVar[FaultPhase]
    FAULT_PHASE_DONE: _ClassVar[FaultPhase]
    FAULT_PHASE_FAILED: _ClassVar[FaultPhase]
FAULT_ACTION_UNSPECIFIED: FaultAction
FAULT_ACTION_KILL_AGENT: FaultAction
FAULT_ACTION_RESTART_AGENT: FaultAction
FAULT_ACTION_STOP_AGENT: FaultAction
FAULT_ACTION_CAMERA: FaultAction
FAULT_ACTION_DROP: FaultAction
FAULT_ACTION_PARTITION: FaultAction
FAULT_ACTION_HEAL: FaultAction
FAULT_ACTION_NETEM: FaultAction
FAULT_ACTION_STALL_AGENT: FaultAction
FAULT_ACTION_LINK: FaultAction
FAULT_ACTION_KILL_SELECTOR: FaultAction
FAULT_ACTION_RESTART_SELECTOR: FaultAction
FAULT_ACTION_KILL_ROUTER: FaultAction
FAULT_ACTION_RESTART_ROUTER: FaultAction
FAULT_ACTION_STALL_WORLD: FaultAction
FAULT_ACTION_STALL_SELECTOR: FaultAction
FAULT_ACTION_STALL_RECORDER: FaultAction
FAULT_ACTION_STALL_ROUTER: FaultAction
FAULT_ACTION_KILL_NODE: FaultAction
FAULT_ACTION_PARTITION_NODES: FaultAction
FAULT_PHASE_UNSPECIFIED: FaultPhase
FAULT_PHASE_COMMAND: FaultPhase
FAULT_PHASE_DONE: FaultPhase
FAULT_PHASE_FAILED: FaultPhase

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
