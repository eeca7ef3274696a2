"""Typed, validated scenario model: the only place defaults live.

Defaults follow the dissertation's Table 4.1 (LEO, ~622 km). Pure: no file I/O here;
:mod:`swarm.scenario_files` loads YAML and applies ``--set`` overrides.
"""

from __future__ import annotations

from typing import Annotated, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from scipy.special import gammaincinv

from .vision_config import VisionConfig

PosFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class Orbit(_Model):
    mean_motion_rad_s: PosFloat = Field(1.08e-3, description="HCW mean motion n (1/s); 622 km LEO")


class Spacecraft(_Model):
    inertia_kg_m2: list[float] | list[list[float]] = Field(
        [1.67, 5.0, 3.67],
        description="principal moments [Jx, Jy, Jz] or a full 3×3 tensor (kg m²). Default: Table 4.1 "
        "with Jy lowered from 8.33 to 5.0 so a rigid body can have it; the dissertation's own "
        "values need allow_nonphysical_inertia",
    )
    allow_nonphysical_inertia: bool = Field(
        False,
        description="accept an inertia whose principal moments break the triangle inequality "
        "(the dissertation's 8.33 > 1.67 + 3.67 does); only to reproduce its numbers",
    )
    half_size_m: PosFloat = Field(0.2, description="half the cube side (40 cm cube satellites)")

    @field_validator("inertia_kg_m2")
    @classmethod
    def _shape(cls, v):
        arr = np.asarray(v, dtype=float)
        if arr.shape not in ((3,), (3, 3)):
            raise ValueError(f"must be 3 principal moments or a 3×3 matrix, got shape {arr.shape}")
        if arr.shape == (3, 3) and not np.allclose(arr, arr.T):
            raise ValueError("inertia tensor must be symmetric")
        return v

    def J(self) -> np.ndarray:
        arr = np.asarray(self.inertia_kg_m2, dtype=float)
        return np.diag(arr) if arr.shape == (3,) else arr

    @model_validator(mode="after")
    def _physical(self):
        J = self.J()
        moments = np.linalg.eigvalsh(J)
        if np.any(moments <= 0):
            raise ValueError(f"inertia_kg_m2: principal moments must be positive, got {moments.round(4).tolist()}")
        a, b, c = sorted(moments)
        if c > a + b + 1e-12 and not self.allow_nonphysical_inertia:
            raise ValueError(
                f"inertia_kg_m2: principal moments {[round(x, 4) for x in moments]} break the triangle "
                f"inequality ({c:.4g} > {a:.4g} + {b:.4g}); no rigid body has this inertia. Set "
                "spacecraft.allow_nonphysical_inertia: true to use it anyway (the dissertation's "
                "Table 4.1 values need this)"
            )
        return self


class Initial(_Model):
    position_max_m: NonNegFloat = Field(10.0, description="truth positions uniform in ±this per H axis")
    velocity_max_m_s: NonNegFloat = Field(0.005, description="truth velocities uniform in ±this per axis")
    rate_max_rad_s: NonNegFloat = Field(0.006, description="truth body rates uniform in ±this per axis")
    drift_free: bool = Field(False, description="set v_y = −2 n x so no satellite drifts along-track")
    attitude: Literal["random", "identity"] = "random"
    min_separation_m: NonNegFloat = Field(1.0, description="redraw positions closer than this")


class Disturbances(_Model):
    """Truth disturbances, also the filter's matching process noise."""

    torque: bool = Field(True, description="white torque disturbance in the truth")
    force: bool = Field(True, description="white force (acceleration) disturbance in the truth")
    torque_sigma_Nm_sqrt_s: NonNegFloat = Field(5e-6, description="σ_t: torque noise density")
    accel_sigma_m_s15: NonNegFloat = Field(1e-8, description="σ_f: acceleration noise density (m/s^1.5)")


