"""Typed, validated scenario model: the only place defaults live.

Defaults follow the dissertation's Table 4.1 (LEO, ~622 km). Pure: no file I/O here;
:mod:`swarmrt.scenario_files` loads YAML and applies ``--set`` overrides.
"""

from __future__ import annotations

from typing import Annotated, Literal, get_args

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from .config_types import CameraAxes, NonNegFloat, PosFloat
from .config_types import ConfigModel as _Model
from .vision_config import VisionConfig, mono_tag_problem


class Drag(_Model):
    """Atmospheric drag of the truth (``orbit.model: j2``): an exponential atmosphere
    (:class:`swarmcore.orbit.ExponentialAtmosphere`; defaults: Vallado Table 8-4, 500 km band)
    and each satellite's ballistic coefficient ``C_D A / m``."""

    enabled: bool = Field(False, description="add drag to the truth (and to a j2 filter's model)")
    ballistic_m2_kg: NonNegFloat | list[NonNegFloat] = Field(
        0.01, description="C_D A / m (m²/kg): one value for every satellite or one per satellite"
    )
    chief_ballistic_m2_kg: NonNegFloat = Field(
        0.01, description="the chief (the reference point every agent knows, not a satellite): its C_D A / m"
    )
    rho0_kg_m3: PosFloat = Field(6.967e-13, description="density at h0_m")
    h0_m: NonNegFloat = Field(500e3, description="reference altitude of the band")
    scale_height_m: PosFloat = Field(63.822e3, description="scale height H_s")
    co_rotating: bool = Field(True, description="the air turns with the Earth")


class Orbit(_Model):
    """The reference orbit. ``hcw`` (default): the Hill-Clohessy-Wiltshire model about a
    circular orbit of mean motion ``mean_motion_rad_s`` (every earlier result). ``j2``: the
    truth propagates each satellite's ECI state under two-body + J2 (+ drag) with
    :func:`swarmcore.orbit.propagate`; relative truth is each satellite in the Hill frame of
    a *chief* (a reference orbit given by its elements, propagated with the same model,
    known to every agent) — ``docs/long-range-core.md``."""

    model: Literal["hcw", "j2"] = Field("hcw", description="hcw: HCW truth (mean_motion_rad_s); j2: J2 (+ drag) truth")
    mean_motion_rad_s: PosFloat = Field(1.08e-3, description="HCW mean motion n (1/s); 622 km LEO (model hcw only)")
    altitude_m: PosFloat | None = Field(
        None, description="j2: the chief's semi-major axis minus the Earth's equatorial radius (default 550 km); "
        "give this or semi_major_axis_m"
    )
    semi_major_axis_m: PosFloat | None = Field(None, description="j2: the chief's semi-major axis (m)")
    eccentricity: float = Field(0.0, ge=0.0, lt=0.2, description="j2: the chief's eccentricity")
    inclination_deg: float = Field(97.6, ge=0.0, le=180.0, description="j2: inclination")
    raan_deg: float = Field(0.0, description="j2: right ascension of the ascending node")
    argp_deg: float = Field(0.0, description="j2: argument of perigee")
    true_anomaly_deg: float = Field(0.0, description="j2: true anomaly at t = 0")
    j2: NonNegFloat = Field(1.08262668e-3, description="j2: the Earth's J2 (0: two-body)")
    step_s: PosFloat = Field(10.0, le=60.0, description="j2: RK8 step of the orbit propagator (at most this; dt_s is cut into equal steps)")
    drag: Drag = Drag()

    @model_validator(mode="after")
    def _elements(self):
        if self.altitude_m is not None and self.semi_major_axis_m is not None:
            raise ValueError("orbit.altitude_m and orbit.semi_major_axis_m: give one of them, not both")
        if self.model == "j2":
            a = self.semi_major_axis()
            r_p = a * (1.0 - self.eccentricity)
            if r_p < 6378137.0 + 100e3:
                raise ValueError(
                    f"orbit.eccentricity: perigee radius {r_p / 1e3:.0f} km is less than 100 km above the Earth "
                    "(raise orbit.altitude_m or lower orbit.eccentricity)"
                )
        if self.model == "hcw" and (self.drag.enabled or self.altitude_m is not None or self.semi_major_axis_m is not None):
            raise ValueError("orbit.model: hcw has no chief orbit elements or drag (set orbit.model: j2)")
        return self

    def semi_major_axis(self) -> float:
        """The chief's semi-major axis (m)."""
        if self.semi_major_axis_m is not None:
            return float(self.semi_major_axis_m)
        return 6378137.0 + (550e3 if self.altitude_m is None else float(self.altitude_m))

    def mean_motion(self) -> float:
        """n (rad/s): ``mean_motion_rad_s`` (hcw) or the chief's ``√(μ/a³)`` (j2)."""
        if self.model == "hcw":
            return float(self.mean_motion_rad_s)
        return float(np.sqrt(3.986004418e14 / self.semi_major_axis() ** 3))


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
    layout: Literal["random", "lattice", "train"] = Field(
        "random", description="random: positions uniform in ±position_max_m; lattice: a nominal grid of spacing_m (as cubic as "
        "n allows, centred on the origin) plus a uniform offset in ±position_max_m per axis (large swarms; graph.kind nearest); "
        "train: an along-track train, satellite i at y = −i·spacing_m (satellite 0 leads, on the chief) plus the offset")
    spacing_m: PosFloat = Field(20.0, description="lattice: distance between neighbouring nominal positions (m)")
    position_max_m: NonNegFloat = Field(10.0, description="truth positions uniform in ±this per H axis (lattice: the offset)")
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
    satellites: list[Annotated[int, Field(ge=0)]] | None = Field(
        None, description="only these satellites have a GPS receiver (null: every satellite graph.absolute names; the star "
        "tracker is unaffected)"
    )


