"""Every message on the bus and every key expression, in one place.

Messages are JSON (readable in Foxglove and MCAP tools), validated by pydantic models:
a malformed or unexpected payload raises :class:`MessageError` naming the problem, and
the receiving process counts it, logs it and carries on. Small vectors are JSON lists
(exact: Python writes the shortest repr that round-trips); large matrices travel as
little-endian float64 in base64 (:class:`B64Array`), also exact. Every message carries
the schema version ``v``, the run id, the sender, the step ``k`` and the simulation time
``t_s``. Units and frames are in every field name.

Key space (one run id per swarm, so swarms can share a router)::

    swarm/<run>/clock                world → all           Clock
    swarm/<run>/sat/<i>/sensors      world → agent i       Sensors
    swarm/<run>/sat/<i>/cam          world → agent i       CameraOutput
    swarm/<run>/sat/<i>/img          world → agent i       Images  (rendered; JSON header + raw pixels)
    swarm/<run>/meas/<i>             agent i → all         MeasBatch
    swarm/<run>/est/<i>              agent i → all         Estimate
    swarm/<run>/cov/<i>              agent i (queryable)   FullEstimate
    swarm/<run>/init/<i>             world (queryable)     FullEstimate (the prior)
    swarm/<run>/claim/<token>        world (queryable)     Claim (a satellite id for --id auto)
    swarm/<run>/select               selector → all        Select
    swarm/<run>/fault                CLI / roles → all     Fault
    swarm/<run>/health/<i>           agent i → all         Health
    swarm/<run>/truth                world → recorder      Truth   (agents never subscribe)
    swarm/<run>/rx/<i>               world → agent i       Delivery (links.enabled: what the radio delivered)
    swarm/<run>/links                world → recorder      LinkStats (links.enabled: per-link counters)
    swarm/<run>/rejoin/<i>[/<j>/<B>] world (queryable)     RejoinFate (links.enabled: a restart's state transfer)
    swarm/<run>/alive/<role>/<id>    liveliness tokens
"""

from __future__ import annotations

import base64
import re
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from swarmcore.scenario import FaultAction

from ..netem import NetemError, validate_field

SCHEMA_VERSION = 1

__all__ = [
    "SCHEMA_VERSION",
    "MessageError",
    "B64Array",
    "Clock",
    "Sensors",
    "Detection",
    "CameraOutput",
    "RelMeas",
    "MeasBatch",
    "Estimate",
    "FullEstimate",
    "Select",
    "Fault",
    "Health",
    "Truth",
    "Claim",
    "Delivery",
    "Delivered",
    "LinkStats",
    "RejoinFate",
    "Images",
    "ViewMeta",
    "Keys",
    "MODELS",
    "encode",
    "decode",
    "parse_key",
]


class MessageError(ValueError):
    """A payload that is not a valid message of the expected kind."""


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vec4 = Annotated[list[float], Field(min_length=4, max_length=4)]
SatId = Annotated[int, Field(ge=0, le=10_000)]


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class B64Array(_Msg):
    """A float64 array: little-endian bytes in base64, with its shape."""

    dtype: Literal["<f8"] = "<f8"
    shape: list[Annotated[int, Field(ge=0)]]
    b64: str

    @classmethod
    def of(cls, a: np.ndarray) -> "B64Array":
        a = np.ascontiguousarray(a, dtype="<f8")
        return cls(shape=list(a.shape), b64=base64.b64encode(a.tobytes()).decode("ascii"))

    def array(self) -> np.ndarray:
        try:
            raw = base64.b64decode(self.b64, validate=True)
        except ValueError as exc:
            raise MessageError(f"array payload is not base64: {exc}") from None
        count = int(np.prod(self.shape)) if self.shape else 1
        if len(raw) != 8 * count:
            raise MessageError(f"array of shape {self.shape} needs {8 * count} bytes, got {len(raw)}")
        return np.frombuffer(raw, dtype="<f8").reshape(self.shape).copy()