class Gyro(_Model):
    arw_rad_sqrt_s: NonNegFloat = Field(3.16e-7, description="σ_v: angle random walk (rad/√s)")
    rrw_rad_s15: NonNegFloat = Field(3.16e-10, description="σ_u: rate (bias) random walk (rad/s^1.5)")
    bias_initial_sigma_rad_s: NonNegFloat = Field(1e-5, description="σ of each truth bias at t = 0")
    bias_walk: bool = Field(True, description="let the truth bias random-walk")


class StarTracker(_Model):
    enabled: bool = True
    sigma_rad: PosFloat = Field(2.9e-5, description="σ_star per axis")


class GPS(_Model):
    enabled: bool = True
    sigma_m: PosFloat = Field(0.01, description="σ_gps per H axis")


class Relative(_Model):
    """Synthetic relative pose measurements (chapter 4 isotropic, or chapter 6 camera-frame)."""

    model: Literal["isotropic", "camera"] = Field("isotropic", description="noise model")
    sigma_att_rad: PosFloat = Field(0.03, description="σ_q: isotropic relative attitude noise")
    sigma_pos_m: PosFloat = Field(0.01, description="σ_p: isotropic relative position noise")
    sigma_pos_camera_m: list[PosFloat] = Field(
        [0.25, 0.25, 0.12], description="camera model: position σ along camera x, y, z at the reference range"
    )
    sigma_att_camera_rad: list[PosFloat] = Field(
        [0.03, 0.03, 0.03], description="camera model: attitude σ about camera x, y, z at the reference range"
    )
    range_exponent: NonNegFloat = Field(
        2.0, description="camera model: σ grows as (range / reference_range_m) ** range_exponent"
    )
    reference_range_m: PosFloat = Field(10.0, description="camera model: range at which σ is as given")

    @field_validator("sigma_pos_camera_m", "sigma_att_camera_rad")
    @classmethod
    def _three(cls, v):
        if len(v) != 3:
            raise ValueError(f"needs 3 values (camera x, y, z), got {len(v)}")
        return v


class Sensors(_Model):
    gyro: Gyro = Gyro()
    star_tracker: StarTracker = StarTracker()
    gps: GPS = GPS()
    relative: Relative = Relative()


class Graph(_Model):
    """Which relative measurements exist (G(i, j) = 1: i measures j); diagonal = absolute."""

    kind: Literal["complete", "star", "chain", "duplex_chain", "matrix"] = "complete"
    landmark: int = Field(0, ge=0, description="star: the satellite every other one measures")
    matrix: list[list[int]] | None = Field(None, description="matrix: explicit n×n incidence (0/1)")
    absolute: Literal["all", "none"] | list[int] = Field(
        "all", description="satellites with star tracker + GPS (for kind=matrix the diagonal decides)"
    )


class Gate(_Model):
    enabled: bool = True
    probability: float = Field(0.999, gt=0.5, lt=1.0, description="χ²(6) quantile of the threshold")

    def threshold(self) -> float | None:
        """The χ²(6) quantile: ``2 · gammaincinv(3, p)``, exactly what ``scipy.stats.chi2.ppf``
        computes (importing scipy.stats would cost every process ~1 s of start-up)."""
        return float(2 * gammaincinv(6 / 2, self.probability)) if self.enabled else None


class InitialSigma(_Model):
    """Each filter's initial 1-σ uncertainty; its initial estimate is drawn from it.

    Larger priors are accepted, but an EKF linearised about a poor prior is overconfident
    at first: the iterated update (``filter.max_iterations``) repairs the first update on
    well-connected graphs; on sparse ones (a chain) far satellites stay overconfident for
    tens of steps when the attitude prior is worse than ~0.02 rad.
    """

    att_rad: PosFloat = 0.01
    rate_rad_s: PosFloat = 0.001
    bias_rad_s: PosFloat = 1e-5
    pos_m: PosFloat = 0.1
    vel_m_s: PosFloat = 0.001


