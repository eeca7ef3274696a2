"""Bytes ⇄ messages: :func:`encode`, :func:`decode` (the size limit, the protobuf parse and
:func:`~swarmrt.bus.validation.validate`; a bus sample is opened with
:func:`swarmrt.bus.receive.receive`, which calls it), and the protobuf helpers that stand in
for pydantic's (:func:`replace`, :func:`opt`, :func:`as_dict`), the schemas a recording
embeds (:func:`file_descriptor_set`) and an image message's pixels (:func:`pixels`)."""

from __future__ import annotations

import numpy as np
from google.protobuf.message import DecodeError

from swarmrt.bus.accounting import counted
from swarmrt.bus.v1.images_pb2 import Images
from swarmrt.bus.validation import validate
from swarmrt.bus.wire import MAX_PAYLOAD_BYTES, MAX_PAYLOAD_DEFAULT, MODELS, SCHEMA_VERSION, MessageError


# -- encoding and decoding -------------------------------------------------------------
@counted
def encode(msg) -> bytes:
    """The wire bytes of a message; stamps the schema version when the builder left it out."""
    if not msg.schema_version:
        msg.schema_version = SCHEMA_VERSION
    return msg.SerializeToString()


@counted
def decode(kind: str, payload: bytes | bytearray | memoryview, shallow: bool = False, n_sats: int | None = None):
    """Parse and validate a payload of the given kind; :class:`MessageError` on any defect.

    ``shallow``: for a receiver that reads only the header and the scalars of an estimate
    (who, which step, prior or posterior), check only those (:data:`SHALLOW_KINDS`); its
    arrays are then not to be read. Everything else is always checked in full."""
    cls = MODELS.get(kind)
    if cls is None:
        raise MessageError(f"unknown message kind {kind!r}")
    limit = MAX_PAYLOAD_BYTES.get(kind, MAX_PAYLOAD_DEFAULT)
    if len(payload) > limit:
        raise MessageError(f"invalid {kind} message: {len(payload)} bytes, more than the {limit} a {kind} message may have")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except DecodeError as exc:
        raise MessageError(f"invalid {kind} message: not a {cls.DESCRIPTOR.full_name} ({exc})") from None
    validate(msg, kind, shallow, n_sats)
    return msg


# -- helpers in place of pydantic's -------------------------------------------------------
def replace(msg, **changes):
    """A copy of ``msg`` with some fields changed (``None`` clears an optional field)."""
    out = type(msg)()
    out.CopyFrom(msg)
    fields = out.DESCRIPTOR.fields_by_name
    for name, v in changes.items():
        f = fields.get(name)
        if f is None:
            raise AttributeError(f"{out.DESCRIPTOR.full_name} has no field {name!r}")
        if v is None:
            out.ClearField(name)
        elif f.is_repeated:
            out.ClearField(name)
            getattr(out, name).extend(v)
        elif f.message_type is not None:
            getattr(out, name).CopyFrom(v)
        else:
            setattr(out, name, v)
    return out


def opt(msg, name: str):
    """An optional field's value, or None when it is unset."""
    return getattr(msg, name) if msg.HasField(name) else None


def as_dict(msg, exclude=()) -> dict:
    """Plain Python values of every field (unset optional fields as None), for JSON."""
    out = {}
    for f in msg.DESCRIPTOR.fields:
        if f.name in exclude:
            continue
        v = getattr(msg, f.name)
        if f.is_repeated:
            v = [as_dict(x) for x in v] if f.message_type is not None else list(v)
        elif f.message_type is not None:
            v = as_dict(v) if msg.HasField(f.name) else None
        elif f.has_presence and not msg.HasField(f.name):
            v = None
        out[f.name] = v
    return out


def file_descriptor_set(message_class) -> bytes:
    """The serialized FileDescriptorSet of a protobuf message class and everything it
    imports: the schema data of an MCAP channel with encoding "protobuf"."""
    from google.protobuf import descriptor_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd):
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        fds.file.append(proto)

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


def pixels(msg: Images) -> list[np.ndarray]:
    """Every view's images in view order, as writeable uint8 arrays (height × width)."""
    return [
        np.frombuffer(im, dtype=np.uint8).reshape(v.height_px, v.width_px).copy()
        for v in msg.views
        for im in v.images_mono8
    ]