class _Header(_Msg):
    v: Literal[1] = SCHEMA_VERSION
    run: str = Field(min_length=1, max_length=64)
    sender: str = Field(min_length=1, max_length=64)
    k: int = Field(ge=0, description="step index")
    t_s: float = Field(description="simulation time (s)")


class Clock(_Header):
    """World → all: step k begins; who is alive; the run's mode."""

    kind: Literal["clock"] = "clock"
    live_agents: list[SatId]
    mode: Literal["lockstep", "free"] = "lockstep"
    done: bool = False


class Sensors(_Header):
    """World → agent i: its own gyro (mean rate over k−1→k), star tracker and GPS at t_k."""

    kind: Literal["sensors"] = "sensors"
    sat: SatId
    gyro_rate_B_rad_s: Vec3 | None = None
    q_BI_star: Vec4 | None = None
    r_H_gps_m: Vec3 | None = None
    sigma_star_rad: float = Field(gt=0)
    sigma_gps_m: float = Field(gt=0)


class Detection(_Msg):
    """One camera output: a (synthetic or image-derived) relative pose of ``target``."""

    target: SatId
    camera: int = Field(ge=0, le=5)
    q_BjBi: Vec4
    r_ij_Bi_m: Vec3


class CameraOutput(_Header):
    """World → agent i: what its cameras produced at step k (possibly nothing)."""

    kind: Literal["cam"] = "cam"
    sat: SatId
    detections: list[Detection] = []
    cameras_off: list[Annotated[int, Field(ge=0, le=5)]] = []


class RelMeas(_Msg):
    """A relative pose measurement with its covariance R_Bi (6×6 row-major, [att rad, pos m]).

    ``camera``: 0–5 the body-fixed face cameras; 6 + j the tracking stereo pair aimed at j."""

    observer: SatId
    target: SatId
    camera: int = Field(ge=0, le=6 + 10_000)
    q_BjBi: Vec4
    r_ij_Bi_m: Vec3
    R_Bi: Annotated[list[float], Field(min_length=36, max_length=36)]


class MeasBatch(_Header):
    """Agent i → all: every relative measurement it took at step k (an empty batch too)."""

    kind: Literal["meas"] = "meas"
    observer: SatId
    meas: list[RelMeas] = []

    @field_validator("meas")
    @classmethod
    def _same_observer(cls, v, info):
        obs = info.data.get("observer")
        for m in v:
            if m.observer != obs:
                raise ValueError(f"measurement by {m.observer} in the batch of observer {obs}")
            if m.target == m.observer:
                raise ValueError(f"satellite {m.observer} cannot measure itself")
        return v


class Estimate(_Header):
    """Agent i → all: its posterior (or initial prior) of the whole swarm at step k.

    Carries each satellite's pose covariance block ``P_pose`` (n, 6, 6) over
    ``[a, Δr]`` and the full diagonal; the full covariance is served on ``cov/<i>``.
    """

    kind: Literal["est"] = "est"
    own: SatId
    phase: Literal["prior", "posterior"] = "posterior"
    q_BI: list[Vec4]
    omega_BI_B_rad_s: list[Vec3]
    r_H_m: list[Vec3]
    v_H_m_s: list[Vec3]
    bias_B_rad_s: Vec3
    P_pose: B64Array
    P_diag: B64Array
    gate_accepted: int = 0
    gate_rejected: int = 0
    nis: float = 0.0
    nis_dof: int = 0
    iterations: int = 1
    step_ms: float = 0.0
    batches_used: list[SatId] = []
    batches_missing: list[SatId] = []
    batches_late: int = 0
    late_used: int = Field(0, ge=0, description="late measurements inserted at their own step (replay)")
    late_dropped: int = Field(0, ge=0, description="late measurements dropped (older than the history, or late: drop)")
    replayed_steps: int = Field(0, ge=0, description="filter steps re-run for late measurements")


class FullEstimate(_Header):
    """A complete filter state with the full 12n×12n covariance (prior, restart, selector)."""

    kind: Literal["full_est"] = "full_est"
    own: SatId
    q_BI: list[Vec4]
    omega_BI_B_rad_s: list[Vec3]
    r_H_m: list[Vec3]
    v_H_m_s: list[Vec3]
    bias_B_rad_s: Vec3
    P: B64Array


