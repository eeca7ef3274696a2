"""Chaos campaigns (``swarm chaos``): a seeded schedule of faults run against a swarm, then
named invariants checked over the finished run folder. This package owns the campaign
logic; the command itself (``swarm/cli/chaos.py``) only parses, calls it and prints.

- :mod:`swarm.chaos.campaign` — bus-free: draws the seeded schedule (episodes, their rules
  and kinds), writes it into a scenario, checks a finished run (:func:`~swarm.chaos.campaign.check_run`:
  the invariants, recovery times) and the tables of what fired. A local campaign, or one
  over a Ray cluster, is then run on the path of ``swarm run`` (:func:`swarm.api.run`).
- :mod:`swarm.chaos.compose` — a campaign under ``docker compose`` (``swarm chaos
  --compose``): runs the compose swarm and sends each command of the schedule as ``swarm
  fault --compose`` does, at its step.

Importing the package loads neither module.
"""
