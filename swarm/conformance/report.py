"""The kit's verdicts: one line per clause, ``conformance.json``, the exit status."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from swarm.conformance.clauses import CLAUSES, CONTRACT_VERSION, SCHEMA, clause

__all__ = ["Verdict", "Report", "PASS", "FAIL", "NOT_CLAIMED", "NOT_RUN", "ERROR"]

PASS, FAIL, NOT_CLAIMED, NOT_RUN, ERROR = "pass", "fail", "not claimed", "not run", "error"


@dataclass
class Verdict:
    id: str
    status: str
    evidence: str
    case: str = ""
    title: str = ""
    mandatory: bool = True
    claim: str | None = None

    @classmethod
    def of(cls, cid: str, status: str, evidence: str, case: str = "") -> Verdict:
        c = clause(cid)
        return cls(cid, status, evidence, case or c.case, c.title, c.mandatory, c.claim)

    @property
    def failed(self) -> bool:
        """A failure that makes the kit's exit status non-zero: a mandatory clause, or a
        claimed optional one, that failed (or whose case could not be run)."""
        return self.status in (FAIL, ERROR)

    def line(self) -> str:
        kind = "" if self.mandatory else f" (claim {self.claim})"
        return f"{self.id:<4} {self.status.upper():<11} {self.title}{kind} [{self.case}]: {self.evidence}"


@dataclass
class Report:
    agent: str
    sat: int
    claims: list[str]
    scenario: dict
    verdicts: list[Verdict] = field(default_factory=list)
    cases: dict[str, dict] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def passed(self) -> bool:
        return not any(v.failed for v in self.verdicts)

    @property
    def complete(self) -> bool:
        return all(v.status != NOT_RUN for v in self.verdicts)

    @property
    def exit_code(self) -> int:
        return 0 if self.passed else 1

    def lines(self) -> list[str]:
        order = {c.id: i for i, c in enumerate(CLAUSES)}
        out = [v.line() for v in sorted(self.verdicts, key=lambda v: order[v.id])]
        failed = [v.id for v in self.verdicts if v.failed]
        mand = [v for v in self.verdicts if v.mandatory]
        ok = sum(v.status == PASS for v in mand)
        verdict = "CONFORMS" if not failed else f"DOES NOT CONFORM (failed: {', '.join(failed)})"
        partial = "" if self.complete else " (partial: some cases not run)"
        out.append(f"agent contract {CONTRACT_VERSION} ({SCHEMA}), satellite {self.sat}: {verdict}{partial}; "
                   f"{ok}/{len(mand)} mandatory clauses pass; {len(self.cases)} cases in {self.wall_s:.0f} s")
        return out

    def to_json(self) -> dict:
        return {
            "contract_version": CONTRACT_VERSION,
            "schema": SCHEMA,
            "agent": self.agent,
            "sat": self.sat,
            "claims": self.claims,
            "passed": self.passed,
            "complete": self.complete,
            "wall_s": round(self.wall_s, 1),
            "clauses": [asdict(v) for v in self.verdicts],
            "cases": self.cases,
            "scenario": self.scenario,
        }

    def write(self, path: Path) -> Path:
        path.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        return path
