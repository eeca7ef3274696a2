"""The swarm's 3-D scene as Foxglove messages, built from plain values.

One builder serves every place the scene is shown: the recorder (from the recorded bus
messages, through :class:`swarm.record.foxglove.FoxgloveDeriver`), the live view
(:mod:`swarm.live`, the same deriver fed by the bus as it runs) and ``swarm sim`` (from the
simulator's values at each step, :mod:`swarm.record.scene_file`). So a Foxglove layout made
for one opens the others (``docs/foxglove-layout.json``).

Channels (every SceneUpdate entity in frame ``hcw``, the Hill frame, unless noted):

=========================== ============================= ==============================================
topic                       schema                        what
=========================== ============================= ==============================================
``/foxglove/tf``            foxglove.FrameTransforms      ``hcw`` → ``sat<i>``: each true body frame
``/foxglove/truth``         foxglove.SceneUpdate          each satellite as a cube, labelled; metadata
                                                          ``k``, ``t_s``
``/foxglove/est/<i>``       foxglove.SceneUpdate          filter i's estimate of each satellite it
                                                          tracks: a translucent cube and the 3σ position
                                                          ellipsoid
``/foxglove/measurements``  foxglove.SceneUpdate          a line per relative measurement, observer →
                                                          target
``/foxglove/links``         foxglove.SceneUpdate          (``links:``) each directed link coloured by
                                                          what it did in the step (:data:`LINK_STATES`)
``/foxglove/cameras``       foxglove.SceneUpdate          the cameras' fields of view: a frustum per face
                                                          camera (frame ``sat<i>``; red once a fault
                                                          turned it off), or the stereo camera aimed at
                                                          each target it measured
``/foxglove/faults``        foxglove.Log                  each fault: a command (info), carried out
                                                          (warning), failed (error)
``/errors/<i>``             swarm_coloc.view.FilterErrors filter i's errors against the truth, for the
                                                          Plot panel (``/errors/0.own_pos_err_m``,
                                                          ``/errors/0.nees[2]``)
=========================== ============================= ==============================================

Every channel is protobuf with its FileDescriptorSet as the schema: the official Foxglove
schemas (``foxglove-schemas-protobuf``), and for ``/errors/<i>`` one built here
(:data:`ERRORS_FIELDS`). Foxglove quaternions are Hamilton (x, y, z, w) rotating the parent frame onto the
child; for the body frame B in H that is exactly our Shuster ``q_BH = q_BI ⊗ q_IH`` (pinned in
``tests/test_foxglove.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from swarmcore import quat
from swarmcore.cameras import T_CB
from swarmcore.metrics import pose_errors, pose_nees
from swarmrt.bus.messages import file_descriptor_set

__all__ = [
    "ChannelSpec",
    "SceneMessage",
    "SceneSink",
    "WriterSink",
    "CameraRig",
    "SceneBuilder",
    "CHANNELS",
    "LINK_STATES",
    "LINK_COUNTERS",
    "ERRORS_SPEC",
    "FilterErrors",
    "link_states",
    "q_BH",
    "proto_spec",
    "scene_topics",
]

#: Every channel of the scene (``<i>``: one per satellite's filter).
CHANNELS = {
    "/foxglove/tf": "foxglove.FrameTransforms",
    "/foxglove/truth": "foxglove.SceneUpdate",
    "/foxglove/est/<i>": "foxglove.SceneUpdate",
    "/foxglove/measurements": "foxglove.SceneUpdate",
    "/foxglove/links": "foxglove.SceneUpdate",
    "/foxglove/cameras": "foxglove.SceneUpdate",
    "/foxglove/faults": "foxglove.Log",
    "/errors/<i>": "swarm_coloc.view.FilterErrors",
    "/sat<i>/cam<c>": "foxglove.RawImage",
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
#: The cumulative per-link counters :func:`link_states` reads (``LinkStats``, ``LinkCounters``).
LINK_COUNTERS = ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")

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


def link_states(prev: dict[str, Any] | None, cur: dict[str, Any]) -> np.ndarray:
    """(n, n) index into :data:`LINK_STATES` of each directed link's state in one step, −1
    for no traffic (and on the diagonal), from two consecutive cumulative counter sets
    (``prev`` None: the first step, from zero). ``delivered`` counts on-time deliveries only
    here: the step's deliveries minus its late ones."""
    d = {k: np.asarray(cur[k]) - (0 if prev is None else np.asarray(prev[k])) for k in LINK_COUNTERS}
    d["delivered"] = d["delivered"] - d["delivered_late"]
    d["in_flight"] = d["sent"]
    n = d["sent"].shape[0]
    out = np.full((n, n), -1, dtype=int)
    for code in range(len(LINK_STATES) - 1, -1, -1):  # best first, so the worst overwrites
        out[d[LINK_STATES[code][0]] > 0] = code
    np.fill_diagonal(out, -1)
    return out


