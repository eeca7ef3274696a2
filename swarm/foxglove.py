"""Standard Foxglove channels derived from the bus, so a recording plays back in 3-D.

Written by the recorder next to the project's own messages, protobuf-encoded with the
official schemas (``foxglove-schemas-protobuf``), each channel carrying its
FileDescriptorSet as the MCAP schema:

* ``/foxglove/tf`` (``foxglove.FrameTransforms``): frame ``hcw`` (the HCW frame) → ``sat<i>``
  (true body frames);
* ``/foxglove/truth`` (``foxglove.SceneUpdate``): the satellites as 40 cm cubes, labelled;
* ``/foxglove/est/<i>`` (``foxglove.SceneUpdate``): agent i's estimate of every satellite —
  a translucent cube at the estimated pose and the 3σ position ellipsoid;
* ``/foxglove/measurements`` (``foxglove.SceneUpdate``): a line per relative measurement
  broadcast at the step, observer → target;
* ``/foxglove/links`` (``foxglove.SceneUpdate``, when the scenario has ``links:``): the radio of
  each step — every directed link i → j that carried traffic drawn as the half of the segment
  between the true positions on the sender's side (so i → j and j → i are both visible), coloured
  by what happened on it in that step (:data:`LINK_STATES`, from the difference of the world's
  cumulative :class:`~swarm.bus.messages.LinkStats` counters between consecutive steps);
* ``/foxglove/cam/<i>/<c>`` (``foxglove.RawImage``): camera images, when they travel on the bus.

Frames: Foxglove quaternions are Hamilton (x, y, z, w) rotating the parent frame onto the
child; for the body frame B in H that is exactly our Shuster ``q_BH = q_BI ⊗ q_IH``
(the conversion is pinned in ``tests/test_foxglove.py``).
"""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from swarmcore import quat

from .bus.convert import array
from .bus.messages import file_descriptor_set, pixels

__all__ = ["FoxgloveDeriver", "file_descriptor_set", "q_BH", "CHANNELS", "LINK_STATES", "link_states"]

CHANNELS = {
    "/foxglove/tf": "foxglove.FrameTransforms",
    "/foxglove/truth": "foxglove.SceneUpdate",
    "/foxglove/est/<i>": "foxglove.SceneUpdate",
    "/foxglove/measurements": "foxglove.SceneUpdate",
    "/foxglove/links": "foxglove.SceneUpdate",
    "/foxglove/cam/<i>/<c>": "foxglove.RawImage",
}

#: What happened on a directed link in one step, worst first, with its colour (RGB) in
#: ``/foxglove/links``. A link with several events in a step (a late copy arrives while this
#: step's copy is lost) shows the worst one; ``in_flight``: a copy was sent and nothing
#: arrived or was lost yet (latency longer than the step); a link with no traffic is not drawn.
LINK_STATES: tuple[tuple[str, tuple[float, float, float]], ...] = (
    ("unreachable", (0.55, 0.55, 0.55)),  # grey: dead, out of range or blocked; nothing sent
    ("dropped_queue", (0.75, 0.2, 0.85)),  # purple: did not fit the transmitter's queue
    ("lost", (0.9, 0.1, 0.1)),  # red: lost on the channel
    ("delivered_late", (1.0, 0.65, 0.0)),  # orange: arrived after the step it was taken in
    ("delivered", (0.1, 0.8, 0.2)),  # green: arrived within its own step
    ("in_flight", (0.3, 0.6, 1.0)),  # blue: sent, not arrived yet
)
#: The cumulative counters of ``LinkStats`` that :func:`link_states` reads.
_LINK_COUNTERS = ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")

_PALETTE = [
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.4, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
]


def q_BH(q_BI: np.ndarray, mean_motion: float, t: float) -> np.ndarray:
    """Shuster ``q_BH`` (= Foxglove's x, y, z, w of frame B in frame H)."""
    half = -0.5 * mean_motion * t  # T_IH is a turn of +n t about z: T(q_IH) with angle −n t
    q_IH = np.array([0.0, 0.0, np.sin(half), np.cos(half)])
    return quat.normalize(quat.qmul(q_BI, q_IH))


def link_states(prev: dict[str, np.ndarray] | None, cur: dict[str, np.ndarray]) -> np.ndarray:
    """(n, n) index into :data:`LINK_STATES` of each directed link's state in one step, −1
    for no traffic (and on the diagonal), from two consecutive cumulative counter sets
    (``prev`` None: the first step, from zero). ``delivered`` counts on-time deliveries only
    here: the step's deliveries minus its late ones."""
    d = {k: np.asarray(cur[k]) - (0 if prev is None else np.asarray(prev[k])) for k in _LINK_COUNTERS}
    d["delivered"] = d["delivered"] - d["delivered_late"]
    d["in_flight"] = d["sent"]
    n = d["sent"].shape[0]
    out = np.full((n, n), -1, dtype=int)
    for code in range(len(LINK_STATES) - 1, -1, -1):  # best first, so the worst overwrites
        out[d[LINK_STATES[code][0]] > 0] = code
    np.fill_diagonal(out, -1)
    return out