class Select(_Header):
    """Selector (or the world's fallback) → all: the pairs to measure at step k."""

    kind: Literal["select"] = "select"
    pairs: list[tuple[SatId, SatId]]
    strategy: str
    ref_agent: SatId | None = None
    fallback: bool = False
    select_ms: float = 0.0


class Fault(_Header):
    """A fault: a command (from the CLI or the scenario) and its outcome (from the executor)."""

    kind: Literal["fault"] = "fault"
    action: FaultAction
    phase: Literal["command", "done", "failed"] = "command"
    target: SatId | None = None
    camera: int | None = Field(None, ge=0, le=5)
    state: Literal["on", "off"] | None = None
    rate: float | None = Field(None, ge=0.0, le=1.0)
    netem: str | None = Field(
        None, max_length=200, description="netem: the tc netem arguments applied to the target's container "
        "('delay 200ms 50ms loss 10% rate 1mbit', canonical form) or 'clear'"
    )
    detail: str = ""

    @field_validator("netem")
    @classmethod
    def _netem_args(cls, v):
        if v is None:
            return v
        try:
            return validate_field(v)
        except NetemError as exc:
            raise ValueError(str(exc)) from None

    @model_validator(mode="after")
    def _netem_needs_args(self):
        if self.action == "netem" and self.netem is None:
            raise ValueError("action netem needs netem (tc netem arguments or 'clear')")
        return self


class Health(_Header):
    """Agent i → all: camera health and what it has had to cope with."""

    kind: Literal["health"] = "health"
    sat: SatId
    camera_ok: Annotated[list[bool], Field(min_length=6, max_length=6)]
    malformed: int = 0
    batches_missing: int = 0
    batches_late: int = 0
    drop_rate: float = 0.0
    host: str = Field("", max_length=253, description="the agent's host name (its container id under Docker)")


class Delivered(_Msg):
    """One batch the radio delivered: when it arrived (simulated time) and the batch itself."""

    arrival_t_s: float
    batch: MeasBatch


class Delivery(_Header):
    """World (the radio channel) → agent i: the peer batches that reached it by step k
    (``links.enabled``); ``batch.k < k`` marks a late one."""

    kind: Literal["rx"] = "rx"
    sat: SatId
    items: list[Delivered] = []


class LinkStats(_Header):
    """World → recorder: the link counters (cumulative, per directed link, n × n, row =
    sender) after step k, each transmitter's queue, and this step's delivered latencies."""

    kind: Literal["links"] = "links"
    sent: B64Array
    delivered: B64Array
    delivered_late: B64Array
    lost: B64Array
    dropped_queue: B64Array
    unreachable: B64Array
    bytes_delivered: B64Array
    queue_bytes: list[Annotated[int, Field(ge=0)]]
    latencies: list[tuple[SatId, SatId, Annotated[int, Field(ge=0)], float]] = Field(
        default_factory=list, description="(sender, receiver, sent step, latency s) of each delivery of this step"
    )


class RejoinFate(_Header):
    """World (the radio) → a restarting agent: what the link does to the full estimate it
    fetches from ``peer`` (``links.enabled``): it arrives at ``arrival_t_s`` (simulated
    time), or it is ``lost``, ``dropped`` at the peer's queue, or the link is
    ``unreachable``. The transfer takes the peer's transmitter like any message."""

    kind: Literal["rejoin"] = "rejoin"
    sat: SatId
    peer: SatId
    bytes: int = Field(ge=0)
    fate: Literal["delivered", "lost", "dropped", "unreachable"]
    arrival_t_s: float | None = None


class Claim(_Header):
    """World → an agent started with ``--id auto``: the satellite it is to fly, and whether
    the run is already under way (then it initialises from a live peer)."""

    kind: Literal["claim"] = "claim"
    sat: SatId
    token: str = Field(min_length=1, max_length=128)
    running: bool = False