class BearingSensor(_Model):
    """Angles-only camera (``sensors.relative.model: bearing``, :mod:`swarmcore.bearing`):
    observer i measures only the unit line of sight to target j. Each satellite has six
    face cameras (``swarmcore.cameras``); the one nearest the line of sight takes the image.
    Noise: isotropic angular noise σ_px / f_px in the tangent plane (the upper bound of
    :func:`swarmcore.bearing.bearing_noise_cov`, exact on the boresight)."""

    sigma_px: PosFloat = Field(1.0, description="centroid noise (pixels, 1σ per image axis)")
    f_px: PosFloat = Field(5000.0, description="focal length (pixels)")
    half_fov_deg: float = Field(60.0, gt=0.0, lt=90.0, description="half field of view of each face camera")
    min_size_px: PosFloat | None = Field(None, description="resolved-target detection: apparent size ≥ this (null: off)")
    limiting_magnitude: float | None = Field(
        None, description="unresolved detection: visual magnitude ≤ this (lit diffuse sphere; null: off)"
    )
    sun_exclusion_deg: NonNegFloat = Field(30.0, lt=180.0, description="no image within this angle of the Sun")
    sun_direction_I: list[float] = Field([1.0, 0.0, 0.0], min_length=3, max_length=3, description="Sun direction in I (fixed)")
    target_size_m: PosFloat = Field(0.3, description="each target's size (resolved test)")
    target_area_m2: PosFloat = Field(0.06, description="each target's cross-section (brightness)")
    target_albedo: PosFloat = Field(0.2, description="each target's albedo")

    @property
    def sigma_rad(self) -> float:
        return float(self.sigma_px / self.f_px)


class Relative(_Model):
    """Synthetic relative pose measurements (chapter 4 isotropic, or chapter 6 camera-frame)."""

    model: Literal["isotropic", "camera", "bearing"] = Field(
        "isotropic", description="noise model; bearing: angles-only (unit line of sight, see bearing)")
    bearing: BearingSensor = BearingSensor()
    sigma_att_rad: PosFloat = Field(0.03, description="σ_q: isotropic relative attitude noise")
    sigma_pos_m: PosFloat = Field(0.01, description="σ_p: isotropic relative position noise")
    sigma_pos_camera_m: CameraAxes = Field(
        [0.25, 0.25, 0.12], description="camera model: position σ along camera x, y, z at the reference range"
    )
    sigma_att_camera_rad: CameraAxes = Field(
        [0.03, 0.03, 0.03], description="camera model: attitude σ about camera x, y, z at the reference range"
    )
    range_exponent: NonNegFloat = Field(
        2.0, description="camera model: σ grows as (range / reference_range_m) ** range_exponent"
    )
    reference_range_m: PosFloat = Field(10.0, description="camera model: range at which σ is as given")


class Sensors(_Model):
    gyro: Gyro = Gyro()
    star_tracker: StarTracker = StarTracker()
    gps: GPS = GPS()
    relative: Relative = Relative()


