"""One satellite's agent: measurement pipeline and full-swarm filter (see :mod:`sat_agent.node`)."""
