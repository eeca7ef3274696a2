"""``swarm``: the command line of the cooperative-localisation emulator.

Every command that takes a SCENARIO accepts ``--set dotted.key=value`` (repeatable) to
override any field, e.g. ``--set n_sats=6 --set filter.gate.enabled=false``. The commands
are thin: each parses its options, calls the library (:mod:`swarm.simulation`,
:mod:`swarm.studies`, :mod:`swarm.supervise`, :mod:`swarm.record`, :mod:`swarm.bench`)
and prints what it returns.
"""

from __future__ import annotations

# Each module registers its commands; `swarm --help` lists them in this order.
# isort: off
from swarm.cli import simulate, distributed, chaos, live, conformance, vision, bench, scenario  # noqa: F401
# isort: on
from swarm.cli.common import app

__all__ = ["app", "main", "optional_values"]


def main() -> None:  # console-script entry point
    import sys

    sys.argv[1:] = optional_values(sys.argv[1:])
    app()


#: Options whose value may be left out (``swarm run --live`` = ``--live 127.0.0.1:8765``):
#: the option → (what a given value looks like, the value when none is given).
OPTIONAL_VALUES = {"--live": (r"\[?[\w.:-]*\]?:\d+", "127.0.0.1:8765")}


def optional_values(args: list[str]) -> list[str]:
    """``args`` with the default value put after each option of :data:`OPTIONAL_VALUES`
    given without one (Typer has no optional option values)."""
    import re

    out = []
    for i, a in enumerate(args):
        out.append(a)
        spec = OPTIONAL_VALUES.get(a)
        if spec is not None and (i + 1 >= len(args) or not re.fullmatch(spec[0], args[i + 1])):
            out.append(spec[1])
    return out


if __name__ == "__main__":
    main()