class Truth(_Header):
    """World → recorder only: the true state at step k."""

    kind: Literal["truth"] = "truth"
    q_BI: list[Vec4]
    omega_BI_B_rad_s: list[Vec3]
    r_H_m: list[Vec3]
    v_H_m_s: list[Vec3]
    gyro_bias_B_rad_s: list[Vec3]


class ViewMeta(_Msg):
    """One camera's view inside :class:`Images`: where the camera is and how it projects."""

    camera: int = Field(ge=0, description="0–5 face cameras; 6 + j the stereo pair tracking j")
    T_CB: Annotated[list[float], Field(min_length=9, max_length=9)] = Field(description="body → camera (OpenCV axes), row-major")
    r_C_B_m: Vec3 = Field(description="(left) camera centre in the body frame")
    width_px: int = Field(ge=1, le=16384)
    height_px: int = Field(ge=1, le=16384)
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    target: int = Field(-1, ge=-1, description="stereo: the tracked satellite; −1 for face cameras")
    baseline_m: float = Field(0.0, ge=0.0)
    n_images: int = Field(1, ge=1, le=2, description="1 (face camera) or 2 (stereo left, right)")


class Images(_Header):
    """World → agent i: the images its scheduled cameras saw at step k (possibly none).

    On the wire: this JSON header, one newline, then the raw 8-bit grey pixels of every
    view's images in order (``height_px × width_px`` bytes each): images are too large for
    JSON and base64 and need no conversion. :func:`decode` checks the byte count.
    ``targets``: the satellites this observer is scheduled to measure."""

    kind: Literal["img"] = "img"
    sat: SatId
    targets: list[SatId] = []
    views: list[ViewMeta] = []
    _pixels: list = PrivateAttr(default_factory=list)

    def pixel_shapes(self) -> list[tuple[int, int]]:
        """(height, width) of every image the views announce, in wire order."""
        return [(v.height_px, v.width_px) for v in self.views for _ in range(v.n_images)]

    def with_pixels(self, pixels: list) -> "Images":
        want = self.pixel_shapes()
        got = [tuple(np.shape(p)) for p in pixels]
        if got != want:
            raise MessageError(f"images: pixel arrays of shapes {got} do not match the views' {want}")
        self._pixels = [np.ascontiguousarray(p, dtype=np.uint8) for p in pixels]
        return self

    @property
    def pixels(self) -> list:
        """Every view's images, flattened in view order (uint8 arrays, height × width)."""
        return self._pixels

    def __eq__(self, other) -> bool:
        if not isinstance(other, Images):
            return NotImplemented
        return self.header_json() == other.header_json() and len(self.pixels) == len(other.pixels) and all(
            np.array_equal(a, b) for a, b in zip(self.pixels, other.pixels)
        )

    __hash__ = None

    def header_json(self) -> bytes:
        return self.model_dump_json().encode("utf-8")


MODELS: dict[str, type[_Header]] = {
    "clock": Clock,
    "sensors": Sensors,
    "cam": CameraOutput,
    "meas": MeasBatch,
    "est": Estimate,
    "full_est": FullEstimate,
    "select": Select,
    "fault": Fault,
    "health": Health,
    "truth": Truth,
    "claim": Claim,
    "img": Images,
    "rx": Delivery,
    "links": LinkStats,
    "rejoin": RejoinFate,
}


def encode(msg: _Header) -> bytes:
    if isinstance(msg, Images):
        return msg.header_json() + b"\n" + b"".join(p.tobytes() for p in msg.pixels)
    return msg.model_dump_json().encode("utf-8")


