"""What the wire carries: the generated message classes (``swarmrt/bus/v1/``), the kind of
each (:data:`MODELS`), the schema version, the limits every receiver applies (payload
size, satellite ids, tolerances) and the errors a refused message raises. The bottom of
the bus package: it imports only the generated code."""

from __future__ import annotations

import re

from google.protobuf.message import Message

from swarmrt.bus.v1.claim_pb2 import Claim
from swarmrt.bus.v1.clock_pb2 import Clock, Recorded
from swarmrt.bus.v1.common_pb2 import Header, Matrix
from swarmrt.bus.v1.estimate_pb2 import Estimate, FullEstimate
from swarmrt.bus.v1.estimators_pb2 import CiState, EstimatorMessage, PairwiseState
from swarmrt.bus.v1.fault_pb2 import Fault
from swarmrt.bus.v1.health_pb2 import Health
from swarmrt.bus.v1.images_pb2 import CameraView, Images
from swarmrt.bus.v1.links_pb2 import Delivered, Delivery, Latency, LinkStats, RejoinFate
from swarmrt.bus.v1.measurements_pb2 import MeasBatch, StepBatches
from swarmrt.bus.v1.recording_pb2 import BusGap, Liveliness, Malformed
from swarmrt.bus.v1.selection_pb2 import Select
from swarmrt.bus.v1.sensors_pb2 import CameraOutput, Detection, Sensors
from swarmrt.bus.v1.truth_pb2 import Truth

__all__ = [
    "Claim", "Clock", "Recorded", "Header", "Matrix", "Estimate", "FullEstimate", "CiState", "EstimatorMessage", "PairwiseState", "Fault",
    "Health", "CameraView", "Images", "Delivered", "Delivery", "Latency", "LinkStats", "RejoinFate", "MeasBatch", "StepBatches",
    "BusGap", "Liveliness", "Malformed", "Select", "CameraOutput", "Detection", "Sensors", "Truth", "MODELS", "SCHEMA_VERSION",
    "MAX_SAT_ID", "QUAT_TOL", "SYM_TOL", "MAX_PAYLOAD_BYTES", "MAX_PAYLOAD_DEFAULT", "RUN_ID_RE", "MessageError", "KeyMismatch",
]

SCHEMA_VERSION = 1
MAX_SAT_ID = 10_000
QUAT_TOL = 1e-6  # |‖q‖ − 1| a unit quaternion may show (checked as |‖q‖² − 1| ≤ 2e-6; ours: ~1e-16)
SYM_TOL = 1e-9  # |A − Aᵀ| relative to max |A| a covariance may show (round-off only)
MiB = 1 << 20
MAX_PAYLOAD_BYTES = {"img": 64 * MiB, "full_est": 64 * MiB, "batches": 64 * MiB}
RUN_ID_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # a run id: what a key segment and a Zenoh key may hold
MAX_PAYLOAD_DEFAULT = 8 * MiB  # every other kind (an estimate of 100 satellites is ~60 KB)


class MessageError(ValueError):
    """A payload that is not a valid message of the expected kind."""


class KeyMismatch(MessageError):
    """A valid message on a key its sender, observer or satellite field says it may not
    use (someone speaking for another): dropped and counted apart from other malformed
    messages, whatever the router let through."""


MODELS: dict[str, type[Message]] = {
    "clock": Clock,
    "sensors": Sensors,
    "cam": CameraOutput,
    "meas": MeasBatch,
    "batches": StepBatches,
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
    "recorded": Recorded,
}
