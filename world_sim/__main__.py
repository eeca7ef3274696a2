"""python -m world_sim --scenario FILE --run RUN [bus flags]"""

from __future__ import annotations

import os
import sys


def main(argv=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()  # first, before numpy loads: the project's BLAS kernels and threads
    from swarmrt.node import bus_config_from_args, load_role_scenario, role_arg_parser, serve, setup_logging

    p = role_arg_parser("world_sim: truth, time, sensors and cameras of the swarm")
    p.add_argument("--no-recorder", action="store_true", help="do not wait for a recorder at startup")
    p.add_argument("--agent-passwords", default=os.environ.get("SWARM_AGENT_PASSWORDS") or None,
                   help="agents.json of `swarm keys`: give each --id auto agent its satellite's credential (env SWARM_AGENT_PASSWORDS)")
    a = p.parse_args(argv)
    setup_logging("world", a.verbose)
    sc = load_role_scenario(a.scenario, a.sets)
    from .node import World

    passwords = None
    if a.agent_passwords and sc.emulator.security:
        from swarmrt.security import load_agent_passwords

        passwords = load_agent_passwords(a.agent_passwords)
    w = World(sc, a.run, bus_config_from_args(a, sc), expect_recorder=not a.no_recorder, agent_passwords=passwords)
    # The "done" clock may still be on its way: leave once the recorder has finished.
    return serve(w, linger_s=sc.emulator.shutdown_linger_s + 5.0)


if __name__ == "__main__":
    sys.exit(main())
