"""Every message on the bus and every key expression: the one import surface of the bus's
message code (``from swarmrt.bus import messages as M``; every name in ``__all__`` is stable),
over five modules that each own one concern:

- :mod:`.wire`: the generated classes, :data:`MODELS`, the schema version, the limits, the errors;
- :mod:`.codec`: :func:`encode`, :func:`decode` and the protobuf helpers;
- :mod:`.validation`: what the schema cannot say (:func:`validate`), the shallow readings, the
  memo of validated arrays the conversions reuse;
- :mod:`.keys`: key expressions, :func:`parse_key`, :func:`check_key`, :func:`grants`;
- :mod:`.accounting`: the CPU time spent on messages (:func:`counted`).

A bus sample is opened with :func:`swarmrt.bus.receive.receive` (key, run, decode, key check).

Messages are Protocol Buffers, schema version 1: ``proto/swarm/v1/*.proto`` is the single
source of truth (one file per message family; ``proto/README.md`` gives the conventions
and the evolution rules), and the classes here are the code generated from it
(``swarmrt/bus/v1/*_pb2.py``, made by ``scripts/gen_proto.py``). Any language with a protobuf
code generator reads them; the recorder embeds the schemas in the MCAP file.

Fields 1–5 of every message are the header: ``schema_version``, ``run``, ``sender``,
``k`` (step), ``t_s`` (simulation time). Units and frames are in every field name. Arrays
are packed ``repeated double`` (per-satellite rows concatenated, row-major) and
covariances :class:`Matrix` values (``shape`` + ``data``); both are little-endian
float64 on the wire, so values round-trip bit for bit.

:func:`decode` checks what a schema cannot: the schema version, bounded payload size,
finite numbers, unit quaternions (``|‖q‖ − 1| ≤ QUAT_TOL``), symmetric positive-definite
covariances, array lengths that match their shapes, ids within ``MAX_SAT_ID``, allowed
values of the string enumerations. :func:`check_key` checks a message against the key it
came on (the satellite in the key, the sender). A failure raises :class:`MessageError`
naming the problem; the receiving process counts it, logs it and carries on.

Generated classes are built with keywords and read by attribute, as before
(``Clock(run=..., k=3)``, ``msg.k``); :func:`replace` and :func:`as_dict` stand in for
what pydantic gave (``model_copy(update=...)``, ``model_dump()``). Repeated fields read
as sequences (``np.asarray(msg.q_BI)`` is a fast copy); an optional field that is unset
reads as its zero value, ``msg.HasField(name)`` (or :func:`opt`) tells.

Key space (one run id per swarm, so swarms can share a router)::

    swarm/<run>/clock                world → all           Clock (and queryable: the last two steps' clocks)
    swarm/<run>/recorded             recorder → world      Recorded (the last step whose clock it has taken in)
    swarm/<run>/sat/<i>/sensors      world → agent i       Sensors
    swarm/<run>/sat/<i>/cam          world → agent i       CameraOutput
    swarm/<run>/sat/<i>/img          world → agent i       Images  (rendered scenarios)
    swarm/<run>/meas/<i>             agent i → the radio   MeasBatch (the world, the recorder; with the
                                                           selector or a tool that asks for them)
    swarm/<run>/batches              world → all agents    StepBatches (links.enabled false, an estimator whose
                                                           radio is "all": every batch of a step, one message)
    swarm/<run>/batches/<i>          world → agent i       StepBatches (links.enabled false, radio "graph": the
                                                           batches of i's graph neighbours, its radio's delivery)
    swarm/<run>/est/<i>              agent i → all         Estimate
    swarm/<run>/cov/<i>              agent i (queryable)   FullEstimate
    swarm/<run>/init/<i>             world (queryable)     FullEstimate (the prior)
    swarm/<run>/claim/<token>        world (queryable)     Claim (a satellite id for --id auto)
    swarm/<run>/select               selector → all        Select
    swarm/<run>/fault                CLI / world → all     Fault (commands: the CLI's, the world's schedule)
    swarm/<run>/fault/<reporter>     that role → all       Fault (what <reporter> carried out: done / failed)
    swarm/<run>/health/<i>           agent i → all         Health (and the world, queryable on health/*: the last two steps')
    swarm/<run>/truth                world → recorder      Truth   (agents never subscribe)
    swarm/<run>/rx/<i>               world → agent i       Delivery (links.enabled: what the radio delivered)
    swarm/<run>/links                world → recorder      LinkStats (links.enabled: per-link counters)
    swarm/<run>/rejoin/<i>[/<j>/<B>] world (queryable)     RejoinFate (links.enabled: a restart's state transfer)
    swarm/<run>/alive/<role>/<id>    liveliness tokens

Who may use which key is defined here too (:func:`grants`): the router's access rules are
generated from it (:mod:`swarmrt.security`), and :func:`check_key` holds every receiver to
the same table whatever the router let through.
"""

