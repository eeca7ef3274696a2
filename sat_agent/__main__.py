"""python -m sat_agent --id N --scenario FILE --run RUN [--restart] [bus flags]"""

from __future__ import annotations

import dataclasses
import sys


def main(argv=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()  # first, before numpy loads: the project's BLAS kernels and threads
    from swarmrt.node import bus_config_from_args, load_role_scenario, role_arg_parser, serve, setup_logging

    p = role_arg_parser("sat_agent: one satellite's measurements and its estimator (the scenario's estimator.kind)")
    p.add_argument("--id", required=True, help="this satellite's id (0..n-1), or 'auto' to be given one by the world")
    p.add_argument("--restart", action="store_true", help="initialise from a live peer's estimate")
    a = p.parse_args(argv)
    sc = load_role_scenario(a.scenario, a.sets)
    from .node import Agent, claim_id

    bus = bus_config_from_args(a, sc)
    restart = a.restart
    if a.id == "auto":
        setup_logging("agent-?", a.verbose)
        sat, running, password = claim_id(sc, a.run, bus)
        restart = restart or running
        if password and sc.emulator.security:
            # Reconnect as agent-<sat>: the claimant's credential may do nothing but claim.
            from swarmrt.security import Credential

            base = bus.identity()
            bus = dataclasses.replace(bus, credential_file=None,
                                      credential=base.with_identity(f"agent-{sat}", password) if base is not None
                                      else Credential(f"agent-{sat}", password))
    else:
        try:
            sat = int(a.id)
        except ValueError:
            p.error(f"--id {a.id!r}: expected a satellite number or 'auto'")
    setup_logging(f"agent-{sat}", a.verbose)
    # Our final estimate may still be on its way: once done, leave when the recorder has it.
    return serve(Agent(sc, sat, a.run, bus, restart=restart), linger_s=sc.emulator.shutdown_linger_s + 5.0)


if __name__ == "__main__":
    sys.exit(main())
