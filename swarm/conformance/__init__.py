"""The conformance kit of the agent contract (``docs/agent-contract.md``).

``swarm conformance --agent 'COMMAND'`` runs COMMAND as satellite i of small local swarms
(:mod:`.kit`: one case per situation the contract speaks of), reads what each run
recorded (:mod:`.evidence`), judges every clause (:mod:`.judge`) and reports one line per
clause with its evidence, and ``conformance.json`` (:mod:`.report`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from swarm.conformance.clauses import CLAIMS, CLAUSES, CONTRACT_VERSION, SCHEMA
from swarm.conformance.kit import CASE_NAMES, CASES, CaseRun, Kit, kit_scenario
from swarm.conformance.report import Report

__all__ = ["run_conformance", "CLAUSES", "CLAIMS", "CASE_NAMES", "CONTRACT_VERSION", "SCHEMA"]


def run_conformance(command: str, out: Path, sat: int = 1, scenario=None, claims=(), cases=None, log=print) -> Report:
    """Run the kit (every case, or those named in ``cases``; the clean run always, as the
    reference) and return its report, also written to ``out/conformance.json``.
    ValueError for a scenario or a claim the kit cannot use."""
    from swarm.conformance.judge import judge_all

    unknown = sorted(set(claims) - set(CLAIMS))
    if unknown:
        raise ValueError(f"--claims: unknown {', '.join(unknown)} (known: {', '.join(CLAIMS)})")
    names = list(CASE_NAMES) if not cases else ["clean", *[c for c in cases if c != "clean"]]
    bad = [c for c in names if c not in CASE_NAMES]
    if bad:
        raise ValueError(f"--cases: unknown {', '.join(bad)} (known: {', '.join(CASE_NAMES)})")
    base = kit_scenario(scenario, sat, command)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kit = Kit(command, sat, base, out, set(claims), log=log)
    t0 = time.monotonic()
    # The supervisors' own bus node (LocalSwarm) logs what it refuses and the bus gaps it
    # sees: the kit provokes both, so they go to a file, not the report.
    sup = logging.getLogger("supervisor")
    handler = logging.FileHandler(out / "supervisor.log", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    sup.addHandler(handler)
    sup.propagate = False
    try:
        for case in CASES:
            if case.name not in names:
                continue
            clean = kit.runs.get("clean")
            if clean is not None and case.name != "clean" and (clean.error or not _joined(clean)):
                # Every case would wait emulator.startup_timeout_s for it, to learn nothing more.
                kit.runs[case.name] = CaseRun(case.name, out / case.name, error="skipped: the agent never joined the clean run "
                                              f"(see {clean.out / 'logs' / f'agent-{sat}.log'})")
                continue
            log(f"case {case.name}: {case.what} ...")
            run = kit.run_case(case)
            log(f"case {case.name}: {run.wall_s:.0f} s; world {run.world_code}, satellite {sat}'s agent {run.agent_codes}"
                + (f"; ERROR {run.error}" if run.error else ""))
    finally:
        sup.removeHandler(handler)
        sup.propagate = True
        handler.close()
    report = Report(agent=command, sat=sat, claims=sorted(claims), scenario=base.model_dump(mode="json"),
                    verdicts=judge_all(kit), cases={n: r.summary() for n, r in kit.runs.items()},
                    wall_s=time.monotonic() - t0)
    report.write(out / "conformance.json")
    return report


def _joined(run: CaseRun) -> bool:
    """Whether the agent under test was on the bus at all (its token or a message of its)."""
    ev = run.ev
    return ev is not None and (bool(ev.token_events()) or bool(ev.from_me))
