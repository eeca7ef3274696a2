"""python -m world_sim --scenario FILE --run RUN [bus flags]"""

from __future__ import annotations

import os
import sys

from swarm.node import RunBroken, bus_config_from_args, install_term_handler, load_role_scenario, role_arg_parser, setup_logging


def main(argv=None) -> int:
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
        from swarm.security import load_agent_passwords

        passwords = load_agent_passwords(a.agent_passwords)
    w = World(sc, a.run, bus_config_from_args(a, sc), expect_recorder=not a.no_recorder, agent_passwords=passwords)
    install_term_handler(w.stop)
    try:
        w.run_steps()
        if not w.stop.is_set():
            # The "done" clock may still be on its way: leave once the recorder has finished.
            w.linger_while_recording(sc.emulator.shutdown_linger_s + 5.0)
    except RunBroken as exc:
        w.log.error("%s; exiting", exc)
        return exc.exit_code
    finally:
        w.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