class Filter(_Model):
    mode: Literal["cooperative", "isolated"] = Field(
        "cooperative", description="cooperative: every filter uses every broadcast relative "
        "measurement; isolated: only its own"
    )
    update: Literal["auto", "information", "sequential", "stacked"] = "auto"
    gate: Gate = Gate()
    initial_sigma: InitialSigma = InitialSigma()
    att_rw_other_rad_sqrt_s: NonNegFloat = Field(
        5e-4, description="filter-only attitude random walk on other satellites (Table 4.1 'quaternion process noise')"
    )
    pos_rw_m_sqrt_s: NonNegFloat = Field(
        5e-5, description="filter-only position random walk (Table 4.1 'position process noise')"
    )
    max_iterations: int = Field(
        3, ge=1, le=20, description="iterated-EKF passes at most (1: the plain MEKF of the dissertation)"
    )
    iterate_above_rad: NonNegFloat = Field(
        0.01, description="iterate only when the first pass turns some attitude by more than this"
    )
    rk4_substeps: int = Field(1, ge=1, le=100, description="RK4 steps per dt for the others' attitude")
    late: Literal["replay", "drop"] = Field(
        "replay", description="a relative measurement older than the current step (delivered late by the "
        "links): replay inserts it at its own step and re-runs the filter from there; drop discards it"
    )
    history_s: NonNegFloat = Field(
        10.0, description="replay: how far back (s) each agent keeps its priors, inputs and measurements; "
        "anything older is dropped and counted"
    )


class Cameras(_Model):
    width_px: int = Field(2000, ge=16)
    height_px: int = Field(2000, ge=16)
    fov_deg: float = Field(90.0, gt=1, lt=179)


#: Selection strategies (:mod:`swarmcore.selection` implements each; add one there and here).
StrategyName = Literal[
    "none", "complete", "random", "random_tree", "greedy", "swarm_greedy", "fast_swarm_greedy", "logdet_greedy"
]
#: The strategies that need no state estimate (a selector's fallback).
FallbackStrategy = Literal["random_tree", "random", "complete"]


class Selection(_Model):
    """Measurement selection (chapter 6); see :mod:`swarmcore.selection` for the strategies."""

    strategy: StrategyName = Field(
        "none",
        description="none: take every measurement of the graph each step; complete: every candidate; "
        "random: m random directed pairs; random_tree: a uniform random spanning tree (at most m "
        "edges); greedy: minimise the weighted posterior trace (dissertation); swarm_greedy: greedy "
        "on the trace averaged over every satellite's filter (anchor-free); fast_swarm_greedy: the "
        "same, lazy, over each satellite's nearest neighbours; logdet_greedy: greedy D-optimal",
    )
    budget: int = Field(5, ge=1, description="m: relative measurements per step")
    neighbors: int = Field(
        5, ge=1, description="fast_swarm_greedy: candidates limited to pairs where one end is among the "
        "other's k nearest (estimated) neighbours"
    )
    sat_weights: list[Annotated[float, Field(ge=0)]] | None = Field(
        None, description="c_a: per-satellite weights (default 1)"
    )
    state_weights: list[Annotated[float, Field(ge=0)]] = Field(
        [1.0] * 12, description="c_b: weights of the 12 error states [a, Δω|Δβ, Δr, Δv] of a satellite"
    )
    require_visible: bool = Field(True, description="only candidates predicted to be visible")
    fallback: FallbackStrategy = Field(
        "random_tree", description="state-free strategy used when the selector has no estimate"
    )


class Jitter(_Model):
    """Random extra latency of each delivered message, drawn per (link, message)."""

    distribution: Literal["none", "uniform", "normal", "exponential"] = Field(
        "none", description="none; uniform on [0, scale_s]; normal: |N(0, scale_s²)| (half-normal); "
        "exponential with mean scale_s"
    )
    scale_s: NonNegFloat = Field(0.0, description="the distribution's scale (s)")


class Latency(_Model):
    """One-way latency of a message: fixed + range / c + per_m_s · range + jitter."""

    fixed_s: NonNegFloat = Field(0.0, description="processing and access delay (s)")
    speed_of_light: bool = Field(True, description="add range / c (the propagation delay)")
    per_m_s: NonNegFloat = Field(0.0, description="extra delay per metre of range (store-and-forward radios), s/m")
    jitter: Jitter = Jitter()


