"""Agents that break the contract on purpose, for tests/test_conformance.py: a kit that
cannot fail is worthless.

``python tests/broken_agent.py mute K``: the Python agent started from the contract's
environment (``sat_agent.from_env``) that joins, flies steps 0..K-1, then stops answering:
it keeps its session and its token, hears everything, and publishes nothing until the run
is over (C5, C6)."""

from __future__ import annotations

import sys


def mute_from(k_mute: int) -> None:
    from sat_agent.protocol import AgentProtocol
    from swarmrt.protocol import Wait

    step = AgentProtocol.step

    def silent_step(self, k):
        if k < k_mute:
            yield from step(self, k)
            return
        self.last_step = k
        yield Wait(lambda: self.done, 1e9)  # alive and listening, silent to the end

    AgentProtocol.step = silent_step  # type: ignore[method-assign]


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] != "mute":
        sys.stderr.write("usage: broken_agent.py mute K\n")
        return 2
    mute_from(int(argv[1]))
    from sat_agent.from_env import main as agent_main

    return agent_main()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
