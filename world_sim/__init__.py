"""The world: truth, time, sensors and cameras of the swarm (see :mod:`world_sim.node`)."""