class Loss(_Model):
    """Message loss on a link: independent (Bernoulli) or bursty (Gilbert–Elliott: a Good and
    a Bad state, every message lost in Bad; per message P(Good→Bad) = p, P(Bad→Good) = r,
    so the mean burst is 1/r messages and the long-run loss rate p / (p + r))."""

    model: Literal["none", "bernoulli", "gilbert_elliott"] = "none"
    rate: float = Field(0.0, ge=0.0, lt=1.0, description="long-run fraction of messages lost")
    mean_burst: float = Field(1.0, ge=1.0, description="gilbert_elliott: mean run of consecutive losses (messages)")


class LinkOverride(_Model):
    """Parameters of one directed link (``from`` transmits, ``to`` receives) that differ
    from the defaults; a field left out keeps the default."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, populate_by_name=True)

    src: int = Field(ge=0, alias="from", description="transmitting satellite")
    dst: int = Field(ge=0, alias="to", description="receiving satellite")
    dead: bool = Field(False, description="the link carries nothing")
    latency: Latency | None = None
    loss: Loss | None = None
    max_range_m: PosFloat | None = None


class Links(_Model):
    """Inter-satellite links: what the radio does to the relative-measurement batches (and
    to the state a restarted agent fetches from a peer). Defaults: the ideal network (every
    batch reaches every live peer within its own step), which keeps every earlier result.

    Every draw comes from a stream keyed by (seed, purpose, step) over all n×n links, so
    the fate of a message never depends on arrival order: the same numbers in-process and
    distributed. In lockstep, times are simulated; in free mode, real (scaled by
    ``emulator.realtime_factor``).

    A batch is applied at the first step at or after its arrival, so with links on ANY
    latency makes it late — the default propagation delay (range / c, tens of ns) too:
    every peer batch then waits one step (``filter.late: replay`` gives it its own step
    back; ``drop`` loses it). ``latency.speed_of_light: false`` with zero latency, no loss
    and no cap is exactly the ideal network."""

    enabled: bool = Field(False, description="false: the ideal network of earlier versions")
    latency: Latency = Latency()
    rate_Bps: PosFloat | None = Field(
        None, description="each transmitter's data rate (bytes/s), shared by all its outgoing copies; "
        "null: unlimited"
    )
    queue_bytes: Annotated[int, Field(ge=0)] = Field(
        262_144, description="each transmitter's queue (bytes) while rate_Bps holds it back"
    )
    queue_policy: Literal["drop_tail", "drop_head"] = Field(
        "drop_tail", description="a copy that does not fit: drop it (drop_tail), or drop the oldest "
        "waiting copies until it fits (drop_head)"
    )
    loss: Loss = Loss()
    max_range_m: PosFloat | None = Field(None, description="no link beyond this range (m); null: unlimited")
    line_of_sight: bool = Field(
        False, description="another satellite's body (a sphere of spacecraft.half_size_m · √3) between "
        "two satellites blocks their link"
    )
    overrides: list[LinkOverride] = Field(default_factory=list, description="per directed link parameters")


#: Every fault the emulator knows (scheduled in a scenario, or sent with ``swarm fault``).
FaultAction = Literal[
    "kill-agent",
    "restart-agent",
    "stop-agent",
    "camera",
    "kill-selector",
    "restart-selector",
    "drop",
    "partition",
    "heal",
    "netem",
    "kill-router",
    "restart-router",
]
FAULT_ACTIONS: tuple[str, ...] = get_args(FaultAction)
#: Faults on an agent's process, carried out by the supervisor (``swarm run``) or Docker.
AGENT_PROCESS_FAULTS = ("kill-agent", "restart-agent", "stop-agent")
#: Faults on the selector's process.
SELECTOR_PROCESS_FAULTS = ("kill-selector", "restart-selector")
#: Faults on a container's network: compose only (local processes share one network).
#: netem: Linux traffic control (delay, jitter, loss, rate) in the container's namespace.
NETWORK_FAULTS = ("partition", "heal", "netem")
#: Faults on the bus itself: a Zenoh router's process (target: the router's index, 0 by
#: default; ``swarm run --routers 2`` has two). Carried out by the supervisor or Docker.
ROUTER_FAULTS = ("kill-router", "restart-router")
#: Faults some process other than the bus roles carries out (supervisor, Docker).
PROCESS_FAULTS = AGENT_PROCESS_FAULTS + SELECTOR_PROCESS_FAULTS + NETWORK_FAULTS + ROUTER_FAULTS
#: Faults that name a satellite.
TARGETED_FAULTS = (*AGENT_PROCESS_FAULTS, "camera", "drop", *NETWORK_FAULTS)


class FaultSpec(_Model):
    """A time-tagged fault of the distributed emulator (applied at the start of a step)."""

    at_step: int = Field(ge=0, description="the step at whose start the fault is applied")
    action: FaultAction
    target: int | None = Field(None, ge=0, description="satellite id (agent and camera faults)")
    camera: int | None = Field(None, ge=0, le=5, description="camera index 0..5 (+z,+x,+y,−x,−y,−z)")
    state: Literal["on", "off"] | None = None
    rate: float | None = Field(None, ge=0.0, le=1.0, description="drop: fraction of outgoing messages lost")
    down_s: float | None = Field(
        None, ge=0.0, le=3600.0, description="restart-router: how long (wall s) the router stays down before a new one "
        "starts on the same endpoint (default 0)"
    )

    @model_validator(mode="after")
    def _complete(self):
        if self.action in NETWORK_FAULTS:
            raise ValueError(f"action {self.action} acts on a container's network: send it with `swarm fault --compose`")
        if self.action in TARGETED_FAULTS and self.target is None:
            raise ValueError(f"action {self.action} needs a target satellite id")
        if self.action == "camera" and (self.camera is None or self.state is None):
            raise ValueError("action camera needs camera (0..5) and state (on|off)")
        if self.action == "drop" and self.rate is None:
            raise ValueError("action drop needs rate (0..1)")
        if self.down_s is not None and self.action != "restart-router":
            raise ValueError("down_s is for action restart-router")
        return self


class Emulator(_Model):
    """How the distributed emulator keeps time and waits (``swarm run``)."""

    time_mode: Literal["lockstep", "free"] = Field(
        "lockstep", description="lockstep: the world waits for every live agent (reproducible); "
        "free: the clock runs at realtime_factor × wall time"
    )
    realtime_factor: PosFloat = Field(1.0, description="free mode: simulated seconds per wall second")
    lockstep_max_realtime_factor: PosFloat | None = Field(
        None, description="lockstep: never run faster than this many simulated seconds per wall second "
        "(None: as fast as the agents allow); for demos and for faults typed by hand"
    )
    step_timeout_s: PosFloat = Field(10.0, description="lockstep: longest wait for a live peer's message")
    select_timeout_s: PosFloat = Field(2.0, description="longest wait for the selector before falling back")
    startup_timeout_s: PosFloat = Field(120.0, description="longest wait for every process to come up")
    flush_every_s: PosFloat = Field(1.0, description="recorder: flush to disk at least this often (sim time)")
    record_images: bool = Field(
        False, description="recorder: also write every rendered image (foxglove.RawImage, large) besides its metadata"
    )
    bus_grace_s: PosFloat = Field(
        10.0, description="a peer whose liveliness vanished with the bus (no router reachable) is declared dead only if "
        "it is still gone this long after the bus came back; any other disappearance counts after liveliness_hold_s"
    )
    liveliness_hold_s: PosFloat = Field(
        0.3, description="how long a vanished liveliness token is held before it counts (the link to a router may be "
        "going down with it, or a client failing over to another router)"
    )
    bus_lost_after_s: PosFloat = Field(
        30.0, description="no router reachable this long: the run is broken, every role exits (non-zero)"
    )
    shutdown_linger_s: PosFloat = Field(
        30.0, description="after the last step: how long the recorder waits for every live agent's final estimate, "
        "and the world and agents keep their bus sessions open until the recorder has them"
    )
    security: bool = Field(
        True, description="on (default): every process authenticates to the router with its own credential and "
        "the router's access rules say who may put, subscribe and query what (swarm/security.py); "
        "off: anyone reaching the router may publish anything (debugging, measuring the cost; loud in logs and summary)"
    )


class Scenario(_Model):
    name: str = "unnamed"
    seed: int = Field(0, ge=0)
    n_sats: int = Field(5, ge=2, le=200)
    duration_s: PosFloat = 100.0
    dt_s: PosFloat = 1.0
    truth_substeps: int = Field(20, ge=1, le=1000, description="RK4 substeps per dt for the truth attitude")
    orbit: Orbit = Orbit()
    spacecraft: Spacecraft = Spacecraft()
    initial: Initial = Initial()
    disturbances: Disturbances = Disturbances()
    sensors: Sensors = Sensors()
    graph: Graph = Graph()
    filter: Filter = Filter()
    cameras: Cameras = Cameras()
    selection: Selection = Selection()
    vision: VisionConfig = Field(
        default_factory=VisionConfig,
        description="rendered cameras and vision pipelines (chapter 5); pipeline none keeps sensors.relative",
    )
    emulator: Emulator = Emulator()
    links: Links = Field(default_factory=Links, description="inter-satellite links (delay, data rate, loss, range)")
    faults: list[FaultSpec] = Field(default_factory=list, description="time-tagged faults (distributed runs)")

    @property
    def steps(self) -> int:
        return round(self.duration_s / self.dt_s) + 1

    @model_validator(mode="after")
    def _cross_checks(self):
        n = self.n_sats
        g = self.graph
        if g.kind == "star" and g.landmark >= n:
            raise ValueError(f"graph.landmark: {g.landmark} is not a satellite id (0..{n - 1})")
        if g.kind == "matrix":
            if g.matrix is None:
                raise ValueError("graph.matrix: required when graph.kind is 'matrix'")
            m = np.asarray(g.matrix)
            if m.shape != (n, n):
                raise ValueError(f"graph.matrix: must be {n}×{n} for n_sats={n}, got shape {m.shape}")
            if not np.isin(m, (0, 1)).all():
                raise ValueError("graph.matrix: entries must be 0 or 1")
        if isinstance(g.absolute, list):
            bad = [i for i in g.absolute if not 0 <= i < n]
            if bad:
                raise ValueError(f"graph.absolute: unknown satellite ids {bad} (0..{n - 1})")
        if self.selection.sat_weights is not None and len(self.selection.sat_weights) != n:
            raise ValueError(f"selection.sat_weights: needs {n} values, got {len(self.selection.sat_weights)}")
        if len(self.selection.state_weights) != 12:
            raise ValueError("selection.state_weights: needs 12 values (one per error state)")
        if self.duration_s < self.dt_s:
            raise ValueError("duration_s: must be at least dt_s")
        if self.vision.pipeline == "mono":
            if n > 97:
                raise ValueError(f"vision.pipeline: mono needs a unique AprilTag per face; 36h11 has 587 tags, enough for 97 satellites, not {n}")
            if self.vision.mono.tag_size_m >= 2 * self.spacecraft.half_size_m:
                raise ValueError("vision.mono.tag_size_m: the tag must be smaller than the cube face")
        for idx, o in enumerate(self.links.overrides):
            for end, v in (("from", o.src), ("to", o.dst)):
                if v >= n:
                    raise ValueError(f"links.overrides.{idx}.{end}: {v} is not a satellite id (0..{n - 1})")
            if o.src == o.dst:
                raise ValueError(f"links.overrides.{idx}: a link joins two different satellites, not {o.src} to itself")
        pairs = [(o.src, o.dst) for o in self.links.overrides]
        if len(set(pairs)) != len(pairs):
            raise ValueError("links.overrides: each directed link may be listed once")
        for idx, f in enumerate(self.faults):
            if f.target is not None and f.target >= n:
                raise ValueError(f"faults.{idx}.target: {f.target} is not a satellite id (0..{n - 1})")
        return self
