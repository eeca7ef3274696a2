"""Start an agent of another language with what the agent contract gives it, then become it.

python -m swarm.supervise.exec_agent --id 3 --run compose --scenario /scenarios/demo.yaml \\
    --credential /run/secrets/agent-3.json [--restart] -- swarm-rust-agent [ARGS...]

What ``swarm run`` does for a satellite of ``emulator.agent_commands``
(:func:`swarm.supervise.launch.foreign_agent_env`, docs/agent-contract.md clause 1), for a
process that is not started by ``swarm run``: a compose service (compose.rust.yaml) or a
satellite on another host. The scenario is resolved as every role resolves it (the file,
then ``SWARM_SET`` and ``--set``), written as JSON to an anonymous in-memory file the agent
inherits (``SWARM_SCENARIO_JSON=/proc/self/fd/N``: nothing on disk, so nothing is left behind
when the agent ends, whatever ends it; a temporary folder outlived every agent, since after
``exec`` no one is left to remove it), and the command is executed in this process's place
(``exec``: its signals and exit status are the agent's own; under compose, tini is its parent).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def main(argv=None) -> int:
    from swarmrt.node import bus_config_from_args, load_role_scenario, role_arg_parser

    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv or argv.index("--") == len(argv) - 1:
        print("exec_agent: give the agent's command after `--` (e.g. -- swarm-rust-agent)", file=sys.stderr)
        return 2
    cut = argv.index("--")
    mine, command = argv[:cut], argv[cut + 1:]
    p = role_arg_parser("start an agent of another language with the agent contract's environment, then exec it")
    p.add_argument("--id", type=int, required=True, help="its satellite (one of the scenario's emulator.agent_commands)")
    p.add_argument("--restart", action="store_true", help="SWARM_RESTART=1: it joins a running swarm (a restart)")
    a = p.parse_args(mine)
    sc = load_role_scenario(a.scenario, a.sets)
    if not 0 <= a.id < sc.n_sats:
        p.error(f"--id {a.id}: not a satellite of this scenario (0..{sc.n_sats - 1})")
    if a.id not in sc.emulator.agent_commands:
        # The world hands --id auto claimants every satellite not listed there: one of them
        # would fly this satellite too.
        p.error(f"--id {a.id}: not in the scenario's emulator.agent_commands ({dict(sc.emulator.agent_commands) or 'empty'}): "
                f"add emulator.agent_commands.{a.id}=<name> to every role's SWARM_SET so the world keeps it for this agent")
    from .launch import foreign_agent_env, write_scenario_json

    fd = os.memfd_create("swarm-scenario.json", 0)  # (no MFD_CLOEXEC: the agent inherits it)
    os.set_inheritable(fd, True)
    path = Path(f"/proc/self/fd/{fd}")  # the same path in the agent: exec keeps the pid and the fd
    write_scenario_json(sc, path)
    env = dict(os.environ, **foreign_agent_env(sc, a.id, a.run, bus_config_from_args(a, sc), None, a.restart, scenario_json=path))
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execvpe(command[0], command, env)
    except OSError as exc:
        print(f"exec_agent: cannot run {command[0]!r}: {exc}", file=sys.stderr)
        return 127
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main())