class Graph(_Model):
    """Which relative measurements exist (G(i, j) = 1: i measures j); diagonal = absolute."""

    kind: Literal["complete", "star", "chain", "duplex_chain", "matrix", "nearest"] = "complete"
    landmark: int = Field(0, ge=0, description="star: the satellite every other one measures")
    neighbors: int = Field(3, ge=1, description="nearest: each satellite measures its k nearest by nominal position (initial.layout: lattice)")
    matrix: list[list[int]] | None = Field(None, description="matrix: explicit n×n incidence (0/1)")
    absolute: Literal["all", "none"] | list[int] = Field(
        "all", description="satellites with star tracker + GPS (for kind=matrix the diagonal decides)"
    )


class Gate(_Model):
    enabled: bool = True
    probability: float = Field(0.999, gt=0.5, lt=1.0, description="χ²(6) quantile of the threshold")

    def threshold(self, dof: int = 6) -> float | None:
        """The χ²(dof) quantile (6: a pose; 2: a bearing): ``2 · gammaincinv(dof/2, p)``, exactly
        what ``scipy.stats.chi2.ppf`` computes (importing scipy.stats would cost every process
        ~1 s of start-up)."""
        from scipy.special import gammaincinv  # here, not at import: the CLI's start-up needs no scipy

        return float(2 * gammaincinv(dof / 2, self.probability)) if self.enabled else None


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
    dynamics: Literal["auto", "hcw", "j2"] = Field(
        "auto", description="translation model of the filter: hcw (closed-form HCW about the chief's mean motion), j2 "
        "(swarmcore.relmotion: the differenced J2 (+ drag) equations about the chief, exact STM; needs orbit.model: j2); "
        "auto: the truth's orbit.model"
    )
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
#: Every selection strategy by name (the one list: the CLI, compare and the benches read it).
STRATEGIES: tuple[str, ...] = tuple(s for s in get_args(StrategyName) if s != "none")
#: Those that plan without a state estimate, and those that plan from the full-swarm covariance.
STATE_FREE: tuple[str, ...] = get_args(FallbackStrategy)
NEEDS_STATE: tuple[str, ...] = tuple(s for s in STRATEGIES if s not in STATE_FREE)


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

    model_config = ConfigDict(extra="forbid", validate_assignment=True, populate_by_name=True, allow_inf_nan=False)

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
    "stall-agent",
    "stall-world",
    "stall-selector",
    "stall-recorder",
    "stall-router",
    "link",
    "kill-node",
    "partition-nodes",
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
#: A role's process stopped (SIGSTOP; ``docker pause`` under compose) for ``down_s`` wall
#: seconds, then continued (SIGCONT; ``docker unpause``): a stall, not a death. Its sockets
#: stay open; past the Zenoh lease (10 s) its router drops its session. The target of
#: ``stall-agent`` is the satellite, of ``stall-router`` the router's index (0 by default).
STALL_FAULTS = ("stall-agent", "stall-world", "stall-selector", "stall-recorder", "stall-router")
#: Faults some process other than the bus roles carries out (supervisor, Docker).
PROCESS_FAULTS = AGENT_PROCESS_FAULTS + SELECTOR_PROCESS_FAULTS + NETWORK_FAULTS + ROUTER_FAULTS + STALL_FAULTS
#: A fault of the radio (the world's link model; ``links.enabled`` runs only): the directed
#: link ``target → peer`` (no peer: every link of ``target``, both ways) made dead
#: (``state: off``), slower (``delay_s`` added to its fixed latency) or lossier (``rate``, a
#: Bernoulli loss rate), or given back the scenario's parameters (``state: on``).
RADIO_FAULTS = ("link",)
#: Faults on a host of a cluster run (``swarm run --cluster``; target: the node's index, 0 the
#: head): ``kill-node`` takes the node down (its raylet and everything on it killed; its
#: agents restarted on the others), ``partition-nodes`` cuts node ``target`` and node ``peer``
#: apart for ``down_s`` wall seconds (every packet between them dropped), then heals it.
CLUSTER_FAULTS = ("kill-node", "partition-nodes")
#: Faults that name a satellite.
TARGETED_FAULTS = (*AGENT_PROCESS_FAULTS, "camera", "drop", *NETWORK_FAULTS, "stall-agent", *RADIO_FAULTS)
#: Faults that take ``down_s``: how long the router stays down, or the stall lasts (wall s).
TIMED_FAULTS = ("restart-router", *STALL_FAULTS, "partition-nodes")


