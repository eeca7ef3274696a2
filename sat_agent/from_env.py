"""``python -m sat_agent.from_env``: the Python agent started the way a program of any
language is (``emulator.agent_commands``, ``swarm run --agent I=COMMAND``,
``swarm conformance --agent COMMAND``).

It reads nothing but the environment of ``docs/agent-contract.md`` clause C1 and maps it
to ``sat_agent``'s own arguments; it is also the reference for how an agent of another
language reads its start-up:

================================  =====================================================
``SWARM_SAT_ID``                  this satellite's id (``--id``)
``SWARM_RUN``                     the run id, part of every key (``--run``)
``SWARM_CONNECT``                 the routers' endpoints, comma-separated (``--connect``,
                                  client mode)
``SWARM_CREDENTIAL``              the credential file (``{"user", "password"[, "ca"]}``;
                                  empty when security is off) (``--credential``)
``SWARM_SCENARIO_JSON``           the resolved scenario as JSON (with ``derived``:
                                  numbers the scenario implies)
``SWARM_RESTART``                 ``1``: the run is under way, rejoin (``--restart``)
================================  =====================================================

Exit status: that of ``python -m sat_agent`` (0, 3 bus lost, 4 world gone, 2 a bad
environment).
"""

from __future__ import annotations

import json
import os
import sys

__all__ = ["main", "environment"]

ENV = ("SWARM_SAT_ID", "SWARM_RUN", "SWARM_CONNECT", "SWARM_CREDENTIAL", "SWARM_SCENARIO_JSON", "SWARM_RESTART")


def environment(env=None) -> dict[str, str]:
    """The contract's variables (C1); SystemExit(2) naming the first missing one."""
    env = os.environ if env is None else env
    missing = [v for v in ENV if v not in env and v != "SWARM_CREDENTIAL"]
    if missing:
        sys.stderr.write(f"sat_agent.from_env: {missing[0]} is not set (docs/agent-contract.md, C1)\n")
        raise SystemExit(2)
    return {v: env.get(v, "") for v in ENV}


def main(env=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()  # first, before numpy loads (as python -m sat_agent)
    e = environment(env)
    from swarmrt.bus.session import BusConfig
    from swarmrt.node import serve, setup_logging
    from swarmrt.scenario_files import ScenarioError, scenario_from_dict

    try:
        sat = int(e["SWARM_SAT_ID"])
    except ValueError:
        sys.stderr.write(f"sat_agent.from_env: SWARM_SAT_ID={e['SWARM_SAT_ID']!r} is not a satellite id\n")
        return 2
    setup_logging(f"agent-{sat}")
    try:
        with open(e["SWARM_SCENARIO_JSON"]) as f:
            doc = json.load(f)
        doc.pop("derived", None)  # implied values, for agents that do not compute them
        sc = scenario_from_dict(doc, e["SWARM_SCENARIO_JSON"])
    except (OSError, ValueError, ScenarioError) as exc:
        sys.stderr.write(f"sat_agent.from_env: SWARM_SCENARIO_JSON: {exc}\n")
        return 2
    connect = [x for x in e["SWARM_CONNECT"].split(",") if x]
    cred = e["SWARM_CREDENTIAL"] or None
    if not sc.emulator.security:
        cred = None  # a router without security refuses a session that offers a credential
    bus = BusConfig(mode="client", connect=connect, credential_file=cred)
    from .node import Agent

    return serve(Agent(sc, sat, e["SWARM_RUN"], bus, restart=e["SWARM_RESTART"] == "1"),
                 linger_s=sc.emulator.shutdown_linger_s + 5.0)


if __name__ == "__main__":
    sys.exit(main())