def decode(kind: str, payload: bytes | bytearray | memoryview):
    """Parse and validate a payload of the given kind; :class:`MessageError` on any defect."""
    model = MODELS.get(kind)
    if model is None:
        raise MessageError(f"unknown message kind {kind!r}")
    payload = bytes(payload)
    body = None
    if model is Images:
        payload, nl, body = payload.partition(b"\n")
        if not nl:
            raise MessageError("invalid img message: no newline between the JSON header and the pixels")
    try:
        msg = model.model_validate_json(payload)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(p) for p in first["loc"]) or "(payload)"
        raise MessageError(f"invalid {kind} message: {loc}: {first['msg']} ({exc.error_count()} error(s))") from None
    if body is not None:
        shapes = msg.pixel_shapes()
        need = sum(h * w for h, w in shapes)
        if len(body) != need:
            raise MessageError(f"invalid img message: {len(shapes)} image(s) need {need} pixel bytes, got {len(body)}")
        pix, off = [], 0
        for h, w in shapes:
            # A copy, not a view into the payload: writeable and aligned like any new array.
            pix.append(np.frombuffer(body, dtype=np.uint8, count=h * w, offset=off).reshape(h, w).copy())
            off += h * w
        msg.with_pixels(pix)
    return msg


_RUN_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class Keys:
    """Key expressions of one run."""

    def __init__(self, run: str):
        if not _RUN_RE.match(run):
            raise ValueError(f"run id {run!r}: use 1-64 letters, digits, '_', '-' or '.'")
        self.run = run
        self.root = f"swarm/{run}"

    def clock(self) -> str:
        return f"{self.root}/clock"

    def sensors(self, i: int) -> str:
        return f"{self.root}/sat/{i}/sensors"

    def cam(self, i: int) -> str:
        return f"{self.root}/sat/{i}/cam"

    def img(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/img"

    def meas(self, i: int | str = "*") -> str:
        return f"{self.root}/meas/{i}"

    def est(self, i: int | str = "*") -> str:
        return f"{self.root}/est/{i}"

    def cov(self, i: int | str = "*") -> str:
        return f"{self.root}/cov/{i}"

    def init(self, i: int | str = "*") -> str:
        return f"{self.root}/init/{i}"

    def select(self) -> str:
        return f"{self.root}/select"

    def fault(self) -> str:
        return f"{self.root}/fault"

    def health(self, i: int | str = "*") -> str:
        return f"{self.root}/health/{i}"

    def truth(self) -> str:
        return f"{self.root}/truth"

    def rx(self, i: int | str = "*") -> str:
        return f"{self.root}/rx/{i}"

    def links(self) -> str:
        return f"{self.root}/links"

    def rejoin(self, i: int | str = "*", peer: int | str | None = None, size: int | None = None) -> str:
        """``rejoin/<i>``: the fates the world gives agent i's rejoin transfers (recorded);
        ``rejoin/<i>/<peer>/<bytes>``: agent i's question about one (a query)."""
        tail = "" if peer is None else f"/{peer}/{size}"
        return f"{self.root}/rejoin/{i}{tail}"

    def claim(self, token: str = "*") -> str:
        return f"{self.root}/claim/{token}"

    def alive(self, role: str = "*", ident: int | str = "*") -> str:
        return f"{self.root}/alive/{role}/{ident}"

    def everything(self) -> str:
        return f"{self.root}/**"


_KEY_RE = re.compile(
    r"^swarm/(?P<run>[^/]+)/(?:"
    r"(?P<clock>clock)|(?P<select>select)|(?P<fault>fault)|(?P<truth>truth)|(?P<links>links)"
    r"|sat/(?P<sat>\d+)/(?P<satkind>sensors|cam|img)"
    r"|(?P<idkind>meas|est|health|cov|init|rx|rejoin)/(?P<id>\d+)(?:/\d+/\d+)?"
    r"|alive/(?P<role>[^/]+)/(?P<ident>[^/]+))$"
)


def parse_key(key: str) -> tuple[str, str, int | None]:
    """``(run, kind, satellite id or None)`` of a key; :class:`MessageError` if unknown."""
    m = _KEY_RE.match(str(key))
    if not m:
        raise MessageError(f"unexpected key {key!r}")
    run = m["run"]
    for k in ("clock", "select", "fault", "truth", "links"):
        if m[k]:
            return run, k, None
    if m["satkind"]:
        return run, m["satkind"], int(m["sat"])
    if m["idkind"]:
        kind = {"cov": "full_est", "init": "full_est"}.get(m["idkind"], m["idkind"])
        return run, kind, int(m["id"])
    ident = m["ident"]
    return run, "alive", int(ident) if ident.isdigit() else None