class FaultSpec(_Model):
    """A time-tagged fault of the distributed emulator (applied at the start of a step)."""

    at_step: int = Field(ge=0, description="the step at whose start the fault is applied")
    action: FaultAction
    target: int | None = Field(None, ge=0, description="satellite id (agent and camera faults); a node's index (kill-node, "
                               "partition-nodes; 0 is the head)")
    camera: int | None = Field(None, ge=0, le=5, description="camera index 0..5 (+z,+x,+y,−x,−y,−z)")
    state: Literal["on", "off"] | None = None
    rate: float | None = Field(None, ge=0.0, le=1.0, description="drop: fraction of outgoing messages lost; link: its "
                               "loss rate (Bernoulli) from now on")
    down_s: float | None = Field(
        None, ge=0.0, le=3600.0, description="restart-router: how long (wall s) the router stays down before a new one "
        "starts on the same endpoint (default 0); stall-*: how long (wall s) the process stays stopped (required)"
    )
    peer: int | None = Field(None, ge=0, description="link: the receiving satellite of the link target → peer (absent: "
                             "every link of target, both ways); partition-nodes: the other node")
    delay_s: float | None = Field(None, ge=0.0, le=3600.0, description="link: latency (s) added to its fixed latency")

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
        if self.rate is not None and self.action not in ("drop", "link"):
            raise ValueError("rate is for actions drop and link")
        if self.action in CLUSTER_FAULTS:
            if self.target is None:
                raise ValueError(f"action {self.action} needs a target node (its index; 0 is the head)")
            if self.action == "partition-nodes" and (self.peer is None or self.peer == self.target or not self.down_s):
                raise ValueError("action partition-nodes needs target and peer (two different nodes) and down_s > 0 "
                                 "(how long they stay cut apart, wall s)")
        if self.delay_s is not None and self.action != "link":
            raise ValueError("delay_s is for action link")
        if self.peer is not None and self.action not in ("link", "partition-nodes"):
            raise ValueError("peer is for actions link and partition-nodes")
        if self.action == "link":
            if self.state is None and self.delay_s is None and self.rate is None:
                raise ValueError("action link needs state (off: dead, on: the scenario's parameters back), delay_s or rate")
            if self.state == "on" and (self.delay_s is not None or self.rate is not None):
                raise ValueError("action link with state on gives the link back as the scenario has it: no delay_s or rate")
            if self.peer is not None and self.peer == self.target:
                raise ValueError(f"peer: satellite {self.peer} has no link to itself")
        elif self.state is not None and self.action != "camera":
            raise ValueError("state is for actions camera and link")
        if self.down_s is not None and self.action not in TIMED_FAULTS:
            raise ValueError(f"down_s is for actions {', '.join(TIMED_FAULTS)}")
        if self.action in STALL_FAULTS and not self.down_s:
            raise ValueError(f"action {self.action} needs down_s > 0 (how long the process stays stopped, wall s)")
        return self


class Placement(_Model):
    """Where the processes of a cluster run go (``swarm run --cluster``; a local run ignores
    it). Nodes are numbered 0 (the head) then by address."""

    world: int = Field(0, ge=0, description="the node of the world")
    selector: int = Field(0, ge=0, description="the node of the selector")
    recorder: int = Field(0, ge=0, description="the node of the recorder (it writes run.mcap there)")
    agents: Literal["spread"] | list[int] = Field(
        "spread", description="spread: satellite i on node i mod N (N nodes); or one node index per satellite"
    )


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
    select_timeout_s: PosFloat = Field(
        2.0, description="free-running: longest wait for the selector before falling back (lockstep waits for a live "
        "selector as for a live agent: step_timeout_s plus the bus lease; a selector gone is replaced at once)"
    )
    startup_timeout_s: PosFloat = Field(120.0, description="longest wait for every process to come up")
    recorder_max_lag_steps: int = Field(
        4, ge=1, le=1000, description="lockstep: the world begins step k only once the recorder has taken in the clock "
        "of step k - recorder_max_lag_steps (it keeps up, or the swarm waits for it: counted as recorder_lag in "
        "summary.json); every role keeps its messages of the last recorder_max_lag_steps + 2 steps and sends them again "
        "when the recorder comes back after a gap, so a router failover loses nothing from the recording"
    )
    gate: bool = Field(
        True, description="local runs (swarm run) and each node of a cluster run: every process reaches its router through an "
        "ingress gate that rate-limits "
        "what each identity sends in (a token bucket with a burst allowance; the sender is held back, nothing is dropped), "
        "so a stolen credential's flood cannot slow the swarm; counted per identity in summary.json (router_gate)"
    )
    gate_steps_per_s: float = Field(
        50.0, ge=1.0, le=1e6, description="the gate's rate for an identity: this many of its step budgets per wall second "
        "(a step budget: the size limits of every key the identity may put, the same limits the router enforces; an "
        "honest role sends a small part of it per step); its burst: recorder_max_lag_steps + 3 step budgets"
    )
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
        "the router's access rules say who may put, subscribe and query what (swarmrt/security.py); "
        "off: anyone reaching the router may publish anything (debugging, measuring the cost; loud in logs and summary)"
    )
    agent_start: Literal["fork", "spawn"] = Field(
        "fork", description="how swarm run starts the Python agents: fork (from one fork server that has imported and compiled "
        "everything once: fast, shared memory; swarm/supervise/forkserver.py) or spawn (one fresh interpreter each)"
    )
    agent_commands: dict[int, str] = Field(
        default_factory=dict, description="satellites flown by another program than the Python sat_agent: {satellite id: "
        "command line} (docs/agent-contract.md: what it is given and what it owes the swarm); `swarm run --agent I=CMD`"
    )
    placement: Placement = Field(default_factory=lambda: Placement(), description="swarm run --cluster: which node "
                                 "runs what (docs/cluster.md)")