# -- channels and sinks -----------------------------------------------------------------------
@dataclass(frozen=True)
class ChannelSpec:
    """How a channel is encoded: its schema (name, encoding, data) and message encoding."""

    schema_name: str
    schema_encoding: str  # "protobuf" | "jsonschema"
    schema_data: bytes
    message_encoding: str  # "protobuf" | "json"


@dataclass(frozen=True)
class SceneMessage:
    topic: str
    spec: ChannelSpec
    data: bytes
    log_ns: int


_SPECS: dict[str, ChannelSpec] = {}


def proto_spec(cls) -> ChannelSpec:
    """The channel spec of a protobuf message class (its FileDescriptorSet as the schema)."""
    name = cls.DESCRIPTOR.full_name
    spec = _SPECS.get(name)
    if spec is None:
        spec = _SPECS[name] = ChannelSpec(name, "protobuf", file_descriptor_set(cls), "protobuf")
    return spec


#: ``/errors/<i>``: one filter's errors at one step against the truth of that step. Scalars
#: are NaN when missing; arrays are indexed by satellite id (NaN: a satellite the filter does
#: not track). Protobuf like every other channel, its schema built here (no generated code).
ERRORS_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("k", "uint64", "step"),
    ("t_s", "double", "simulated time (s)"),
    ("own", "uint32", "the filter's own satellite"),
    ("own_att_err_deg", "double", "attitude error of its own satellite (deg)"),
    ("own_pos_err_m", "double", "position error of its own satellite (m)"),
    ("own_att_3sigma_deg", "double", "3 sqrt(trace of its attitude covariance) (deg)"),
    ("own_pos_3sigma_m", "double", "3 sqrt(trace of its position covariance) (m)"),
    ("own_nees", "double", "NEES of its own pose (6 degrees of freedom)"),
    ("others_att_err_rms_deg", "double", "RMS over the other satellites it tracks (deg)"),
    ("others_pos_err_rms_m", "double", "RMS over the other satellites it tracks (m)"),
    ("nees_mean", "double", "mean NEES over the satellites it tracks (6 when consistent)"),
    ("att_err_deg", "repeated double", "per satellite id"),
    ("pos_err_m", "repeated double", "per satellite id"),
    ("att_3sigma_deg", "repeated double", "per satellite id"),
    ("pos_3sigma_m", "repeated double", "per satellite id"),
    ("nees", "repeated double", "per satellite id"),
)


