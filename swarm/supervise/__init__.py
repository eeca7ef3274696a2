"""Supervision: ``swarm run``'s process tree (launch, lifeline), the Zenoh router, faults carried
out on processes, containers and networks (netem and its fallback), compose's keys service."""
