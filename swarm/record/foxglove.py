"""Standard Foxglove channels derived from the bus, so a run plays back (and shows live) in 3-D.

:class:`FoxgloveDeriver` turns decoded bus messages (truth, posterior estimates, measurement
batches, link counters, faults, images) into the values :class:`swarm.record.scene.SceneBuilder`
takes, and the builder makes the scene's messages (the channels are listed there). The
recorder feeds it the recorded messages when the run is over (its sink: the recording); the
live view (:mod:`swarm.live`) feeds it the bus as the run goes (its sink: the Foxglove
WebSocket server). ``swarm sim`` feeds the builder the simulator's values
(:mod:`swarm.record.scene_file`). One builder, so the same layout opens all three.

Rendered camera images (``/sat<i>/cam<c>``, ``foxglove.RawImage``, mono8) are added here when
asked for (``emulator.record_images``): the recorder writes them as they arrive.
"""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from swarm.record.scene import (
    CHANNELS,
    LINK_COUNTERS,
    LINK_STATES,
    CameraRig,
    SceneBuilder,
    SceneMessage,
    SceneSink,
    WriterSink,
    _ts,
    link_states,
    proto_spec,
    q_BH,
)
from swarmrt.bus.convert import array
from swarmrt.bus.messages import file_descriptor_set, opt, pixels

__all__ = ["FoxgloveDeriver", "file_descriptor_set", "q_BH", "CHANNELS", "LINK_STATES", "link_states", "DERIVED_KINDS"]

#: The bus message kinds the scene is derived from (images aside).
DERIVED_KINDS = ("truth", "est", "meas", "links", "fault")


class FoxgloveDeriver:
    """Decoded bus messages → :class:`SceneBuilder` (→ the recording, or the live server).

    ``out``: an MCAP writer with ``schema``/``channel``/``add`` (the recorder's), or a
    :class:`~swarm.record.scene.SceneSink`. ``n_sats``: the swarm's size (default: from the
    first truth message)."""

    def __init__(self, out, mean_motion: float | None = None, half_size_m: float = 0.2, images: bool = False,
                 n_sats: int | None = None, cameras: CameraRig | None = None):
        self.sink: SceneSink = out if hasattr(out, "emit") else WriterSink(out)
        self.images = images  # rendered camera images too (large: opt-in)
        self.mean_motion = mean_motion
        self.half_size_m = half_size_m
        self.cameras = cameras or CameraRig(offset_m=half_size_m)
        self.builder: SceneBuilder | None = None
        if mean_motion is not None and n_sats is not None:
            self.builder = SceneBuilder(self.sink, n_sats, mean_motion, half_size_m, self.cameras)

    @classmethod
    def for_scenario(cls, out, sc, images: bool | None = None) -> FoxgloveDeriver:
        """The deriver of a scenario's run (its orbit, size, cameras)."""
        return cls(out, sc.orbit.mean_motion_rad_s, sc.spacecraft.half_size_m,
                   images=sc.emulator.record_images if images is None else images, n_sats=sc.n_sats, cameras=CameraRig.of(sc))

    def _builder(self, n: int) -> SceneBuilder | None:
        if self.builder is None and self.mean_motion is not None:
            self.builder = SceneBuilder(self.sink, n, self.mean_motion, self.half_size_m, self.cameras)
        return self.builder

    def on_message(self, kind: str, msg, log_ns: int, draw: bool = True) -> None:
        """One decoded bus message of ``kind`` received at ``log_ns``; ``draw`` False: only
        keep what later messages need (the live view skips steps it has no time to draw)."""
        if self.mean_motion is None:
            return
        if kind == "truth":
            b = self._builder(len(msg.q_BI) // 4)
            if b is not None:
                b.truth(int(msg.k), msg.t_s, np.asarray(msg.q_BI), np.asarray(msg.r_H_m), log_ns, draw)
            return
        b = self.builder
        if kind == "img" and self.images:
            self._images(msg, log_ns)
        if b is None:
            return
        if kind == "est" and msg.phase == "posterior":
            b.estimate(int(msg.own), int(msg.k), msg.t_s, list(msg.ids), np.asarray(msg.q_BI), np.asarray(msg.r_H_m),
                       array(msg.P_pose), log_ns, draw)
        elif kind == "meas":
            b.measurements(int(msg.observer), int(msg.k), list(msg.target), log_ns, draw)
        elif kind == "links":
            b.links(int(msg.k), {c: array(getattr(msg, c)) for c in LINK_COUNTERS}, log_ns, draw)
        elif kind == "fault":
            b.fault(int(msg.k), msg.t_s, msg.action, msg.phase, msg.sender, log_ns, target=opt(msg, "target"),
                    camera=opt(msg, "camera"), state=opt(msg, "state"), detail=msg.detail)

    def _images(self, m, log_ns: int) -> None:
        """Every rendered view as ``foxglove.RawImage`` (mono8) on ``/sat<i>/cam<c>[/left|/right]``."""
        pix = iter(pixels(m))
        spec = proto_spec(RawImage)
        for v in m.views:
            for side in (("",) if len(v.images_mono8) == 1 else ("/left", "/right")):
                im = next(pix)
                msg = RawImage(timestamp=_ts(round(m.t_s * 1e9)), frame_id=f"sat{m.sat}/cam{v.camera}",
                               width=v.width_px, height=v.height_px, encoding="mono8", step=v.width_px, data=im.tobytes())
                self.sink.emit(SceneMessage(f"/sat{m.sat}/cam{v.camera}{side}", spec, msg.SerializeToString(), log_ns))
