"""Scene messages onto the Foxglove SDK's channels (a :class:`~swarm.record.scene.SceneSink`).

Every channel is a generic ``foxglove.Channel`` carrying the same protobuf bytes, schema and
encodings as the recording's channel of that topic (the SDK's typed channels only take its
own message classes). A channel is created once per topic, on a private
``foxglove.Context`` so that nothing else in the process logs to this server. ``wants(topic)``
is the channel's ``has_sinks()``: true only while some client is subscribed, so no scene is
built for nobody.
"""

from __future__ import annotations

import threading
from typing import Any

from swarm.record.scene import ChannelSpec, SceneMessage

__all__ = ["LiveSink"]


class LiveSink:
    def __init__(self, context=None):
        import foxglove

        self._fg = foxglove
        self.context = context if context is not None else foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.latest: dict[str, SceneMessage] = {}  # the last message built per topic (a late subscriber gets it)
        self.sent = 0

    def advertise(self, topics: list[tuple[str, ChannelSpec]]) -> None:
        """Create the channels now, so a client sees (and can subscribe to) every topic at once."""
        for topic, spec in topics:
            self._channel(topic, spec)

    def _channel(self, topic: str, spec: ChannelSpec):
        ch = self._channels.get(topic)
        if ch is None:
            with self._lock:
                ch = self._channels.get(topic)
                if ch is None:
                    schema = self._fg.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data)
                    ch = self._channels[topic] = self._fg.Channel(topic, schema=schema, message_encoding=spec.message_encoding,
                                                                  context=self.context)
        return ch

    @property
    def topics(self) -> list[str]:
        return list(self._channels)

    def wants(self, topic: str) -> bool:
        ch = self._channels.get(topic)
        return ch is not None and ch.has_sinks()

    def emit(self, msg: SceneMessage) -> None:
        self._channel(msg.topic, msg.spec).log(msg.data, log_time=msg.log_ns)
        self.latest[msg.topic] = msg
        self.sent += 1

    def resend(self, topic: str) -> bool:
        """Log the last message of ``topic`` again (for a client that just subscribed)."""
        m = self.latest.get(topic)
        if m is None:
            return False
        self._channel(m.topic, m.spec).log(m.data, log_time=m.log_ns)
        return True