class Bound(_Model):
    """The posterior Cramér–Rao bound of an in-process run (:mod:`swarmcore.crlb`,
    ``summary.json``'s ``bound`` and ``rms_over_bound``): along the true trajectory, for
    the scenario's process noise and exactly the measurements the run took."""

    enabled: bool = Field(True, description="compute the bound (about one full-swarm filter's covariance step per "
                          "step; off: no bound in the result or summary)")
    max_sats: int = Field(
        40, ge=2, description="compute it only for swarms of at most this many satellites (its cost per step grows as "
        "(12 n)³: ~2 ms at n = 10, a 12000 × 12000 covariance at n = 1000)")
    filter: int | None = Field(
        None, ge=0, description="null: the centralized bound (every satellite's gyro, every absolute reading, every "
        "relative measurement taken); an id f: the bound of what filter f hears (its own gyro, its own absolute "
        "reading, the relative measurements that reached it, late ones counted at the step they were taken)")


class EstimatorConfig(_Model):
    """Which estimator every agent flies, and its parameters (the fields beside ``kind``).

    Built in: ``full`` (the full-swarm MEKF, the reference), ``ci`` (covariance
    intersection, Carrillo-Arce et al. 2013; split CI), ``pairwise`` (Luft et al. 2018).
    A plug-in package adds kinds through the ``swarm_coloc.estimators`` entry-point group
    (``docs/estimators.md``). Each kind validates its own parameters when the scenario
    is loaded; an unknown kind or field is an error naming it."""

    model_config = ConfigDict(extra="allow", validate_assignment=True, allow_inf_nan=False)

    kind: str = Field("full", pattern=r"^[a-z][a-z0-9_\-]*$", description="the estimator's name")

    def params(self) -> dict:
        """The parameters: every field but ``kind``."""
        return dict(self.model_extra or {})