from __future__ import annotations

from swarmcore.scenario import FAULT_ACTIONS
from swarmrt.bus.accounting import codec_cpu_ms, counted
from swarmrt.bus.codec import as_dict, decode, encode, file_descriptor_set, opt, pixels, replace
from swarmrt.bus.keys import IDENTITIES, Grants, Keys, check_key, grants, parse_key
from swarmrt.bus.validation import _LINK_COUNTERS as _LINK_COUNTERS
from swarmrt.bus.validation import (
    MAX_OPAQUE_BYTES,
    SHALLOW_KINDS,
    batch_arrays,
    check_estimator_message,
    detection_arrays,
    forget_arrays,
    prepare,
    step_batch_arrays,
    validate,
)
from swarmrt.bus.validation import _Memo as _Memo
from swarmrt.bus.wire import (
    MAX_PAYLOAD_BYTES,
    MAX_SAT_ID,
    MODELS,
    QUAT_TOL,
    SCHEMA_VERSION,
    BusGap,
    CameraOutput,
    CameraView,
    CiState,
    Claim,
    Clock,
    Delivered,
    Delivery,
    Detection,
    Estimate,
    EstimatorMessage,
    Fault,
    FullEstimate,
    Header,
    Health,
    Images,
    KeyMismatch,
    Latency,
    LinkStats,
    Liveliness,
    Malformed,
    Matrix,
    MeasBatch,
    MessageError,
    PairwiseState,
    Recorded,
    RejoinFate,
    Select,
    Sensors,
    StepBatches,
    Truth,
)
from swarmrt.bus.wire import MAX_PAYLOAD_DEFAULT as MAX_PAYLOAD_DEFAULT
from swarmrt.bus.wire import SYM_TOL as SYM_TOL

__all__ = [
    "SCHEMA_VERSION",
    "MAX_SAT_ID",
    "QUAT_TOL",
    "MAX_PAYLOAD_BYTES",
    "SHALLOW_KINDS",
    "MessageError",
    "KeyMismatch",
    "Grants",
    "grants",
    "IDENTITIES",
    "Header",
    "Matrix",
    "Clock",
    "Recorded",
    "Sensors",
    "Detection",
    "CameraOutput",
    "MeasBatch",
    "StepBatches",
    "Estimate",
    "FullEstimate",
    "EstimatorMessage",
    "CiState",
    "PairwiseState",
    "MAX_OPAQUE_BYTES",
    "Select",
    "Fault",
    "Health",
    "Truth",
    "Claim",
    "Images",
    "CameraView",
    "Delivery",
    "Delivered",
    "Latency",
    "LinkStats",
    "RejoinFate",
    "Liveliness",
    "BusGap",
    "Malformed",
    "Keys",
    "MODELS",
    "FAULT_ACTIONS",
    "encode",
    "decode",
    "validate",
    "check_estimator_message",
    "check_key",
    "parse_key",
    "replace",
    "as_dict",
    "opt",
    "pixels",
    "batch_arrays",
    "step_batch_arrays",
    "detection_arrays",
    "forget_arrays",
    "prepare",
    "file_descriptor_set",
    "codec_cpu_ms",
    "counted",
]