def _errors_class():
    """The ``swarm_coloc.view.FilterErrors`` protobuf class, built from :data:`ERRORS_FIELDS`."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    F = descriptor_pb2.FieldDescriptorProto
    fd = descriptor_pb2.FileDescriptorProto(name="swarm_coloc/view/filter_errors.proto", package="swarm_coloc.view", syntax="proto3")
    m = fd.message_type.add(name="FilterErrors")
    types = {"uint64": F.TYPE_UINT64, "uint32": F.TYPE_UINT32, "double": F.TYPE_DOUBLE}
    for num, (name, typ, _doc) in enumerate(ERRORS_FIELDS, start=1):
        rep = typ.startswith("repeated ")
        m.field.add(name=name, number=num, type=types[typ.removeprefix("repeated ")],
                    label=F.LABEL_REPEATED if rep else F.LABEL_OPTIONAL, json_name=name)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("swarm_coloc.view.FilterErrors"))
    fds = descriptor_pb2.FileDescriptorSet(file=[fd]).SerializeToString()
    return cls, fds


FilterErrors, _ERRORS_FDS = _errors_class()
ERRORS_SPEC = ChannelSpec("swarm_coloc.view.FilterErrors", "protobuf", _ERRORS_FDS, "protobuf")


class SceneSink(Protocol):
    """Where scene messages go: a recording, the live server."""

    def wants(self, topic: str) -> bool:
        """Whether anyone would see a message on ``topic`` now (the builder skips building
        what no one wants)."""
        ...

    def emit(self, msg: SceneMessage) -> None: ...


class WriterSink:
    """Scene messages into an MCAP writer with ``schema``, ``channel`` and ``add`` (the
    recorder's :class:`~swarm.record.mcaplog.CheckpointWriter`); everything is wanted."""

    def __init__(self, writer):
        self.w = writer
        self._channels: dict[str, int] = {}

    def wants(self, topic: str) -> bool:
        return True

    def channel(self, topic: str, spec: ChannelSpec) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self.w.schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
            cid = self._channels[topic] = self.w.channel(topic, sid, spec.message_encoding)
        return cid

    def emit(self, msg: SceneMessage) -> None:
        self.w.add(self.channel(msg.topic, msg.spec), msg.data, msg.log_ns, msg.log_ns)


# -- cameras -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraRig:
    """What ``/foxglove/cameras`` draws: the six face cameras (``faces``: synthetic and mono
    pipelines), the stereo tracking camera aimed at each target (``stereo``), or nothing."""

    kind: str = "faces"  # "faces" | "stereo" | "none"
    hfov_deg: float = 90.0
    vfov_deg: float = 90.0
    depth_m: float = 1.5  # how far the drawn frustum reaches (faces; stereo reaches the target)
    offset_m: float = 0.2  # a face camera's distance from the body centre

    @classmethod
    def of(cls, sc) -> CameraRig:
        """The rig of a scenario."""
        v = sc.vision
        if v.pipeline == "stereo":
            c = v.stereo_camera
            h = 2 * math.degrees(math.atan(0.5 * c.width_px / c.focal_px))
            vv = 2 * math.degrees(math.atan(0.5 * c.height_px / c.focal_px))
            return cls("stereo", h, vv, 0.0, sc.spacecraft.half_size_m)
        cam = v.mono_camera if v.pipeline == "mono" else sc.cameras
        h = float(cam.fov_deg)
        if v.pipeline == "mono" and v.mono_camera.focal_px:
            h = 2 * math.degrees(math.atan(0.5 * cam.width_px / v.mono_camera.focal_px))
        vv = 2 * math.degrees(math.atan(math.tan(math.radians(h) / 2) * cam.height_px / cam.width_px))
        return cls("faces", h, vv, 1.5, sc.spacecraft.half_size_m)

    def face_segments(self) -> np.ndarray:
        """(6, 8, 2, 3): each face camera's frustum as 8 segments in body coordinates
        (4 edges from the lens, 4 around the far rectangle)."""
        tx, ty = math.tan(math.radians(self.hfov_deg) / 2), math.tan(math.radians(self.vfov_deg) / 2)
        out = np.zeros((6, 8, 2, 3))
        for c in range(6):
            x, y, z = T_CB[c]  # camera axes in body coordinates: right, down, boresight
            apex = self.offset_m * z
            far = [apex + self.depth_m * (z + sx * tx * x + sy * ty * y) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            for e in range(4):
                out[c, e] = (apex, far[e])
                out[c, 4 + e] = (far[e], far[(e + 1) % 4])
        return out


def _ts(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _color(i: int, a: float = 1.0) -> Color:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return Color(r=r, g=g, b=b, a=a)


def _pose(r, q) -> Pose:
    return Pose(position=Vector3(x=r[0], y=r[1], z=r[2]), orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


def _points(pts) -> list[Point3]:
    return [Point3(x=p[0], y=p[1], z=p[2]) for p in np.asarray(pts, dtype=float).reshape(-1, 3).tolist()]


_IDENTITY = (0.0, 0.0, 0.0, 1.0)
_ORIGIN = (0.0, 0.0, 0.0)
_FOREVER = Duration(seconds=0)
_LOG_LEVELS = {"command": Log.INFO, "done": Log.WARNING, "failed": Log.ERROR}
_KEEP_TRUTH = 16  # steps of truth kept for estimates and measurements that come late


class SceneBuilder:
    """Builds the scene's messages (see the module docstring) from values and hands them to
    a :class:`SceneSink`. Each method takes one step's values of one kind; it keeps what the
    others need (the truth of the last steps, the previous link counters, which cameras are
    off) and builds nothing the sink does not want."""

    def __init__(self, sink: SceneSink, n_sats: int, mean_motion: float, half_size_m: float = 0.2,
                 cameras: CameraRig | None = None):
        self.sink = sink
        self.n = n_sats
        self.mean_motion = mean_motion
        self.size = 2 * half_size_m
        self.rig = cameras or CameraRig(offset_m=half_size_m)
        self._truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # k → (q_BI, r_H) of recent steps
        self._latest_k: int | None = None
        self._link_prev: dict[str, np.ndarray] | None = None
        self._shown: dict[int, set[int]] = {}  # filter → the satellites its scene shows now
        self.camera_off = np.zeros((n_sats, 6), dtype=bool)
        self._face_segments = self.rig.face_segments() if self.rig.kind == "faces" else None
        self._stereo_aims: dict[int, list[int]] = {}  # observer → targets measured in the latest step

    # -- helpers -------------------------------------------------------------------------------
    def _emit(self, topic: str, msg, log_ns: int) -> None:
        self.sink.emit(SceneMessage(topic, proto_spec(type(msg)), msg.SerializeToString(), log_ns))

    def truth_at(self, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(q_BI, r_H) of step k, if it is among the recent steps."""
        return self._truth.get(k)

    def topics(self) -> list[tuple[str, ChannelSpec]]:
        """Every channel this swarm's scene may use (the live server advertises them at once)."""
        su = proto_spec(SceneUpdate)
        out = [("/foxglove/tf", proto_spec(FrameTransforms)), ("/foxglove/truth", su), ("/foxglove/measurements", su),
               ("/foxglove/links", su), ("/foxglove/cameras", su), ("/foxglove/faults", proto_spec(Log))]
        out += [(f"/foxglove/est/{i}", su) for i in range(self.n)]
        out += [(f"/errors/{i}", ERRORS_SPEC) for i in range(self.n)]
        return out

    # -- the truth ----------------------------------------------------------------------------------
    def truth(self, k: int, t_s: float, q_BI: np.ndarray, r_H: np.ndarray, log_ns: int, draw: bool = True) -> None:
        """The true poses of step k: ``/foxglove/tf``, ``/foxglove/truth`` and (face cameras)
        ``/foxglove/cameras``. ``draw`` False: only remember them (every method takes it: the
        live view skips the steps it has no time to draw)."""
        q_BI = np.asarray(q_BI, dtype=float).reshape(-1, 4)
        r = np.asarray(r_H, dtype=float).reshape(-1, 3)
        self._truth[k] = (q_BI, r)
        self._truth.pop(k - _KEEP_TRUTH, None)
        if self._latest_k is None or k >= self._latest_k:
            self._latest_k = k
        if not draw:
            return
        want_tf, want_truth = self.sink.wants("/foxglove/tf"), self.sink.wants("/foxglove/truth")
        want_cams = self._face_segments is not None and self.sink.wants("/foxglove/cameras")
        if not (want_tf or want_truth or want_cams):
            return
        q = q_BH(q_BI, self.mean_motion, t_s)
        ts, n = _ts(log_ns), r.shape[0]
        rl, ql = r.tolist(), q.tolist()
        if want_tf:
            tfs = FrameTransforms(transforms=[
                FrameTransform(timestamp=ts, parent_frame_id="hcw", child_frame_id=f"sat{i}",
                               translation=Vector3(x=rl[i][0], y=rl[i][1], z=rl[i][2]),
                               rotation=Quaternion(x=ql[i][0], y=ql[i][1], z=ql[i][2], w=ql[i][3]))
                for i in range(n)])
            self._emit("/foxglove/tf", tfs, log_ns)
        if want_truth:
            size, white = Vector3(x=self.size, y=self.size, z=self.size), Color(r=1, g=1, b=1, a=1)
            meta = [KeyValuePair(key="k", value=str(k)), KeyValuePair(key="t_s", value=f"{t_s:.6g}")]
            ents = [
                SceneEntity(timestamp=ts, frame_id="hcw", id=f"sat{i}", lifetime=_FOREVER, frame_locked=False,
                            cubes=[CubePrimitive(pose=_pose(rl[i], ql[i]), size=size, color=_color(i))],
                            texts=[TextPrimitive(pose=_pose([rl[i][0], rl[i][1], rl[i][2] + self.size], _IDENTITY), billboard=True,
                                                 font_size=14, scale_invariant=True, color=white, text=f"sat {i}")],
                            metadata=meta)
                for i in range(n)
            ]
            self._emit("/foxglove/truth", SceneUpdate(entities=ents), log_ns)
        if want_cams:
            self._face_cameras(ts, n, log_ns)

    def _face_cameras(self, ts: Timestamp, n: int, log_ns: int) -> None:
        seg = self._face_segments
        assert seg is not None
        on_c, off_c = Color(r=0.55, g=0.85, b=1.0, a=0.45), Color(r=1.0, g=0.15, b=0.1, a=0.8)
        ents = []
        for i in range(n):
            off = self.camera_off[i] if i < self.camera_off.shape[0] else np.zeros(6, dtype=bool)
            lines = []
            for state, color in ((False, on_c), (True, off_c)):
                cams = np.nonzero(off == state)[0]
                if cams.size:
                    lines.append(LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(_ORIGIN, _IDENTITY), thickness=1.0,
                                               scale_invariant=True, points=_points(seg[cams]), color=color))
            meta = [KeyValuePair(key=f"cam{c}", value="off" if off[c] else "on") for c in range(6)]
            ents.append(SceneEntity(timestamp=ts, frame_id=f"sat{i}", id=f"cams{i}", lifetime=_FOREVER, frame_locked=True,
                                    lines=lines, metadata=meta))
        self._emit("/foxglove/cameras", SceneUpdate(entities=ents), log_ns)

    # -- estimates ----------------------------------------------------------------------------------
    def estimate(self, own: int, k: int, t_s: float, ids: Sequence[int] | np.ndarray, q_BI: np.ndarray, r_H: np.ndarray,
                 P_pose: np.ndarray, log_ns: int, draw: bool = True) -> None:
        """Filter ``own``'s posterior of step k over satellites ``ids``: ``/foxglove/est/<own>``
        (cubes and 3σ position ellipsoids) and ``/errors/<own>`` (against the truth of k,
        when it is known)."""
        topic, etopic = f"/foxglove/est/{own}", f"/errors/{own}"
        want_scene, want_err = draw and self.sink.wants(topic), draw and self.sink.wants(etopic)
        if not (want_scene or want_err):
            return
        q_BI = np.asarray(q_BI, dtype=float).reshape(-1, 4)
        r = np.asarray(r_H, dtype=float).reshape(-1, 3)
        P = np.asarray(P_pose, dtype=float).reshape(-1, 6, 6)
        ids_l = [int(s) for s in ids] if len(ids) else list(range(len(r)))
        if want_scene:
            self._estimate_scene(own, ids_l, t_s, q_BI, r, P, log_ns, topic)
        truth = self._truth.get(k)
        if want_err and truth is not None:
            self._errors(own, k, t_s, np.asarray(ids_l), q_BI, r, P, truth, log_ns, etopic)

    def _estimate_scene(self, own, ids, t_s, q_BI, r, P, log_ns, topic) -> None:
        q = q_BH(q_BI, self.mean_motion, t_s)
        # Every satellite's 3σ position ellipsoid at once (an agent's scene at n = 40 is 40
        # of them, 40 times a step): principal axes of the symmetrised position blocks.
        Pr = P[:, 3:, 3:]
        w, V = np.linalg.eigh(0.5 * (Pr + np.swapaxes(Pr, -1, -2)))
        axes = 2 * 3 * np.sqrt(np.clip(w, 0, None))  # 3σ ellipsoid diameters
        V[np.linalg.det(V) < 0, :, 0] *= -1  # proper rotations
        q_ell = quat.normalize(quat.from_attitude_matrix(np.swapaxes(V, -1, -2)))  # principal axes in H
        ts, size, cube_c, sph_c = _ts(log_ns), Vector3(x=self.size, y=self.size, z=self.size), _color(own, 0.35), _color(own, 0.25)
        rl, ql, q_ell_l, axes_l = r.tolist(), q.tolist(), q_ell.tolist(), axes.tolist()  # Python floats build messages faster
        ents = [
            SceneEntity(
                timestamp=ts,
                frame_id="hcw",
                id=f"est{own}-sat{sat}",
                lifetime=_FOREVER,
                cubes=[CubePrimitive(pose=_pose(rl[j], ql[j]), size=size, color=cube_c)],
                spheres=[SpherePrimitive(pose=_pose(rl[j], q_ell_l[j]), size=Vector3(x=axes_l[j][0], y=axes_l[j][1], z=axes_l[j][2]),
                                         color=sph_c)],
            )
            for j, sat in enumerate(ids)
        ]
        # An estimator that tracks only some satellites: take away those it no longer does.
        gone = self._shown.get(own, set()) - set(ids)
        self._shown[own] = set(ids)
        dels = [SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletion.MATCHING_ID, id=f"est{own}-sat{s}") for s in sorted(gone)]
        self._emit(topic, SceneUpdate(deletions=dels, entities=ents), log_ns)

    def _errors(self, own, k, t_s, ids, q_BI, r, P, truth, log_ns, topic) -> None:
        q_true, r_true = truth
        if ids.max(initial=-1) >= q_true.shape[0]:
            return
        a, dr = pose_errors(q_BI, r, q_true[ids], r_true[ids])
        att = np.degrees(np.linalg.norm(a, axis=-1))
        pos = np.linalg.norm(dr, axis=-1)
        with np.errstate(all="ignore"):
            try:
                nees = pose_nees(a, dr, P)
            except np.linalg.LinAlgError:
                nees = np.full(len(ids), np.nan)
        att3 = 3 * np.degrees(np.sqrt(np.clip(np.trace(P[:, :3, :3], axis1=-2, axis2=-1), 0, None)))
        pos3 = 3 * np.sqrt(np.clip(np.trace(P[:, 3:, 3:], axis1=-2, axis2=-1), 0, None))
        n = max(self.n, int(ids.max(initial=-1)) + 1)

        def full(x) -> list[float]:
            out = np.full(n, np.nan)
            out[ids] = x
            return out.tolist()

        own_row = np.nonzero(ids == own)[0]
        o = int(own_row[0]) if own_row.size else None
        others = ids != own
        nan = math.nan
        msg = FilterErrors(
            k=int(k), t_s=float(t_s), own=int(own),
            own_att_err_deg=nan if o is None else float(att[o]),
            own_pos_err_m=nan if o is None else float(pos[o]),
            own_att_3sigma_deg=nan if o is None else float(att3[o]),
            own_pos_3sigma_m=nan if o is None else float(pos3[o]),
            own_nees=nan if o is None else float(nees[o]),
            others_att_err_rms_deg=float(np.sqrt(np.mean(att[others] ** 2))) if others.any() else nan,
            others_pos_err_rms_m=float(np.sqrt(np.mean(pos[others] ** 2))) if others.any() else nan,
            nees_mean=float(np.mean(nees)) if nees.size else nan,
            att_err_deg=full(att), pos_err_m=full(pos), att_3sigma_deg=full(att3), pos_3sigma_m=full(pos3), nees=full(nees),
        )
        self.sink.emit(SceneMessage(topic, ERRORS_SPEC, msg.SerializeToString(), log_ns))

    # -- measurements and links -----------------------------------------------------------------
    def measurements(self, observer: int, k: int, targets: Sequence[int], log_ns: int, draw: bool = True) -> None:
        """Observer's relative measurements of step k: a line per target on
        ``/foxglove/measurements`` (between the true positions), and with the stereo camera
        its aim on ``/foxglove/cameras``."""
        truth = self._truth.get(k) or (self._truth.get(self._latest_k) if self._latest_k is not None else None)
        if truth is None or not draw:
            return
        r = truth[1]
        targets = [int(t) for t in targets if 0 <= int(t) < r.shape[0]]
        if not 0 <= observer < r.shape[0]:
            return
        ts = _ts(log_ns)
        if self.sink.wants("/foxglove/measurements"):
            lines = [
                LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(_ORIGIN, _IDENTITY), thickness=2.0, scale_invariant=True,
                              points=_points([r[observer], r[t]]), color=_color(observer, 0.8))
                for t in targets
            ]
            ent = SceneEntity(timestamp=ts, frame_id="hcw", id=f"meas{observer}", lifetime=_FOREVER, lines=lines)
            self._emit("/foxglove/measurements", SceneUpdate(entities=[ent]), log_ns)
        if self.rig.kind == "stereo" and self.sink.wants("/foxglove/cameras"):
            self._stereo_aim(observer, targets, r, ts, log_ns)

    def _stereo_aim(self, observer: int, targets: list[int], r: np.ndarray, ts: Timestamp, log_ns: int) -> None:
        """The tracking stereo camera aimed along the true line of sight at each target it
        measured: a frustum from the observer reaching the target."""
        tx, ty = math.tan(math.radians(self.rig.hfov_deg) / 2), math.tan(math.radians(self.rig.vfov_deg) / 2)
        segs = []
        for t in targets:
            z = r[t] - r[observer]
            rng = float(np.linalg.norm(z))
            if rng <= 0:
                continue
            z = z / rng
            x = np.cross([0.0, 0.0, 1.0], z)
            if np.linalg.norm(x) < 1e-9:
                x = np.array([1.0, 0.0, 0.0])
            x = x / np.linalg.norm(x)
            y = np.cross(z, x)
            apex = r[observer]
            far = [apex + rng * (z + sx * tx * x + sy * ty * y) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            for e in range(4):
                segs += [apex, far[e], far[e], far[(e + 1) % 4]]
        lines = [LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(_ORIGIN, _IDENTITY), thickness=1.0, scale_invariant=True,
                               points=_points(segs), color=_color(observer, 0.5))] if segs else []
        ent = SceneEntity(timestamp=ts, frame_id="hcw", id=f"cams{observer}", lifetime=_FOREVER, lines=lines,
                          metadata=[KeyValuePair(key="aimed_at", value=",".join(map(str, targets)))])
        self._emit("/foxglove/cameras", SceneUpdate(entities=[ent]), log_ns)

    def links(self, k: int, counters: dict[str, Any], log_ns: int, draw: bool = True) -> None:
        """The radio of step k from the cumulative per-link counters (``LinkStats`` or
        ``LinkCounters``): one entity ``links`` on ``/foxglove/links``, a LINE_LIST per state,
        each directed link i → j from r_i to the midpoint of i and j, and the state of every
        link with traffic as metadata (``"i->j": state``)."""
        cur = {c: np.rint(np.asarray(counters[c], dtype=float)).astype(np.int64) for c in LINK_COUNTERS}
        states = link_states(self._link_prev, cur)
        self._link_prev = cur
        if not draw or not self.sink.wants("/foxglove/links"):
            return
        truth = self._truth.get(k) or (self._truth.get(self._latest_k) if self._latest_k is not None else None)
        if truth is None or truth[1].shape[0] != states.shape[0]:
            return
        r = truth[1]
        lines, meta = [], []
        for code, (name, (cr, cg, cb)) in enumerate(LINK_STATES):
            ii, jj = np.nonzero(states == code)
            if not ii.size:
                continue
            pts = []
            for i, j in zip(ii.tolist(), jj.tolist()):
                pts += [r[i], 0.5 * (r[i] + r[j])]
                meta.append(KeyValuePair(key=f"{i}->{j}", value=name))
            lines.append(LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(_ORIGIN, _IDENTITY), thickness=3.0,
                                       scale_invariant=True, points=_points(pts), color=Color(r=cr, g=cg, b=cb, a=0.9)))
        ent = SceneEntity(timestamp=_ts(log_ns), frame_id="hcw", id="links", lifetime=_FOREVER, lines=lines,
                          metadata=sorted(meta, key=lambda kv: tuple(int(x) for x in kv.key.split("->"))))
        self._emit("/foxglove/links", SceneUpdate(entities=[ent]), log_ns)

    # -- faults ---------------------------------------------------------------------------------------
    def fault(self, k: int, t_s: float, action: str, phase: str, sender: str, log_ns: int, target: int | None = None,
              camera: int | None = None, state: str | None = None, detail: str = "") -> None:
        """A fault command or report: a ``foxglove.Log`` on ``/foxglove/faults``; a camera
        turned off or on changes its frustum's colour from the next step."""
        if action == "camera" and phase == "done" and target is not None and camera is not None and 0 <= target < self.n \
                and 0 <= camera < 6:
            self.camera_off[target, camera] = state == "off"
        if not self.sink.wants("/foxglove/faults"):
            return
        what = action + ("" if target is None else f" {target}") + ("" if camera is None else f" camera {camera}") + \
            ("" if state is None else f" {state}")
        text = f"step {k} (t = {t_s:g} s): {what}: {phase}" + (f" ({detail})" if detail else "")
        msg = Log(timestamp=_ts(log_ns), level=_LOG_LEVELS.get(phase, Log.INFO), message=text, name=sender or "?",
                  file=f"fault/{sender}", line=int(k))
        self._emit("/foxglove/faults", msg, log_ns)


def scene_topics(n_sats: int) -> list[str]:
    """The topics of a swarm of ``n_sats`` satellites' scene (images left out)."""
    return [t for t, _ in SceneBuilder(_NullSink(), n_sats, 0.0).topics()]


class _NullSink:
    def wants(self, topic: str) -> bool:
        return False

    def emit(self, msg: SceneMessage) -> None:
        pass