def _ts(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _color(i: int, a: float = 1.0) -> Color:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return Color(r=r, g=g, b=b, a=a)


def _pose(r, q) -> Pose:
    return Pose(position=Vector3(x=r[0], y=r[1], z=r[2]), orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


class FoxgloveDeriver:
    """Turns decoded bus messages into Foxglove messages on the recorder's writer."""

    def __init__(self, writer, mean_motion: float | None = None, half_size_m: float = 0.2, images: bool = False):
        self.w = writer
        self.images = images  # rendered camera images too (large: opt-in)
        self.mean_motion = mean_motion
        self.size = 2 * half_size_m
        self._sids: dict[str, int] = {}
        self._truth_r = None
        self._truth_at: dict[int, np.ndarray] = {}  # true positions of the last few steps (links)
        self._link_prev: dict[str, np.ndarray] | None = None  # counters of the previous LinkStats

    def _channel(self, topic: str, cls) -> int:
        name = cls.DESCRIPTOR.full_name
        sid = self._sids.get(name)
        if sid is None:
            sid = self._sids[name] = self.w.schema(name, "protobuf", file_descriptor_set(cls))
        return self.w.channel(topic, sid, "protobuf")

    def _put(self, topic: str, msg, log_ns: int) -> None:
        self.w.add(self._channel(topic, type(msg)), msg.SerializeToString(), log_ns, log_ns)

    def on_message(self, kind: str, msg, log_ns: int) -> None:
        if self.mean_motion is None:
            return
        if kind == "truth":
            self._truth(msg, log_ns)
        elif kind == "est" and msg.phase == "posterior":
            self._estimate(msg, log_ns)
        elif kind == "meas":
            self._measurements(msg, log_ns)
        elif kind == "links":
            self._links(msg, log_ns)
        elif kind == "img" and self.images:
            self._images(msg, log_ns)

    def _images(self, m, log_ns: int) -> None:
        """Every rendered view as ``foxglove.RawImage`` (mono8) on ``/sat<i>/cam<c>[/left|/right]``."""
        pix = iter(pixels(m))
        for v in m.views:
            for side in (("",) if len(v.images_mono8) == 1 else ("/left", "/right")):
                im = next(pix)
                msg = RawImage(timestamp=_ts(round(m.t_s * 1e9)), frame_id=f"sat{m.sat}/cam{v.camera}",
                               width=v.width_px, height=v.height_px, encoding="mono8", step=v.width_px, data=im.tobytes())
                self._put(f"/sat{m.sat}/cam{v.camera}{side}", msg, log_ns)

    def _truth(self, m, log_ns: int) -> None:
        q = q_BH(np.asarray(m.q_BI).reshape(-1, 4), self.mean_motion, m.t_s)
        r = np.asarray(m.r_H_m).reshape(-1, 3)
        self._truth_r = r
        self._truth_at[m.k] = r
        self._truth_at.pop(m.k - 8, None)
        tfs = FrameTransforms(
            transforms=[
                FrameTransform(
                    timestamp=_ts(log_ns),
                    parent_frame_id="hcw",
                    child_frame_id=f"sat{i}",
                    translation=Vector3(x=r[i, 0], y=r[i, 1], z=r[i, 2]),
                    rotation=Quaternion(x=q[i, 0], y=q[i, 1], z=q[i, 2], w=q[i, 3]),
                )
                for i in range(r.shape[0])
            ]
        )
        self._put("/foxglove/tf", tfs, log_ns)
        ents = []
        for i in range(r.shape[0]):
            ents.append(
                SceneEntity(
                    timestamp=_ts(log_ns),
                    frame_id="hcw",
                    id=f"sat{i}",
                    lifetime=Duration(seconds=0),
                    frame_locked=False,
                    cubes=[CubePrimitive(pose=_pose(r[i], q[i]), size=Vector3(x=self.size, y=self.size, z=self.size), color=_color(i))],
                    texts=[TextPrimitive(pose=_pose(r[i] + [0, 0, self.size], [0, 0, 0, 1]), billboard=True, font_size=14, scale_invariant=True, color=Color(r=1, g=1, b=1, a=1), text=f"sat {i}")],
                )
            )
        self._put("/foxglove/truth", SceneUpdate(entities=ents), log_ns)

    def _estimate(self, m, log_ns: int) -> None:
        q = q_BH(np.asarray(m.q_BI).reshape(-1, 4), self.mean_motion, m.t_s)
        r = np.asarray(m.r_H_m).reshape(-1, 3)
        P = array(m.P_pose)  # (n, 6, 6), [a_B, r_H]
        # Every satellite's 3σ position ellipsoid at once (an agent's scene at n = 40 is 40
        # of them, 40 times a step): principal axes of the symmetrised position blocks.
        Pr = P[:, 3:, 3:]
        w, V = np.linalg.eigh(0.5 * (Pr + np.swapaxes(Pr, -1, -2)))
        axes = 2 * 3 * np.sqrt(np.clip(w, 0, None))  # 3σ ellipsoid diameters
        V[np.linalg.det(V) < 0, :, 0] *= -1  # proper rotations
        q_ell = quat.normalize(quat.from_attitude_matrix(np.swapaxes(V, -1, -2)))  # principal axes in H
        ts, size, cube_c, sph_c = _ts(log_ns), Vector3(x=self.size, y=self.size, z=self.size), _color(m.own, 0.35), _color(m.own, 0.25)
        no_life = Duration(seconds=0)
        r, q, q_ell, axes = r.tolist(), q.tolist(), q_ell.tolist(), axes.tolist()  # Python floats build messages faster
        ents = [
            SceneEntity(
                timestamp=ts,
                frame_id="hcw",
                id=f"est{m.own}-sat{j}",
                lifetime=no_life,
                cubes=[CubePrimitive(pose=_pose(r[j], q[j]), size=size, color=cube_c)],
                spheres=[SpherePrimitive(pose=_pose(r[j], q_ell[j]), size=Vector3(x=axes[j][0], y=axes[j][1], z=axes[j][2]), color=sph_c)],
            )
            for j in range(len(r))
        ]
        self._put(f"/foxglove/est/{m.own}", SceneUpdate(entities=ents), log_ns)

    def _measurements(self, m, log_ns: int) -> None:
        if self._truth_r is None:
            return
        r = self._truth_r
        lines = [
            LinePrimitive(
                type=LinePrimitive.LINE_LIST,
                pose=_pose([0, 0, 0], [0, 0, 0, 1]),
                thickness=2.0,
                scale_invariant=True,
                points=[Point3(x=r[i, 0], y=r[i, 1], z=r[i, 2]), Point3(x=r[j, 0], y=r[j, 1], z=r[j, 2])],
                color=_color(m.observer, 0.8),
            )
            for i, j in ((m.observer, t) for t in m.target)
        ]
        ent = SceneEntity(timestamp=_ts(log_ns), frame_id="hcw", id=f"meas{m.observer}", lifetime=Duration(seconds=0), lines=lines)
        self._put("/foxglove/measurements", SceneUpdate(entities=[ent]), log_ns)

    def _links(self, m, log_ns: int) -> None:
        """One entity ``links`` per step (it replaces the previous step's): a LINE_LIST per
        state, each directed link i → j from r_i to the midpoint of i and j, and the state of
        every link with traffic as metadata (``"i->j": state``)."""
        cur = {k: np.rint(array(getattr(m, k))).astype(np.int64) for k in _LINK_COUNTERS}
        states = link_states(self._link_prev, cur)
        self._link_prev = cur
        r = self._truth_at.get(m.k, self._truth_r)
        if r is None or r.shape[0] != states.shape[0]:
            return
        lines, meta = [], []
        for code, (name, (cr, cg, cb)) in enumerate(LINK_STATES):
            ii, jj = np.nonzero(states == code)
            if not ii.size:
                continue
            pts = []
            for i, j in zip(ii, jj):
                mid = 0.5 * (r[i] + r[j])
                pts += [Point3(x=r[i, 0], y=r[i, 1], z=r[i, 2]), Point3(x=mid[0], y=mid[1], z=mid[2])]
                meta.append(KeyValuePair(key=f"{i}->{j}", value=name))
            lines.append(LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose([0, 0, 0], [0, 0, 0, 1]), thickness=3.0,
                                       scale_invariant=True, points=pts, color=Color(r=cr, g=cg, b=cb, a=0.9)))
        ent = SceneEntity(timestamp=_ts(log_ns), frame_id="hcw", id="links", lifetime=Duration(seconds=0), lines=lines,
                          metadata=sorted(meta, key=lambda kv: tuple(int(x) for x in kv.key.split("->"))))
        self._put("/foxglove/links", SceneUpdate(entities=[ent]), log_ns)
