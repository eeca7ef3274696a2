"""python -m selector --scenario FILE --run RUN [bus flags]"""

from __future__ import annotations

import sys


def main(argv=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()  # first, before numpy loads: the project's BLAS kernels and threads
    from swarmrt.node import bus_config_from_args, load_role_scenario, role_arg_parser, serve, setup_logging

    a = role_arg_parser("selector: chooses the relative measurements of the next step").parse_args(argv)
    setup_logging("selector", a.verbose)
    sc = load_role_scenario(a.scenario, a.sets)
    from .node import Selector

    return serve(Selector(sc, a.run, bus_config_from_args(a, sc)))


if __name__ == "__main__":
    sys.exit(main())
