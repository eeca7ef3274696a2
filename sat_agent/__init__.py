"""One satellite's agent: measurement pipeline and its estimator (full, ci, pairwise or a plug-in; see :mod:`sat_agent.node`)."""
