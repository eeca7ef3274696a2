from swarmrt.bus.v1 import common_pb2 as _common_pb2
from swarmrt.bus.v1 import measurements_pb2 as _measurements_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Delivered(_message.Message):
    __slots__ = ("arrival_t_s", "batch")
    ARRIVAL_T_S_FIELD_NUMBER: _ClassVar[int]
    BATCH_FIELD_NUMBER: _ClassVar[int]
    arrival_t_s: float
    batch: _measurements_pb2.MeasBatch
    def __init__(self, arrival_t_s: _Optional[float] = ..., batch: _Optional[_Union[_measurements_pb2.MeasBatch, _Mapping]] = ...) -> None: ...

class Delivery(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "items")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    ITEMS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    items: _containers.RepeatedCompositeFieldContainer[Delivered]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., items: _Optional[_Iterable[_Union[Delivered, _Mapping]]] = ...) -> None: ...

class Latency(_message.Message):
    __slots__ = ("sender", "receiver", "sent_k", "latency_s")
    SENDER_FIELD_NUMBER: _ClassVar[int]
    RECEIVER_FIELD_NUMBER: _ClassVar[int]
    SENT_K_FIELD_NUMBER: _ClassVar[int]
    LATENCY_S_FIELD_NUMBER: _ClassVar[int]
    sender: int
    receiver: int
    sent_k: int
    latency_s: float
    def __init__(self, sender: _Optional[int] = ..., receiver: _Optional[int] = ..., sent_k: _Optional[int] = ..., latency_s: _Optional[float] = ...) -> None: ...

class LinkStats(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered", "queue_bytes", "latencies")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SENT_FIELD_NUMBER: _ClassVar[int]
    DELIVERED_FIELD_NUMBER: _ClassVar[int]
    DELIVERED_LATE_FIELD_NUMBER: _ClassVar[int]
    LOST_FIELD_NUMBER: _ClassVar[int]
    DROPPED_QUEUE_FIELD_NUMBER: _ClassVar[int]
    UNREACHABLE_FIELD_NUMBER: _ClassVar[int]
    BYTES_DELIVERED_FIELD_NUMBER: _ClassVar[int]
    QUEUE_BYTES_FIELD_NUMBER: _ClassVar[int]
    LATENCIES_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sent: _common_pb2.Matrix
    delivered: _common_pb2.Matrix
    delivered_late: _common_pb2.Matrix
    lost: _common_pb2.Matrix
    dropped_queue: _common_pb2.Matrix
    unreachable: _common_pb2.Matrix
    bytes_delivered: _common_pb2.Matrix
    queue_bytes: _containers.RepeatedScalarFieldContainer[int]
    latencies: _containers.RepeatedCompositeFieldContainer[Latency]
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sent: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., delivered: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., delivered_late: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., lost: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., dropped_queue: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., unreachable: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., bytes_delivered: _Optional[_Union[_common_pb2.Matrix, _Mapping]] = ..., queue_bytes: _Optional[_Iterable[int]] = ..., latencies: _Optional[_Iterable[_Union[Latency, _Mapping]]] = ...) -> None: ...

class RejoinFate(_message.Message):
    __slots__ = ("schema_version", "run", "sender", "k", "t_s", "sat", "peer", "bytes", "fate", "arrival_t_s")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_FIELD_NUMBER: _ClassVar[int]
    SENDER_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    T_S_FIELD_NUMBER: _ClassVar[int]
    SAT_FIELD_NUMBER: _ClassVar[int]
    PEER_FIELD_NUMBER: _ClassVar[int]
    BYTES_FIELD_NUMBER: _ClassVar[int]
    FATE_FIELD_NUMBER: _ClassVar[int]
    ARRIVAL_T_S_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    run: str
    sender: str
    k: int
    t_s: float
    sat: int
    peer: int
    bytes: int
    fate: str
    arrival_t_s: float
    def __init__(self, schema_version: _Optional[int] = ..., run: _Optional[str] = ..., sender: _Optional[str] = ..., k: _Optional[int] = ..., t_s: _Optional[float] = ..., sat: _Optional[int] = ..., peer: _Optional[int] = ..., bytes: _Optional[int] = ..., fate: _Optional[str] = ..., arrival_t_s: _Optional[float] = ...) -> None: ...
