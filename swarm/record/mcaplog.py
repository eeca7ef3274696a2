"""MCAP recording that stays readable when the recorder is killed (SIGKILL) at any instant.

The ``mcap`` library writes the summary and footer only in ``finish()``, so a killed
writer leaves a file ``make_reader`` refuses. :class:`CheckpointWriter` builds records with
the library's record classes and, at every flush, appends them followed by a fresh tail
(an empty private record, DataEnd, Footer with no summary, magic). The new data becomes
visible only when one byte changes: the length of the *previous* tail's private record,
which then spans (and so hides) the previous DataEnd/Footer/magic. Readers skip private
records (opcodes ≥ 0x80), so the file is valid before, during and after every flush:

1. write the new tail (never across a page boundary, so a kill cannot tear it) at its
   final position, beyond the end — the file now ends with a valid footer and magic;
2. write the new records into the gap in front of it (a torn write here is invisible:
   readers still stop at the previous footer);
3. commit: one byte, the previous private record's length.

On a clean stop, :meth:`CheckpointWriter.close` rewrites the file with the library's own
``Writer`` into a chunked, compressed, indexed MCAP. Written by hand because the ``mcap``
package has no incremental finalisation; everything it can do (records, the final file,
reading) is left to it.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Header, Message, Schema
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

__all__ = ["CheckpointWriter", "iter_messages", "iter_records", "recover", "PROFILE"]

PROFILE = "swarm-coloc"
_PRIVATE = 0xFF
_PAGE = 4096


def _pad(n: int) -> bytes:
    """A private record with ``n`` content bytes (readers skip it)."""
    return bytes([_PRIVATE]) + struct.pack("<Q", n) + b"\0" * n


def _tail() -> bytes:
    rb = RecordBuilder()
    DataEnd(0).write(rb)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
    return _pad(0) + rb.end() + MCAP0_MAGIC


_TAIL = _tail()
_TAIL_HIDE = len(_TAIL) - 9  # length that makes a tail's private record cover the rest of it


class CheckpointWriter:
    def __init__(self, path: str | Path, library: str = "swarm-coloc recorder"):
        self.path = Path(path)
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        rb = RecordBuilder()
        Header(profile=PROFILE, library=library).write(rb)
        head = MCAP0_MAGIC + rb.end()
        os.pwrite(self.fd, head + _TAIL, 0)
        self.tail_pos = len(head)  # where the live tail starts
        self.pending = RecordBuilder()
        self.pending_count = 0
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.seq: dict[int, int] = {}
        self.messages = 0
        self.flushes = 0

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = self.schemas.get(name)
        if sid is None:
            sid = self.schemas[name] = len(self.schemas) + 1
            Schema(id=sid, name=name, encoding=encoding, data=data).write(self.pending)
        return sid

    def channel(self, topic: str, schema_id: int, message_encoding: str = "json", metadata: dict | None = None) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            cid = self.channels[topic] = len(self.channels) + 1
            Channel(id=cid, topic=topic, message_encoding=message_encoding, schema_id=schema_id, metadata=metadata or {}).write(self.pending)
        return cid

    def add(self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        seq = self.seq.get(channel_id, 0)
        self.seq[channel_id] = seq + 1
        Message(
            channel_id=channel_id,
            sequence=seq,
            log_time=int(log_time_ns),
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            data=bytes(data),
        ).write(self.pending)
        self.pending_count += 1
        self.messages += 1

    def flush(self) -> None:
        """Make everything added so far durable against a kill (see the module doc)."""
        body = self.pending.end()
        if not body:
            return
        start = self.tail_pos + len(_TAIL)  # the old tail stays in place until the commit
        end = start + len(body)
        if end % _PAGE + len(_TAIL) > _PAGE:  # keep the new tail inside one page
            gap = _PAGE - end % _PAGE
            body += _pad(max(0, gap - 9)) if gap >= 9 else _pad(gap + _PAGE - 9)
            end = start + len(body)
        os.pwrite(self.fd, _TAIL, end)  # 1. new tail at its final place
        os.pwrite(self.fd, body, start)  # 2. the records in front of it
        os.pwrite(self.fd, bytes([_TAIL_HIDE]), self.tail_pos + 1)  # 3. commit: hide the old tail
        self.tail_pos = end
        self.pending_count = 0
        self.flushes += 1

    def close(self, finalize: bool = True) -> None:
        self.flush()
        os.close(self.fd)
        if finalize:
            compact(self.path)


def iter_messages(path: str | Path) -> Iterator[tuple[str, str, bytes, int, int]]:
    """``(topic, schema name, data, log_time_ns, publish_time_ns)`` of every message, in file order.

    Uses ``mcap.reader.make_reader``; a file torn by something other than our recorder
    (e.g. a killed ``mcap.Writer``) falls back to streaming every complete record.
    """
    for schema, channel, msg in iter_records(path):
        yield channel.topic, schema.name if schema else "", msg.data, msg.log_time, msg.publish_time


def iter_records(path: str | Path) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """``(schema, channel, message)`` records of every message, in file order (as
    :func:`iter_messages`, with the schemas' encodings and data)."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader

    # What the indexed reader yielded before it failed (if it did): the record-by-record
    # reader below starts from the file's beginning and would yield those again (a corrupt
    # channel id in a checkpoint file read 42 messages where 28 were written; found by the
    # MCAP fuzz harness). A message is the same one when its topic, times, sequence and bytes are.
    done: set[tuple[str, int, int, int, int]] = set()
    with open(path, "rb") as f:
        try:
            reader = make_reader(f)
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                done.add(_identity(channel, msg))
                yield schema, channel, msg
            return
        except Exception:
            f.seek(0)
    schemas, channels = {}, {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    ch = channels[rec.channel_id]
                    if done and _identity(ch, rec) in done:
                        continue
                    yield schemas.get(ch.schema_id), ch, rec
        except Exception:
            return


def _identity(channel: Channel, msg: Message) -> tuple[str, int, int, int, int]:
    """What makes a recorded message the one it is, cheaply (every message of every read
    goes through it): its topic, log and publish times (ns), sequence and size. Two records
    equal in all of them are one message written twice, which a reader may merge."""
    return (channel.topic, msg.log_time, msg.publish_time, msg.sequence, len(msg.data))


def compact(path: str | Path) -> None:
    """Rewrite a recording as a chunked, zstd-compressed, indexed MCAP (atomic rename)."""
    from mcap.reader import make_reader

    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".compact")
    with open(path, "rb") as src, open(tmp, "wb") as dst:
        reader = make_reader(src)
        w = Writer(dst, compression=_compression(), chunk_size=1 << 20)
        w.start(profile=PROFILE, library="swarm-coloc recorder")
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in sids:
                sids[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in cids:
                cids[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sids.get(channel.schema_id, 0), channel.metadata)
            w.add_message(cids[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()
    os.replace(tmp, path)


def _compression():
    try:
        import zstandard  # noqa: F401

        return CompressionType.ZSTD
    except ImportError:
        try:
            import lz4  # noqa: F401

            return CompressionType.LZ4
        except ImportError:
            return CompressionType.NONE


def recover(path: str | Path, out: str | Path | None = None) -> int:
    """Salvage every complete message of a damaged recording into a clean file; returns the count."""
    path = Path(path)
    out = Path(out) if out else path.with_name(path.stem + ".recovered.mcap")
    w = CheckpointWriter(out)
    count = 0
    for schema, channel, msg in iter_records(path):
        # Each channel keeps its schema (encoding and data) and message encoding.
        sid = w.schema(schema.name, schema.encoding, schema.data) if schema is not None else w.schema("raw", "", b"")
        w.add(w.channel(channel.topic, sid, channel.message_encoding, channel.metadata), msg.data, msg.log_time, msg.publish_time)
        count += 1
    w.close(finalize=True)
    return count
