"""python -m selector --scenario FILE --run RUN [bus flags]"""

from __future__ import annotations

import sys

from swarm.node import RunBroken, bus_config_from_args, install_term_handler, load_role_scenario, role_arg_parser, setup_logging


def main(argv=None) -> int:
    a = role_arg_parser("selector: chooses the relative measurements of the next step").parse_args(argv)
    setup_logging("selector", a.verbose)
    sc = load_role_scenario(a.scenario, a.sets)
    from .node import Selector

    s = Selector(sc, a.run, bus_config_from_args(a, sc))
    install_term_handler(s.stop)
    try:
        s.run_loop()
    except RunBroken as exc:
        s.log.error("%s; exiting", exc)
        return exc.exit_code
    finally:
        s.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
