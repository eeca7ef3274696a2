"""The clauses of the agent contract (``docs/agent-contract.md``), as the kit checks them.

The numbering, titles and the mandatory/optional split are the document's; a test
(``tests/test_conformance_unit.py``) holds the two together.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CONTRACT_VERSION", "SCHEMA", "Clause", "CLAUSES", "CLAIMS", "clause"]

#: The contract's own version (``docs/agent-contract.md``): major changes when a clause
#: asks more of an agent, minor when a clause is added as optional or worded better.
CONTRACT_VERSION = "1.0"
#: The wire schema the contract is written against (``proto/swarm/v1``, ``schema_version`` 1).
SCHEMA = "swarm.v1"


@dataclass(frozen=True)
class Clause:
    id: str  # "C1"
    title: str
    claim: str | None = None  # None: mandatory; else the claim that makes it apply (optional)
    case: str = ""  # the kit's case that judges it

    @property
    def mandatory(self) -> bool:
        return self.claim is None


CLAUSES: tuple[Clause, ...] = (
    Clause("C1", "identity: the environment, the credential, one client session", case="clean"),
    Clause("C2", "liveliness token alive/agent/<i> for its whole life", case="clean"),
    Clause("C3", "ready before step 0: a prior estimate on est/<i>", case="clean"),
    Clause("C4", "key space: puts only on its own keys", case="clean"),
    Clause("C5", "every step: meas/<i>, then est/<i> (posterior) and health/<i>", case="clean"),
    Clause("C6", "in time: before the world's step timeout", case="clean"),
    Clause("C7", "valid messages (swarm.v1, checked as every receiver does)", case="clean"),
    Clause("C8", "end of run: leaves by itself after the done clock, exit 0", case="clean"),
    Clause("C9", "missing radio deliveries: goes on without them", case="faults"),
    Clause("C10", "late radio deliveries (links): rx/<i>, goes on", case="links"),
    Clause("C11", "camera faults: no detections from a camera that is off", case="faults"),
    Clause("C12", "drop fault: the seeded losses from the step its report names", case="faults"),
    Clause("C13", "SIGKILL and restart with SWARM_RESTART=1", case="restart"),
    Clause("C14", "malformed input: dropped, never fatal, numbers unchanged", case="inputs"),
    Clause("C15", "forged input (key mismatch): dropped, numbers unchanged", case="inputs"),
    Clause("C16", "refused messages counted in health/<i>", case="inputs"),
    Clause("C17", "bus loss and return: resend the step, same numbers", case="router"),
    Clause("C18", "bus lost for good: exit 3 after emulator.bus_lost_after_s", case="bus-lost"),
    Clause("C19", "world gone before the end: exit 4", case="world-gone"),
    Clause("C20", "SIGTERM: clean exit 0, nothing left behind", case="sigterm"),
    Clause("C21", "warm rejoin: serves cov/<i>, restarts from a peer's estimate", claim="warm-rejoin", case="clean+restart"),
    Clause("C22", "late batches applied at their own step (replay) and counted", claim="late-replay", case="links"),
)

#: Claims an agent may make (``--claims``), each the optional clause it turns on.
CLAIMS: dict[str, str] = {c.claim: c.id for c in CLAUSES if c.claim is not None}


def clause(cid: str) -> Clause:
    for c in CLAUSES:
        if c.id == cid:
            return c
    raise KeyError(cid)