class Scenario(_Model):
    name: str = "unnamed"
    seed: int = Field(0, ge=0)
    n_sats: int = Field(5, ge=2, le=1000)
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
    estimator: EstimatorConfig = Field(default_factory=EstimatorConfig, description="the estimator every agent flies")
    bound: Bound = Field(default_factory=Bound, description="the Cramér–Rao bound of an in-process run (swarmcore/crlb.py)")

    @property
    def bound_on(self) -> bool:
        """The Cramér–Rao bound is computed for this scenario (``bound.enabled`` and at most
        ``bound.max_sats`` satellites)."""
        return self.bound.enabled and self.n_sats <= self.bound.max_sats

    @property
    def steps(self) -> int:
        return round(self.duration_s / self.dt_s) + 1

    def filter_dynamics(self) -> str:
        """The filter's translation model: ``filter.dynamics``, ``auto`` resolved to ``orbit.model``."""
        return self.orbit.model if self.filter.dynamics == "auto" else self.filter.dynamics

    def ballistic(self) -> np.ndarray:
        """Every satellite's ``C_D A / m`` (m²/kg), zeros when drag is off."""
        d = self.orbit.drag
        if not d.enabled:
            return np.zeros(self.n_sats)
        return np.broadcast_to(np.asarray(d.ballistic_m2_kg, dtype=float), (self.n_sats,)).copy()

    @model_validator(mode="after")
    def _cross_checks(self):
        n = self.n_sats
        g = self.graph
        if self.bound.filter is not None and self.bound.filter >= n:
            raise ValueError(f"bound.filter: {self.bound.filter} is not a satellite id (0..{n - 1})")
        if g.kind == "star" and g.landmark >= n:
            raise ValueError(f"graph.landmark: {g.landmark} is not a satellite id (0..{n - 1})")
        if g.kind == "nearest":
            if self.initial.layout != "lattice":
                raise ValueError("graph.kind: nearest measures the nearest neighbours of a nominal formation: set initial.layout: lattice")
            if g.neighbors >= n:
                raise ValueError(f"graph.neighbors: {g.neighbors} of a swarm of {n} (at most {n - 1})")
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
        gps_sats = self.sensors.gps.satellites
        if gps_sats is not None and (bad := [i for i in gps_sats if i >= n]):
            raise ValueError(f"sensors.gps.satellites: unknown satellite ids {bad} (0..{n - 1})")
        if self.filter.dynamics == "j2" and self.orbit.model != "j2":
            raise ValueError("filter.dynamics: j2 needs a chief orbit (set orbit.model: j2)")
        if self.orbit.model == "j2" and self.vision.pipeline != "none":
            raise ValueError("orbit.model: j2 is not wired into the rendered cameras (vision.pipeline must be none)")
        if isinstance(self.orbit.drag.ballistic_m2_kg, list) and len(self.orbit.drag.ballistic_m2_kg) != n:
            raise ValueError(
                f"orbit.drag.ballistic_m2_kg: needs one value or {n} (one per satellite), got {len(self.orbit.drag.ballistic_m2_kg)}"
            )
        if self.sensors.relative.model == "bearing" and self.vision.pipeline != "none":
            raise ValueError("sensors.relative.model: bearing is the synthetic angles-only camera (vision.pipeline must be none)")
        if self.sensors.relative.model == "bearing" and self.selection.strategy not in ("none", "complete", "random", "random_tree"):
            raise ValueError("selection.strategy: the covariance-driven strategies plan 6-dof pose measurements, not bearings "
                             "(use none, complete, random or random_tree with sensors.relative.model: bearing)")
        if self.duration_s < self.dt_s:
            raise ValueError("duration_s: must be at least dt_s")
        if self.vision.pipeline == "mono" and (why := mono_tag_problem(self.vision, n, self.spacecraft.half_size_m)):
            raise ValueError(why)
        for idx, o in enumerate(self.links.overrides):
            for end, v in (("from", o.src), ("to", o.dst)):
                if v >= n:
                    raise ValueError(f"links.overrides.{idx}.{end}: {v} is not a satellite id (0..{n - 1})")
            if o.src == o.dst:
                raise ValueError(f"links.overrides.{idx}: a link joins two different satellites, not {o.src} to itself")
        pairs = [(o.src, o.dst) for o in self.links.overrides]
        if len(set(pairs)) != len(pairs):
            raise ValueError("links.overrides: each directed link may be listed once")
        for sat, cmd in self.emulator.agent_commands.items():
            if not 0 <= sat < n:
                raise ValueError(f"emulator.agent_commands.{sat}: not a satellite id (0..{n - 1})")
            if not cmd.strip():
                raise ValueError(f"emulator.agent_commands.{sat}: an empty command")
        agents = self.emulator.placement.agents
        if isinstance(agents, list) and len(agents) != n:
            raise ValueError(f"emulator.placement.agents: {len(agents)} node indices for {n} satellites (one each, or spread)")
        for idx, f in enumerate(self.faults):
            if f.action in CLUSTER_FAULTS:
                continue  # node indices: the cluster's size is known when it runs (swarm run --cluster checks them)
            if f.target is not None and f.target >= n:
                raise ValueError(f"faults.{idx}.target: {f.target} is not a satellite id (0..{n - 1})")
            if f.peer is not None and f.peer >= n:
                raise ValueError(f"faults.{idx}.peer: {f.peer} is not a satellite id (0..{n - 1})")
            if f.action in RADIO_FAULTS and not self.links.enabled:
                raise ValueError(f"faults.{idx}.action: {f.action} acts on the radio's link model, which this scenario does "
                                 "not run (links.enabled: false)")
        return self
